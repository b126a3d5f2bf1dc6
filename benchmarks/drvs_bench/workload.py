"""The robot's side of the paper benchmark, run as its own process so its CPU is its own.

drvs: single-shot requests at 30 Hz through DRVS (with --moving, the region slides and the filter
alternates every request; with --fuse, fused single shots; with --track, one continuous fused
track at the same rate, the counterpart of a video stream). raw / jpeg: both cameras stream every
frame to the robot over a plain grpc.aio channel (gRPC's defaults), and the robot runs the same HSV
detection on each frame itself.
With --filter people, the same with OpenCV's HOG people detector (drvs.detectors.people) instead:
the DRVS robot asks for `people`, the streaming robot asks each camera for frames at the request
rate (--max-fps) and runs the detector the cameras run on every frame it gets.

Each mode counts the work it did, so the parent can check that it did what it was meant to
(`cpu_s` is `time.process_time()`: user + system time of this whole process, all its threads).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import statistics
import time
from collections.abc import Callable, Coroutine
from pathlib import Path
from typing import Any, TypeVar

import cv2
import numpy as np
from grpc import aio
from shapely.geometry import box

from drvs.core.errors import DrvsError
from drvs.core.filters import object_type
from drvs.core.geometry import FieldOfView
from drvs.core.homography_file import load_homography
from drvs.core.model import Snapshot
from drvs.detectors import CameraView, Detector, Frame, FrameAnalysis, HsvDetector, select
from drvs.detectors.people import PeopleDetector
from drvs.robot import DetectionResult, DrvsClient
from drvs.v1 import stream_pb2, stream_pb2_grpc

from .common import BOTH_REGION, FPS, IMAGE_SIZE, YELLOW

#: The scene's other colour (scene.yaml: one blue object in each camera's view).
BLUE = "hsv_100120080130255255"
#: The moving variant: a band across both cameras' views slides this far along y each request ...
MOVING_STEP_M = 0.05
#: ... over this range (cameras see about 1 to 6 m in front of them), then starts again ...
MOVING_RANGE_M = 4.0
#: ... and each pass is this much further along x, so no region repeats within a run.
MOVING_PASS_SHIFT_M = 0.01

_R = TypeVar("_R")


def moving_request(i: int) -> tuple[str, tuple[float, float, float, float]]:
    """The i-th request of the moving variant: a robot looking along its path. The region, a 4 m
    band across both cameras' views, slides 5 cm a request; the filter alternates yellow / blue."""
    passes, step = divmod(i, round(MOVING_RANGE_M / MOVING_STEP_M))
    y0 = step * MOVING_STEP_M
    dx = passes * MOVING_PASS_SHIFT_M
    x0, _, x1, _ = BOTH_REGION
    return (YELLOW if i % 2 == 0 else BLUE), (x0 + dx, y0, x1 + dx, y0 + MOVING_RANGE_M)


async def paced(t0: float, count: int, rate_hz: float, one: Callable[[int], Coroutine[Any, Any, None]]) -> None:
    """Start one(0) ... one(count - 1) on schedule, request i at loop time t0 + i / rate_hz (never
    waiting for earlier ones to finish), and wait for them all."""
    loop = asyncio.get_running_loop()
    tasks: list[asyncio.Task[None]] = []
    for i in range(count):
        delay = t0 + i / rate_hz - loop.time()
        if delay > 0:
            await asyncio.sleep(delay)
        tasks.append(loop.create_task(one(i)))
    await asyncio.gather(*tasks)


def _bump(histogram: dict[str, int], value: int) -> None:
    histogram[str(value)] = histogram.get(str(value), 0) + 1


def _latency_figures(latencies: list[float]) -> dict[str, float]:
    """Each request's time from the robot's call to its answer, ms: the median and the 99th percentile."""
    if not latencies:
        return {}
    ordered = sorted(latencies)
    return {
        "latency_ms_p50": statistics.median(ordered),
        "latency_ms_p99": ordered[min(len(ordered) - 1, max(0, math.ceil(0.99 * len(ordered)) - 1))],
    }


async def measured(
    args: argparse.Namespace,
    ask: Callable[[int], Coroutine[Any, Any, _R]],
    tally: Callable[[int, _R], None],
    failures: list[str],
) -> dict[str, Any]:
    """The single-shot workload's schedule, whatever the delivery: `args.warmup` requests back to
    back (connections, caches; a refusal is printed), START, then `args.requests` requests paced at
    `args.rate`, each `ask(i)`'s answer handed to `tally(i, answer)`. A request refused (DrvsError:
    rate limit, invalid, unavailable) is a failure, never delivered. Returns the figures common to
    every delivery: CPU and wall time, requests, refusals, latency."""
    for i in range(-args.warmup, 0):
        try:
            await ask(i)
        except DrvsError as exc:
            print(f"warm-up request {i} refused: {exc}", flush=True)
    print("START", flush=True)
    start_cpu = time.process_time()
    loop = asyncio.get_running_loop()
    t0 = loop.time()
    latencies: list[float] = []
    refused = 0

    async def one(i: int) -> None:
        nonlocal refused
        try:
            asked = time.perf_counter()
            answer = await ask(i)
            latencies.append((time.perf_counter() - asked) * 1000)
        except DrvsError as exc:
            refused += 1
            print(f"request {i} refused: {exc}", flush=True)
            if len(failures) < 10:
                failures.append(f"request {i} refused: {type(exc).__name__}: {exc}")
            return
        tally(i, answer)

    await paced(t0, args.requests, args.rate, one)
    return {
        "cpu_s": time.process_time() - start_cpu,
        "wall_s": loop.time() - t0,
        "requests": args.requests,
        "refused_requests": refused,
        **_latency_figures(latencies),
    }


def _request(args: argparse.Namespace, i: int) -> tuple[str, Any]:
    return moving_request(i) if args.moving else (args.filter, args.region)


async def drvs_mode(args: argparse.Namespace) -> dict[str, object]:
    if args.fuse:
        return await fused_mode(args)
    async with DrvsClient(args.server, robot_id="bench", listen="127.0.0.1:0", advertise=args.advertise) as client:
        print(f"READY {client.port}", flush=True)
        reports = detections = missing = error_reports = busy_reports = delivered = 0
        reports_per_request: dict[str, int] = {}
        detections_per_request: dict[str, int] = {}
        failures: list[str] = []  # the first few, to name in a failed work check

        async def ask(i: int) -> DetectionResult:
            filter_def, region = _request(args, i)
            return await client.detect(filter_def, region, timeout_s=5.0, outlines=not args.no_outlines)

        def tally(i: int, result: DetectionResult) -> None:
            nonlocal reports, detections, missing, error_reports, busy_reports, delivered
            errors = result.errors
            good = [r for r in result.reports if not r.error]
            reports += len(good)
            error_reports += len(errors)
            busy_reports += sum("busy" in e for e in errors)
            detections += len(result.detections)
            missing += len(result.missing_cameras)
            _bump(reports_per_request, len(good))
            _bump(detections_per_request, len(result.detections))
            # Delivered: every camera the request needs answered with a final report, none an error.
            if not errors and result.complete and len(result.camera_ids) == args.cameras == len(good):
                delivered += 1
            elif len(failures) < 10:
                failures.append(
                    f"request {i}: cameras {sorted(result.camera_ids)}, {len(good)} reports, errors {errors}, "
                    f"missing {sorted(result.missing_cameras)}"
                )

        common = await measured(args, ask, tally, failures)
        return {
            **common,
            "requests_delivered": delivered,
            "reports": reports,
            "error_reports": error_reports,
            "busy_reports": busy_reports,
            "detections": detections,
            "missing_finals": missing,
            "failed_requests": args.requests - delivered,
            "reports_per_request": reports_per_request,
            "detections_per_request": detections_per_request,
            "failures": failures,
        }


async def fused_mode(args: argparse.Namespace) -> dict[str, object]:
    """The same single shots with fused delivery: one request and one answer (a snapshot of world
    objects) per request on the robot's own stream; the robot opens no listener."""
    async with DrvsClient(args.server, robot_id="bench") as client:
        print("READY 0", flush=True)
        outlines = not args.no_outlines
        snapshots = objects = missing = delivered = 0
        objects_per_request: dict[str, int] = {}
        failures: list[str] = []

        async def ask(i: int) -> Snapshot:
            filter_def, region = _request(args, i)
            return await client.snapshot(filter_def, region, timeout_s=5.0, outlines=outlines)

        def tally(i: int, snapshot: Snapshot) -> None:
            nonlocal snapshots, objects, missing, delivered
            snapshots += 1
            objects += len(snapshot.objects)
            missing += len(snapshot.camera_errors)
            _bump(objects_per_request, len(snapshot.objects))
            # Delivered: one final snapshot that merged every camera the request needs, none missing.
            if snapshot.final and not snapshot.camera_errors and len(snapshot.camera_ids) == args.cameras:
                delivered += 1
            elif len(failures) < 10:
                failures.append(
                    f"request {i}: cameras {sorted(snapshot.camera_ids)}, final {snapshot.final}, "
                    f"missing {[(e.camera_id, e.code) for e in snapshot.camera_errors.values()]}"
                )

        common = await measured(args, ask, tally, failures)
        return {
            **common,
            "requests_delivered": delivered,
            "snapshots": snapshots,
            "objects": objects,
            "missing_cameras": missing,
            "failed_requests": args.requests - delivered,
            "objects_per_request": objects_per_request,
            "failures": failures,
        }


async def track_mode(args: argparse.Namespace) -> dict[str, object]:
    """A continuous fused request (DrvsClient.track), the counterpart of a video stream: one request,
    then one snapshot a period at `args.rate` on the robot's own stream, `args.requests` snapshots
    in all, each only consumed (counted). A short track first (`args.warmup_snapshots`) warms the
    connection and the track path, as the single-shot modes' warm-up requests do."""
    loop = asyncio.get_running_loop()
    outlines = not args.no_outlines
    async with DrvsClient(args.server, robot_id="bench") as client:
        print("READY 0", flush=True)
        warm = client.track(
            args.filter, args.region, rate_hz=args.rate, duration_s=_track_duration(args.warmup_snapshots, args.rate),
            outlines=outlines,
        )  # fmt: skip
        async for _ in warm:
            pass
        snapshots = objects = missing = missing_a_camera = finals = every_camera = objects_every_camera = 0
        objects_per_snapshot: dict[str, int] = {}
        failures: list[str] = []
        print("START", flush=True)
        start_cpu = time.process_time()
        t0 = loop.time()
        track = client.track(
            args.filter, args.region, rate_hz=args.rate, duration_s=_track_duration(args.requests, args.rate),
            outlines=outlines,
        )  # fmt: skip
        async with track as opened:
            async for snapshot in opened:
                snapshots += 1
                objects += len(snapshot.objects)
                missing += len(snapshot.camera_errors)
                missing_a_camera += bool(snapshot.camera_errors)
                finals += snapshot.final
                if len(snapshot.camera_ids) == args.cameras:
                    every_camera += 1
                    objects_every_camera += len(snapshot.objects)
                _bump(objects_per_snapshot, len(snapshot.objects))
                if snapshot.camera_errors and len(failures) < 10:
                    named = [(e.camera_id, e.code) for e in snapshot.camera_errors.values()]
                    failures.append(f"snapshot {snapshot.sequence}: missing {named}")
            dropped = opened.dropped
        cpu = time.process_time() - start_cpu
        wall = loop.time() - t0
    return {
        "cpu_s": cpu,
        "wall_s": wall,
        "requests": args.requests,
        "snapshots": snapshots,
        "final_snapshots": finals,
        "dropped_snapshots": dropped,
        "objects": objects,
        "missing_cameras": missing,
        "snapshots_missing_a_camera": missing_a_camera,
        # Snapshots that merged a fresh report from every camera (a report later than half a period
        # is merged into the next; the tracker keeps its objects meanwhile).
        "snapshots_every_camera": every_camera,
        "objects_every_camera": objects_every_camera,
        "objects_per_snapshot": objects_per_snapshot,
        "failures": failures,
    }


def _track_duration(snapshots: int, rate: float) -> float:
    """The duration of a track of `snapshots` snapshots at `rate` (it sends one at 0, 1/rate, ...)."""
    return max(1, snapshots - 1) / rate


async def stream_mode(args: argparse.Namespace) -> dict[str, object]:
    encoding = stream_pb2.FRAME_ENCODING_RAW_BGR if args.mode == "raw" else stream_pb2.FRAME_ENCODING_JPEG
    detectors: list[Detector] = []
    wanted = object_type(args.filter)
    for hfile in args.homography:
        h = load_homography(hfile)
        view = CameraView(h, FieldOfView.compute(h, IMAGE_SIZE, args.max_range), IMAGE_SIZE)
        detectors.append(PeopleDetector(view) if wanted.kind == "people" else HsvDetector(view))
    region = box(*args.region)
    duration = args.requests / args.rate
    print("READY 0", flush=True)
    loop = asyncio.get_running_loop()
    # Measured from when every camera's stream has carried its warm-up frames (connections, first
    # frames, the detector's first calls), as the DRVS robot is measured after its warm-up requests.
    warmed = [asyncio.Event() for _ in args.camera]
    measuring = asyncio.Event()
    start_cpu = t0 = 0.0

    async def start_when_warm() -> None:
        nonlocal start_cpu, t0
        for e in warmed:
            await e.wait()
        print("START", flush=True)
        start_cpu = time.process_time()
        t0 = loop.time()
        measuring.set()

    starter = loop.create_task(start_when_warm())
    cameras = [
        {"camera": address, "frames_received": 0, "frames_analysed": 0, "detections": 0, "detections_per_frame": {}}
        for address in args.camera
    ]

    def detect(detector: Detector, data: bytes, seq: int) -> int:
        if encoding == stream_pb2.FRAME_ENCODING_RAW_BGR:
            pixels = np.frombuffer(data, dtype=np.uint8).reshape(IMAGE_SIZE[1], IMAGE_SIZE[0], 3)
        else:
            pixels = np.asarray(cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_COLOR), dtype=np.uint8)
        analysis = FrameAnalysis(Frame(pixels, 0.0, seq))
        if isinstance(detector, HsvDetector):
            return len(detector.detect(analysis, args.filter, region))
        return len(select(detector.narrow(detector.find(analysis, wanted), wanted), region))

    token = args.camera_token_file.read_text().strip() if args.camera_token_file else ""
    metadata = (("authorization", f"Bearer {token}"),) if token else ()

    async def watch(address: str, detector: Detector, counts: dict[str, Any], warm: asyncio.Event) -> None:
        # gRPC's default channel: the baseline is what a user streaming video would get, not DRVS's tuning.
        async with aio.insecure_channel(address) as channel:
            stub = stream_pb2_grpc.FrameStreamStub(channel)
            call = stub.StreamFrames(
                stream_pb2.StreamFramesRequest(encoding=encoding, jpeg_quality=80, max_fps=args.max_fps),
                metadata=metadata,
            )
            try:
                seen = 0
                async for frame in call:
                    seen += 1
                    if not measuring.is_set():  # warming up: analysed, not counted
                        await asyncio.to_thread(detect, detector, frame.data, frame.sequence)
                        if seen >= args.warmup_frames:
                            warm.set()
                        continue
                    counts["frames_received"] += 1
                    found = await asyncio.to_thread(detect, detector, frame.data, frame.sequence)
                    # Added after the await: `x += await ...` reads x before it and loses the other
                    # camera's updates made meanwhile.
                    counts["frames_analysed"] += 1
                    counts["detections"] += found
                    _bump(counts["detections_per_frame"], found)
                    if loop.time() - t0 >= duration:
                        break
            finally:
                call.cancel()

    watchers = zip(args.camera, detectors, cameras, warmed, strict=True)
    await asyncio.gather(*(watch(a, d, c, w) for a, d, c, w in watchers))
    if not measuring.is_set():
        starter.cancel()
        raise SystemExit("a camera's frame stream ended before its warm-up frames")
    wall = loop.time() - t0
    return {
        "cpu_s": time.process_time() - start_cpu,
        "wall_s": wall,
        "frames": sum(c["frames_received"] for c in cameras),
        # What the cameras' sources made meanwhile: fewer frames received means a stream fell behind
        # (a camera or the robot short of CPU), and the baseline carried less than a full stream.
        "frames_expected": round(min(FPS, args.max_fps) * wall) * len(cameras),
        "frames_analysed": sum(c["frames_analysed"] for c in cameras),
        "detections": sum(c["detections"] for c in cameras),
        "per_camera": cameras,
    }


def workload_main(args: argparse.Namespace) -> int:
    run = (track_mode if args.track else drvs_mode) if args.mode == "drvs" else stream_mode
    result = asyncio.run(run(args))
    print("DONE " + json.dumps(result), flush=True)
    return 0


def _region(text: str) -> tuple[float, float, float, float]:
    x0, y0, x1, y1 = (float(v) for v in text.split(","))
    return x0, y0, x1, y1


def add_workload_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--mode", choices=["drvs", "raw", "jpeg"], required=True)
    p.add_argument("--server", help="DRVS server HOST:PORT (drvs mode)")
    p.add_argument("--advertise", help="callback address cameras should call (drvs mode)")
    p.add_argument("--camera", action="append", default=[], help="camera HOST:PORT to stream from (raw/jpeg)")
    p.add_argument("--homography", action="append", type=Path, default=[], help="each camera's homography file")
    p.add_argument("--camera-token-file", type=Path, help="the cameras' token, for their frame streams (raw/jpeg)")
    p.add_argument("--filter", default=YELLOW, help="filter_def to find (hsv_... or people; not with --moving)")
    p.add_argument("--region", type=_region, default=BOTH_REGION, help="X0,Y0,X1,Y1 of the floor to search, metres")
    p.add_argument("--max-range", type=float, default=6.0, help="raw/jpeg: the cameras' --max-range, metres")
    p.add_argument("--max-fps", type=float, default=FPS, help="raw/jpeg: frames per second to ask of each camera")
    p.add_argument("--no-outlines", action="store_true", help="drvs mode: ask for boxes only, as the paper's DRVS")
    p.add_argument("--moving", action="store_true", help="drvs mode: the region slides and the filter alternates")
    p.add_argument("--fuse", action="store_true", help="drvs mode: fused delivery (one snapshot per request)")
    p.add_argument(
        "--track", action="store_true", help="drvs mode: one continuous fused track, --requests snapshots at --rate"
    )
    p.add_argument("--warmup-snapshots", type=int, default=10, help="--track: a short track of these first")
    p.add_argument("--cameras", type=int, default=2, help="drvs mode: cameras every request needs a report from")
    p.add_argument("--warmup", type=int, default=50, help="drvs mode: requests back to back before measuring")
    p.add_argument("--warmup-frames", type=int, default=10, help="raw/jpeg: frames per camera before measuring")
    p.add_argument("--requests", type=int, default=1500)
    p.add_argument("--rate", type=float, default=30.0)

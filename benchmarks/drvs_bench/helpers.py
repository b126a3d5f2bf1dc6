"""Processes the service benchmark runs: an ack-at-once DetectObjectBoundary server (a bare echo,
and fake cameras), a mass registrar, a load generator and a latency-measuring robot."""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import time
from typing import Any

import grpc
from grpc import aio

from drvs.core.errors import DrvsError
from drvs.core.geometry import homography_from_pose
from drvs.robot import DrvsClient
from drvs.tools.fakes import AckingCamera
from drvs.v1 import detection_pb2, detection_pb2_grpc, geometry_pb2, registry_pb2, registry_pb2_grpc
from drvs.wire import _grpc
from drvs.wire._cli import shutdown_event
from drvs.wire._service import Endpoint

from .common import ALL_REGION, YELLOW, peak_rss_bytes

#: Fake cameras sit on a grid this many metres apart; each sees about 6 m in front of it.
GRID_M = 10.0
#: The scene's second colour: the moving variant alternates it with YELLOW request by request.
BLUE = "hsv_100120080130255255"
#: Back-to-back requests before a latency run's measured ones, in DRVS and in the bare path alike.
WARMUP_REQUESTS = 50


def moving_filter(i: int) -> str:
    """The moving variant's filter for request i: yellow and blue in turn, so a request never
    repeats the previous one's filter (request compaction, filter caches)."""
    return YELLOW if i % 2 == 0 else BLUE


def moving_box(i: int, base: tuple[float, float, float, float], dx: float, dy: float) -> tuple[float, ...]:
    """`base` shifted by a different offset (within ±dx, 0..dy) for every i: a robot looking along
    its path, so no region repeats and the region caches do not hit."""
    ox = ((i * 0.6180339887) % 1.0 * 2 - 1) * dx
    oy = ((i * 0.4142135624) % 1.0) * dy
    x0, y0, x1, y1 = base
    return (x0 + ox, y0 + oy, x1 + ox, y1 + oy)


def moving_all_region(i: int) -> tuple[float, ...]:
    """ALL_REGION moved by up to ±1 m along x and 0.5 m along y: still over all three cameras."""
    return moving_box(i, ALL_REGION, 1.0, 0.5)


async def serve_detection(servicer: detection_pb2_grpc.DetectObjectBoundaryServicer) -> None:
    """Serve `servicer` as DetectObjectBoundary on a free loopback port, print `LISTENING address`,
    and stop at SIGINT or SIGTERM."""
    stop = shutdown_event()
    endpoint = Endpoint(
        "127.0.0.1:0",
        [detection_pb2.DESCRIPTOR.services_by_name["DetectObjectBoundary"].full_name],
        lambda s: detection_pb2_grpc.add_DetectObjectBoundaryServicer_to_server(servicer, s),
    )
    await endpoint.start()
    print(f"LISTENING {endpoint.address}", flush=True)
    await stop.wait()
    await endpoint.stop(0.5)


async def ack_server(args: argparse.Namespace) -> None:
    await serve_detection(AckingCamera("ack"))


def grid_position(i: int) -> tuple[float, float]:
    side = 100
    return (i % side) * GRID_M, (i // side) * GRID_M


async def register(args: argparse.Namespace) -> None:
    """Register N fake cameras on a grid, all served by one ack server."""
    async with _grpc.insecure_channel(args.server) as channel:
        stub = registry_pb2_grpc.RegisterVisionServiceStub(channel)
        sem = asyncio.Semaphore(32)
        t0 = time.perf_counter()

        async def one(i: int) -> None:
            x, y = grid_position(i)
            h = homography_from_pose((x, y, 3.0), 90.0, 40.0, 60.0, (640, 480))
            async with sem:
                await stub.Register(
                    registry_pb2.RegisterRequest(
                        camera_id=f"fake{i}",
                        address=args.camera_address,
                        homography=registry_pb2.Homography(m=h.to_list()),
                        image_width=640,
                        image_height=480,
                        max_range_m=6.0,
                        detector_kinds=["hsv"],
                        # The same fake camera each time: registering it again (the routing warm-up
                        # does) proves it is the same one, as a camera whose reply was lost does.
                        forward_secret=f"drvs-bench-fake-camera-{i}",
                    ),
                    timeout=30,
                )

        await asyncio.gather(*(one(i) for i in range(args.count)))
        print("DONE " + json.dumps({"registered": args.count, "seconds": time.perf_counter() - t0}), flush=True)


def one_camera_request(i: int, callback: str, moving: int | None = None) -> detection_pb2.DetectionRequest:
    """A request whose region lies in front of exactly one fake camera. With `moving` (a request
    counter), the region moves by up to ±0.4 m and the filter alternates, request by request."""
    x, y = grid_position(i)
    bounds: tuple[float, ...] = (x - 0.5, y + 3.0, x + 0.5, y + 4.0)
    filter_def = YELLOW
    if moving is not None:
        bounds = moving_box(moving, (x - 0.5, y + 3.0, x + 0.5, y + 4.0), 0.4, 0.8)
        filter_def = moving_filter(moving)
    box = geometry_pb2.Box(x_lower=bounds[0], y_lower=bounds[1], x_upper=bounds[2], y_upper=bounds[3])
    return detection_pb2.DetectionRequest(
        request_id=f"r{i}",
        robot_id="load",
        filter_def=filter_def,
        region=geometry_pb2.Region(box=box),
        callback_address=callback,
    )


def no_camera(reply: detection_pb2.DetectionReply) -> str:
    """The error for a reply that dispatched its request to no camera, with the server's reasons
    (each missing camera's code and message, whether the region was uncovered): a run that fails
    on it says why."""
    why = "; ".join(f"{m.camera_id}: {m.code} {m.message}" for m in reply.missing_cameras[:3])
    if reply.uncovered:
        why += f"{'; ' if why else ''}{len(reply.uncovered)} part(s) of the region uncovered"
    return f"request {reply.request_id} was dispatched to no camera ({why or 'no reason given'})"


class _Caller:
    """One request and its reply, as a unary call or as a message on a DetectStream of its own."""

    def __init__(self, channel: aio.Channel, mode: str) -> None:
        self._stub = detection_pb2_grpc.DetectObjectBoundaryStub(channel)
        self._stream: aio.StreamStreamCall[Any, Any] | None = self._stub.DetectStream() if mode == "stream" else None

    async def __call__(self, message: detection_pb2.DetectionRequest) -> None:
        if self._stream is None:
            unary = await self._stub.DetectObjects(message, timeout=10)
            if not unary.camera_ids:
                raise RuntimeError(no_camera(unary))
            return
        await self._stream.write(message)
        reply = await self._stream.read()
        if not isinstance(reply, detection_pb2.DetectionReply) or reply.HasField("error"):
            raise RuntimeError(f"stream refused or ended: {reply}")
        if not reply.camera_ids:  # routed nowhere: not a request served
            raise RuntimeError(no_camera(reply))

    def close(self) -> None:
        if self._stream is not None:
            self._stream.cancel()


async def load(args: argparse.Namespace) -> None:
    """As many requests as `concurrency` workers can make in `seconds`; each worker waits for the
    reply before its next request (unary calls, or its own DetectStream). A refused request, an
    error reply or a reply naming no camera counts as an error, never as done. With --moving, every
    request's region is new and the filter alternates."""
    async with _grpc.insecure_channel(args.target) as channel:
        messages = [one_camera_request(i % args.cameras, args.callback) for i in range(args.cameras)]
        counter = args.first_index

        def message(i: int) -> detection_pb2.DetectionRequest:
            nonlocal counter
            if not args.moving:
                return messages[i % len(messages)]
            counter += 1
            return one_camera_request(i % args.cameras, args.callback, moving=counter)

        done = errors = 0
        error_kinds: dict[str, int] = {}
        loop = asyncio.get_running_loop()
        callers = [_Caller(channel, args.mode) for _ in range(args.concurrency)]
        for k, caller in enumerate(callers):
            try:
                await caller(with_request_id(messages[0], f"warm{k}"))
            except (grpc.RpcError, RuntimeError):
                errors += 1  # a failed warm-up fails the run as any error does
        end = loop.time() + args.seconds

        async def worker(k: int) -> None:
            nonlocal done, errors
            i = k
            while loop.time() < end:
                try:
                    await callers[k](message(i))
                    done += 1
                except (grpc.RpcError, RuntimeError) as exc:
                    errors += 1
                    kind = str(exc)[:200]
                    error_kinds[kind] = error_kinds.get(kind, 0) + 1
                i += args.concurrency

        t0 = loop.time()
        await asyncio.gather(*(worker(k) for k in range(args.concurrency)))
        elapsed = loop.time() - t0
        for caller in callers:
            caller.close()
        kinds = dict(sorted(error_kinds.items(), key=lambda kv: -kv[1])[:5])
        print(
            "DONE " + json.dumps({"calls": done, "errors": errors, "rps": done / elapsed, "error_kinds": kinds}),
            flush=True,
        )


def with_request_id(message: detection_pb2.DetectionRequest, request_id: str) -> detection_pb2.DetectionRequest:
    copy = detection_pb2.DetectionRequest()
    copy.CopyFrom(message)
    copy.request_id = request_id
    return copy


def percentile(values: list[float], q: float) -> float:
    if not values:
        return math.nan
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, max(0, math.ceil(q / 100 * len(ordered)) - 1))]


async def latency(args: argparse.Namespace) -> None:
    """Single-shot requests over all cameras at a fixed rate: time to first report and to last final.

    WARMUP_REQUESTS back to back first (as the bare path's robot does), not counted. A request
    counts as complete only when every dispatched camera sent a final report and none carried an
    error (a `busy` refusal is an error report); a refused request (DrvsError) is a failure. Only
    complete requests give latencies. With --moving, every request moves its region and alternates
    the filter."""
    async with DrvsClient(args.server, robot_id="latency", listen="127.0.0.1:0") as client:
        for w in range(args.warmup):
            await client.detect(
                moving_filter(w) if args.moving else YELLOW,
                moving_all_region(args.first_index - 1 - w) if args.moving else ALL_REGION,
                timeout_s=5,
            )
        loop = asyncio.get_running_loop()
        first: list[float] = []
        last: list[float] = []
        counts = {"complete": 0, "missing": 0, "error_reports": 0, "refused": 0, "no_camera": 0}
        error_kinds: dict[str, int] = {}

        async def one(i: int, t0: float) -> None:
            filter_def = moving_filter(i) if args.moving else YELLOW
            region = moving_all_region(args.first_index + i) if args.moving else ALL_REGION
            try:
                sub = await client.subscribe(filter_def, region, timeout_s=5.0)
            except DrvsError:
                counts["refused"] += 1
                return
            first_ms = -1.0
            async for report in sub:
                if first_ms < 0 and not report.error:
                    first_ms = (loop.time() - t0) * 1000
            errors = sum(1 for r in sub.result.reports if r.error)
            counts["error_reports"] += errors
            for r in sub.result.reports:
                if r.error and len(error_kinds) < 5:
                    error_kinds[r.error[:200]] = error_kinds.get(r.error[:200], 0) + 1
            if not sub.camera_ids:
                counts["no_camera"] += 1
            elif not sub.result.complete:
                counts["missing"] += 1
            elif errors == 0:
                counts["complete"] += 1
                first.append(first_ms)
                last.append((loop.time() - t0) * 1000)

        start = loop.time()
        tasks = []
        for i in range(args.requests):
            scheduled = start + i / args.rate
            delay = scheduled - loop.time()
            if delay > 0:
                await asyncio.sleep(delay)
            # Timed from its scheduled time: a request sent late counts its lag.
            tasks.append(loop.create_task(one(i, scheduled)))
        await asyncio.gather(*tasks)
        elapsed = loop.time() - start
        print(
            "DONE "
            + json.dumps(
                {
                    "rate_hz": args.rate,
                    "achieved_hz": args.requests / elapsed,
                    "requests": args.requests,
                    "moving": bool(args.moving),
                    **counts,
                    "error_kinds": error_kinds,
                    "first_ms": first,
                    "last_ms": last,
                    "peak_rss_bytes": peak_rss_bytes(os.getpid()),
                }
            ),
            flush=True,
        )


async def rtt(args: argparse.Namespace) -> None:
    """Median round trip to an ack server, as bare unary calls or as messages on one DetectStream:
    the transport's floor."""
    async with _grpc.insecure_channel(args.target) as channel:
        call = _Caller(channel, args.mode)
        msg = one_camera_request(0, "127.0.0.1:9")
        for _ in range(50):
            await call(msg)
        times = []
        loop = asyncio.get_running_loop()
        start = loop.time()
        cpu_start = time.process_time()
        for i in range(args.calls):
            if args.rate:
                delay = start + i / args.rate - loop.time()
                if delay > 0:
                    await asyncio.sleep(delay)
            t0 = time.perf_counter()
            await call(msg)
            times.append((time.perf_counter() - t0) * 1000)
        call.close()
        print(
            "DONE "
            + json.dumps(
                {
                    "rtt_ms_p50": percentile(times, 50),
                    "rtt_ms_p90": percentile(times, 90),
                    "cpu_s": time.process_time() - cpu_start,
                    "wall_s": loop.time() - start,
                }
            ),
            flush=True,
        )


def add_helper_parsers(sub: Any) -> None:
    a = sub.add_parser("ack-server", help="(internal) DetectObjectBoundary that answers at once")
    a.set_defaults(func=lambda args: asyncio.run(ack_server(args)) or 0)
    r = sub.add_parser("register", help="(internal) register N fake cameras")
    r.add_argument("--server", required=True)
    r.add_argument("--camera-address", required=True)
    r.add_argument("--count", type=int, required=True)
    r.set_defaults(func=lambda args: asyncio.run(register(args)) or 0)
    lo = sub.add_parser("routing-load", help="(internal) requests as fast as they go")
    lo.add_argument("--target", required=True)
    lo.add_argument("--callback", default="127.0.0.1:9")
    lo.add_argument("--cameras", type=int, default=1000)
    lo.add_argument("--concurrency", type=int, default=64)
    lo.add_argument("--seconds", type=float, default=5.0)
    lo.add_argument("--mode", choices=["unary", "stream"], default="stream")
    lo.add_argument("--moving", action="store_true", help="a new region and the other filter every request")
    lo.add_argument("--first-index", type=int, default=0, help="--moving: where the regions' sequence starts")
    lo.set_defaults(func=lambda args: asyncio.run(load(args)) or 0)
    la = sub.add_parser("latency", help="(internal) request latency at a fixed rate")
    la.add_argument("--server", required=True)
    la.add_argument("--rate", type=float, required=True)
    la.add_argument("--requests", type=int, required=True)
    la.add_argument("--warmup", type=int, default=WARMUP_REQUESTS, help="back-to-back requests first, not counted")
    la.add_argument("--moving", action="store_true", help="a new region and the other filter every request")
    la.add_argument("--first-index", type=int, default=WARMUP_REQUESTS, help="--moving: where the regions start")
    la.set_defaults(func=lambda args: asyncio.run(latency(args)) or 0)
    rt = sub.add_parser("rtt", help="(internal) bare round trips")
    rt.add_argument("--target", required=True)
    rt.add_argument("--calls", type=int, default=500)
    rt.add_argument("--rate", type=float, default=0.0, help="calls a second (0: back to back)")
    rt.add_argument("--mode", choices=["unary", "stream"], default="stream")
    rt.set_defaults(func=lambda args: asyncio.run(rtt(args)) or 0)

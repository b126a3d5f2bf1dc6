"""The robot's side of the paper benchmark, run as its own process so its CPU is its own.

drvs: 1500 single-shot requests at 30 Hz through DRVS. raw / jpeg: both cameras stream every
frame to the robot, which runs the same HSV detection on each frame itself.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import time
from pathlib import Path

import cv2
import numpy as np
from shapely.geometry import box

from drvs import _grpc
from drvs.camera.homography_file import load_homography
from drvs.detection import Frame, FrameAnalysis, HsvDetector
from drvs.errors import DrvsError
from drvs.geometry import FieldOfView
from drvs.robot import DrvsClient
from drvs.v1 import stream_pb2, stream_pb2_grpc

from .common import BOTH_REGION, FPS, IMAGE_SIZE, YELLOW


async def drvs_mode(args: argparse.Namespace) -> dict[str, object]:
    async with DrvsClient(args.server, robot_id="bench", listen="127.0.0.1:0", advertise=args.advertise) as client:
        print(f"READY {client.port}", flush=True)
        start_cpu = time.process_time()
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        reports = detections = missing = failed = 0

        async def one(i: int) -> None:
            nonlocal reports, detections, missing, failed
            try:
                result = await client.detect(YELLOW, BOTH_REGION, timeout_s=5.0, outlines=not args.no_outlines)
            except DrvsError as exc:  # counted, not fatal: a loaded machine may drop one
                failed += 1
                print(f"request {i} failed: {exc}", flush=True)
                return
            reports += len(result.reports)
            detections += len(result.detections)
            missing += len(result.missing_cameras)

        tasks = []
        for i in range(args.requests):
            delay = t0 + i / args.rate - loop.time()
            if delay > 0:
                await asyncio.sleep(delay)
            tasks.append(loop.create_task(one(i)))
        await asyncio.gather(*tasks)
        return {
            "cpu_s": time.process_time() - start_cpu,
            "wall_s": loop.time() - t0,
            "requests": args.requests,
            "reports": reports,
            "detections": detections,
            "missing_finals": missing,
            "failed_requests": failed,
        }


async def stream_mode(args: argparse.Namespace) -> dict[str, object]:
    encoding = stream_pb2.FRAME_ENCODING_RAW_BGR if args.mode == "raw" else stream_pb2.FRAME_ENCODING_JPEG
    detectors = []
    for hfile in args.homography:
        h = load_homography(hfile)
        detectors.append(HsvDetector(h, FieldOfView.compute(h, IMAGE_SIZE, 6.0), IMAGE_SIZE))
    region = box(*BOTH_REGION)
    duration = args.requests / args.rate
    print("READY 0", flush=True)
    start_cpu = time.process_time()
    loop = asyncio.get_running_loop()
    t0 = loop.time()
    frames = detections = 0

    def detect(detector: HsvDetector, data: bytes, seq: int) -> int:
        if encoding == stream_pb2.FRAME_ENCODING_RAW_BGR:
            pixels = np.frombuffer(data, dtype=np.uint8).reshape(IMAGE_SIZE[1], IMAGE_SIZE[0], 3)
        else:
            pixels = np.asarray(cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_COLOR), dtype=np.uint8)
        return len(detector.detect(FrameAnalysis(Frame(pixels, 0.0, seq)), YELLOW, region))

    token = args.camera_token_file.read_text().strip() if args.camera_token_file else ""
    metadata = (("authorization", f"Bearer {token}"),) if token else ()

    async def watch(address: str, detector: HsvDetector) -> None:
        nonlocal frames, detections
        async with _grpc.insecure_channel(address) as channel:
            stub = stream_pb2_grpc.FrameStreamStub(channel)
            call = stub.StreamFrames(
                stream_pb2.StreamFramesRequest(encoding=encoding, jpeg_quality=80, max_fps=FPS), metadata=metadata
            )
            try:
                async for frame in call:
                    frames += 1
                    detections += await asyncio.to_thread(detect, detector, frame.data, frame.sequence)
                    if loop.time() - t0 >= duration:
                        break
            finally:
                call.cancel()

    await asyncio.gather(*(watch(a, d) for a, d in zip(args.camera, detectors, strict=True)))
    return {
        "cpu_s": time.process_time() - start_cpu,
        "wall_s": loop.time() - t0,
        "frames": frames,
        "detections": detections,
    }


def workload_main(args: argparse.Namespace) -> int:
    run = drvs_mode if args.mode == "drvs" else stream_mode
    result = asyncio.run(run(args))
    print("DONE " + json.dumps(result), flush=True)
    return 0


def add_workload_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--mode", choices=["drvs", "raw", "jpeg"], required=True)
    p.add_argument("--server", help="DRVS server HOST:PORT (drvs mode)")
    p.add_argument("--advertise", help="callback address cameras should call (drvs mode)")
    p.add_argument("--camera", action="append", default=[], help="camera HOST:PORT to stream from (raw/jpeg)")
    p.add_argument("--homography", action="append", type=Path, default=[], help="each camera's homography file")
    p.add_argument("--camera-token-file", type=Path, help="the cameras' token, for their frame streams (raw/jpeg)")
    p.add_argument("--no-outlines", action="store_true", help="drvs mode: ask for boxes only, as the paper's DRVS")
    p.add_argument("--requests", type=int, default=1500)
    p.add_argument("--rate", type=float, default=30.0)

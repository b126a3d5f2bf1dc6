"""Processes the service benchmark runs: an ack-at-once DetectObjectBoundary server (a bare echo,
and fake cameras), a mass registrar, a load generator and a latency-measuring robot."""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import time
from collections.abc import AsyncIterator
from typing import Any

import grpc
from grpc import aio

from drvs import _grpc
from drvs._cli import shutdown_event
from drvs._service import Endpoint
from drvs.geometry import homography_from_pose
from drvs.robot import DrvsClient
from drvs.v1 import detection_pb2, detection_pb2_grpc, geometry_pb2, registry_pb2, registry_pb2_grpc

from .common import ALL_REGION, YELLOW, peak_rss_bytes

#: Fake cameras sit on a grid this many metres apart; each sees about 6 m in front of it.
GRID_M = 10.0


class _Ack(detection_pb2_grpc.DetectObjectBoundaryServicer):
    """Answers at once: a bare grpc.aio echo of the request id, with no validation or work."""

    async def DetectObjects(
        self, request: detection_pb2.DetectionRequest, context: aio.ServicerContext[Any, Any]
    ) -> detection_pb2.DetectionReply:
        return detection_pb2.DetectionReply(request_id=request.request_id, camera_ids=["ack"])

    async def DetectStream(
        self,
        request_iterator: AsyncIterator[detection_pb2.DetectionRequest],
        context: aio.ServicerContext[Any, Any],
    ) -> AsyncIterator[detection_pb2.DetectionReply]:
        async for request in request_iterator:
            yield detection_pb2.DetectionReply(request_id=request.request_id, camera_ids=["ack"])

    async def DetectBatches(
        self,
        request_iterator: AsyncIterator[detection_pb2.DetectionRequests],
        context: aio.ServicerContext[Any, Any],
    ) -> AsyncIterator[detection_pb2.DetectionReplies]:
        async for batch in request_iterator:
            yield detection_pb2.DetectionReplies(
                replies=[
                    detection_pb2.DetectionReply(request_id=request.request_id, camera_ids=["ack"])
                    for request in batch.requests
                ]
            )


async def ack_server(args: argparse.Namespace) -> None:
    stop = shutdown_event()
    endpoint = Endpoint(
        "127.0.0.1:0",
        [detection_pb2.DESCRIPTOR.services_by_name["DetectObjectBoundary"].full_name],
        lambda s: detection_pb2_grpc.add_DetectObjectBoundaryServicer_to_server(_Ack(), s),
    )
    await endpoint.start()
    print(f"LISTENING {endpoint.address}", flush=True)
    await stop.wait()
    await endpoint.stop(0.5)


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
                    ),
                    timeout=30,
                )

        await asyncio.gather(*(one(i) for i in range(args.count)))
        print("DONE " + json.dumps({"registered": args.count, "seconds": time.perf_counter() - t0}), flush=True)


def one_camera_request(i: int, callback: str) -> detection_pb2.DetectionRequest:
    """A request whose region lies in front of exactly one fake camera."""
    x, y = grid_position(i)
    box = geometry_pb2.Box(x_lower=x - 0.5, y_lower=y + 3.0, x_upper=x + 0.5, y_upper=y + 4.0)
    return detection_pb2.DetectionRequest(
        request_id=f"r{i}",
        robot_id="load",
        filter_def=YELLOW,
        region=geometry_pb2.Region(box=box),
        callback_address=callback,
    )


class _Caller:
    """One request and its reply, as a unary call or as a message on a DetectStream of its own."""

    def __init__(self, channel: aio.Channel, mode: str) -> None:
        self._stub = detection_pb2_grpc.DetectObjectBoundaryStub(channel)
        self._stream: aio.StreamStreamCall[Any, Any] | None = self._stub.DetectStream() if mode == "stream" else None

    async def __call__(self, message: detection_pb2.DetectionRequest) -> None:
        if self._stream is None:
            await self._stub.DetectObjects(message, timeout=10)
            return
        await self._stream.write(message)
        reply = await self._stream.read()
        if not isinstance(reply, detection_pb2.DetectionReply) or reply.HasField("error"):
            raise RuntimeError(f"stream refused or ended: {reply}")

    def close(self) -> None:
        if self._stream is not None:
            self._stream.cancel()


async def load(args: argparse.Namespace) -> None:
    """As many requests as `concurrency` workers can make in `seconds`; each worker waits for the
    reply before its next request (unary calls, or its own DetectStream)."""
    async with _grpc.insecure_channel(args.target) as channel:
        messages = [one_camera_request(i % args.cameras, args.callback) for i in range(args.cameras)]
        done = errors = 0
        loop = asyncio.get_running_loop()
        callers = [_Caller(channel, args.mode) for _ in range(args.concurrency)]
        for k, caller in enumerate(callers):
            await caller(with_request_id(messages[0], f"warm{k}"))
        end = loop.time() + args.seconds

        async def worker(k: int) -> None:
            nonlocal done, errors
            i = k
            while loop.time() < end:
                try:
                    await callers[k](messages[i % len(messages)])
                    done += 1
                except (grpc.RpcError, RuntimeError):
                    errors += 1
                i += args.concurrency

        t0 = loop.time()
        await asyncio.gather(*(worker(k) for k in range(args.concurrency)))
        elapsed = loop.time() - t0
        for caller in callers:
            caller.close()
        print("DONE " + json.dumps({"calls": done, "errors": errors, "rps": done / elapsed}), flush=True)


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
    """Single-shot requests over all cameras at a fixed rate: time to first report and to last final."""
    async with DrvsClient(args.server, robot_id="latency", listen="127.0.0.1:0") as client:
        await client.detect(YELLOW, ALL_REGION, timeout_s=5)
        loop = asyncio.get_running_loop()
        first: list[float] = []
        last: list[float] = []
        missing = 0

        async def one() -> None:
            nonlocal missing
            t0 = loop.time()
            sub = await client.subscribe(YELLOW, ALL_REGION, timeout_s=5.0)
            got_first = False
            async for _report in sub:
                if not got_first:
                    first.append((loop.time() - t0) * 1000)
                    got_first = True
            if sub.result.complete and sub.camera_ids:
                last.append((loop.time() - t0) * 1000)
            else:
                missing += 1

        start = loop.time()
        tasks = []
        for i in range(args.requests):
            delay = start + i / args.rate - loop.time()
            if delay > 0:
                await asyncio.sleep(delay)
            tasks.append(loop.create_task(one()))
        await asyncio.gather(*tasks)
        elapsed = loop.time() - start
        print(
            "DONE "
            + json.dumps(
                {
                    "rate_hz": args.rate,
                    "achieved_hz": args.requests / elapsed,
                    "requests": args.requests,
                    "missing": missing,
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
    lo.set_defaults(func=lambda args: asyncio.run(load(args)) or 0)
    la = sub.add_parser("latency", help="(internal) request latency at a fixed rate")
    la.add_argument("--server", required=True)
    la.add_argument("--rate", type=float, required=True)
    la.add_argument("--requests", type=int, required=True)
    la.set_defaults(func=lambda args: asyncio.run(latency(args)) or 0)
    rt = sub.add_parser("rtt", help="(internal) bare round trips")
    rt.add_argument("--target", required=True)
    rt.add_argument("--calls", type=int, default=500)
    rt.add_argument("--rate", type=float, default=0.0, help="calls a second (0: back to back)")
    rt.add_argument("--mode", choices=["unary", "stream"], default="stream")
    rt.set_defaults(func=lambda args: asyncio.run(rtt(args)) or 0)

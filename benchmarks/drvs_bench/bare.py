"""DRVS's message flow in bare grpc.aio, with no DRVS code: the floor that DRVS's own costs are
measured against.

A request goes from the robot to the bare server on a long-lived DetectStream; the server answers
at once and forwards it on a long-lived DetectStream to each camera it names (or, for the routing
floor, to one camera of many); each bare camera acknowledges at once and sends one report to the
robot's listener on a ReportDetections stream it keeps per robot. No validation, no routing index,
no detection, no Python objects beyond the messages: what any grpc.aio system that moves the same
messages between the same processes must pay.
"""

from __future__ import annotations

import argparse
import asyncio
import itertools
import json
import os
import time
from collections.abc import AsyncIterator
from typing import Any

from grpc import aio

from drvs import _grpc
from drvs.v1 import detection_pb2, detection_pb2_grpc

from .common import peak_rss_bytes
from .fakes import AckingCamera
from .helpers import one_camera_request, percentile, serve_detection


class _Forwards:
    """One long-lived DetectStream per camera on one channel; a task per stream drains the acks."""

    def __init__(self, channel: aio.Channel, count: int) -> None:
        self.channel = channel  # an aio.Channel closes its calls when collected
        stub = detection_pb2_grpc.DetectObjectBoundaryStub(channel)
        self.calls: list[aio.StreamStreamCall[Any, Any]] = [stub.DetectStream() for _ in range(count)]
        self.locks = [asyncio.Lock() for _ in range(count)]
        self._drains = [asyncio.get_running_loop().create_task(self._drain(c)) for c in self.calls]

    @staticmethod
    async def _drain(call: aio.StreamStreamCall[Any, Any]) -> None:
        async for _ack in call:
            pass

    async def send(self, k: int, message: detection_pb2.DetectionRequest) -> None:
        async with self.locks[k]:
            await self.calls[k].write(message)


class _BareServer(detection_pb2_grpc.DetectObjectBoundaryServicer):
    def __init__(self, targets: list[str], streams_per_target: int, fanout: str) -> None:
        self._targets = targets
        self._per_target = streams_per_target
        self._fanout = fanout
        self._forwards: list[_Forwards] = []
        self._counter = itertools.count()

    def _open(self) -> None:
        if not self._forwards:
            self._forwards = [_Forwards(_grpc.insecure_channel(t), self._per_target) for t in self._targets]

    async def DetectStream(
        self,
        request_iterator: AsyncIterator[detection_pb2.DetectionRequest],
        context: aio.ServicerContext[Any, Any],
    ) -> AsyncIterator[detection_pb2.DetectionReply]:
        self._open()
        async for request in request_iterator:
            if self._fanout == "all":
                for forwards in self._forwards:
                    await forwards.send(0, request)
                cameras = [f"bare{k}" for k in range(len(self._forwards))]
            else:  # one camera of many, in turn
                k = next(self._counter) % self._per_target
                await self._forwards[0].send(k, request)
                cameras = [f"bare{k}"]
            yield detection_pb2.DetectionReply(request_id=request.request_id, camera_ids=cameras)


class _BareCamera(AckingCamera):
    """Acknowledges each request at once, then sends its one report to the robot."""

    def __init__(self, camera_id: str) -> None:
        super().__init__(camera_id)
        self._reports: dict[str, aio.StreamStreamCall[Any, Any]] = {}
        self._channels: list[aio.Channel] = []  # an aio.Channel closes its calls when collected

    def _report_stream(self, address: str) -> aio.StreamStreamCall[Any, Any]:
        call = self._reports.get(address)
        if call is None:
            self._channels.append(_grpc.insecure_channel(address))
            stub = detection_pb2_grpc.CallbackCoordinatesStub(self._channels[-1])
            call = self._reports[address] = stub.ReportDetections()
        return call

    async def replied(self, request: detection_pb2.DetectionRequest) -> None:
        report = detection_pb2.DetectionReport(request_id=request.request_id, camera_id=self.camera_id, final=True)
        report.capture_time.GetCurrentTime()
        await self._report_stream(request.callback_address).write(report)


class _BareListener(detection_pb2_grpc.CallbackCoordinatesServicer):
    def __init__(self) -> None:
        #: request id -> [reports still to come, future set by the last, loop time of the first]
        self.waiting: dict[str, list[Any]] = {}

    async def ReportDetections(
        self,
        request_iterator: AsyncIterator[detection_pb2.DetectionReport],
        context: aio.ServicerContext[Any, Any],
    ) -> None:
        loop = asyncio.get_running_loop()
        async for report in request_iterator:
            entry = self.waiting.get(report.request_id)
            if entry is None:
                continue
            if entry[2] is None:
                entry[2] = loop.time()
            entry[0] -= 1
            if entry[0] <= 0:
                del self.waiting[report.request_id]
                entry[1].set_result(None)


async def paced(count: int, rate: float) -> AsyncIterator[int]:
    """0 .. count-1, each at its time on a fixed schedule of `rate` a second from the first."""
    loop = asyncio.get_running_loop()
    start = loop.time()
    for i in range(count):
        delay = start + i / rate - loop.time()
        if delay > 0:
            await asyncio.sleep(delay)
        yield i


async def bare_robot(args: argparse.Namespace) -> None:
    """Requests at a fixed rate, one at a time: write it, read the reply, wait for every camera's report.

    --warmup requests go back to back first and are not counted. Paced requests are timed from
    their scheduled send time (as the service benchmark's DRVS robot is); with --rate 0 they go back
    to back, each timed from its send."""
    listener = _BareListener()
    server = _grpc.new_server()
    detection_pb2_grpc.add_CallbackCoordinatesServicer_to_server(listener, server)
    port = _grpc.bind(server, "127.0.0.1:0")
    await server.start()
    async with _grpc.insecure_channel(args.server) as channel:
        call = detection_pb2_grpc.DetectObjectBoundaryStub(channel).DetectStream()
        template = one_camera_request(0, f"127.0.0.1:{port}")
        loop = asyncio.get_running_loop()
        first: list[float] = []
        latencies: list[float] = []

        async def one(request_id: str, t0: float | None = None) -> None:
            t0 = loop.time() if t0 is None else t0
            done = loop.create_future()
            entry: list[Any] = [args.cameras, done, None]
            listener.waiting[request_id] = entry
            template.request_id = request_id
            await call.write(template)
            await call.read()
            await asyncio.wait_for(done, 5)
            first.append((entry[2] - t0) * 1000)
            latencies.append((loop.time() - t0) * 1000)

        for i in range(args.warmup):
            await one(f"w{i}")
        first.clear()
        latencies.clear()  # the warm-up ran back to back: only the paced requests count
        start = loop.time()
        cpu_start = time.process_time()
        if args.rate > 0:
            async for i in paced(args.requests, args.rate):
                await one(f"r{i}", start + i / args.rate)
        else:
            for i in range(args.requests):
                await one(f"r{i}")
        cpu = time.process_time() - cpu_start
        wall = loop.time() - start
        call.cancel()
    await server.stop(0.5)
    print(
        "DONE "
        + json.dumps(
            {
                "cpu_s": cpu,
                "wall_s": wall,
                "requests": args.requests,
                "completed": len(latencies),
                "first_report_ms_p50": percentile(first, 50),
                "last_report_ms_p50": percentile(latencies, 50),
                "first_ms": first,
                "last_ms": latencies,
                "peak_rss_bytes": peak_rss_bytes(os.getpid()),
            }
        ),
        flush=True,
    )


async def idle_robot(args: argparse.Namespace) -> None:
    """A robot process that only wakes at the request rate and does nothing: the floor of any
    asyncio robot on a schedule."""
    loop = asyncio.get_running_loop()
    start = loop.time()
    cpu_start = time.process_time()
    async for _ in paced(args.requests, args.rate):
        pass
    print("DONE " + json.dumps({"cpu_s": time.process_time() - cpu_start, "wall_s": loop.time() - start}), flush=True)


def _server_main(args: argparse.Namespace) -> int:
    asyncio.run(serve_detection(_BareServer(args.camera, args.streams if args.fanout == "one" else 1, args.fanout)))
    return 0


def _camera_main(args: argparse.Namespace) -> int:
    asyncio.run(serve_detection(_BareCamera(args.id)))
    return 0


def add_bare_parsers(sub: Any) -> None:
    s = sub.add_parser("bare-server", help="(internal) bare grpc.aio: answer and forward each request")
    s.add_argument("--camera", action="append", required=True, help="camera HOST:PORT (repeat)")
    s.add_argument("--fanout", choices=["all", "one"], default="all", help="every camera, or one in turn")
    s.add_argument("--streams", type=int, default=1, help="with --fanout one: streams (cameras) to the one target")
    s.set_defaults(func=_server_main)
    c = sub.add_parser("bare-camera", help="(internal) bare grpc.aio: ack each request, report to its robot")
    c.add_argument("--id", required=True)
    c.set_defaults(func=_camera_main)
    r = sub.add_parser("bare-robot", help="(internal) bare grpc.aio robot: request, reply, reports")
    r.add_argument("--server", required=True)
    r.add_argument("--cameras", type=int, required=True, help="reports to wait for per request")
    r.add_argument("--requests", type=int, required=True)
    r.add_argument("--rate", type=float, required=True, help="requests a second (0: back to back)")
    r.add_argument("--warmup", type=int, default=50, help="back-to-back requests first, not counted")
    r.set_defaults(func=lambda args: asyncio.run(bare_robot(args)) or 0)
    i = sub.add_parser("idle-robot", help="(internal) a robot that only wakes at the request rate")
    i.add_argument("--requests", type=int, required=True)
    i.add_argument("--rate", type=float, required=True)
    i.set_defaults(func=lambda args: asyncio.run(idle_robot(args)) or 0)

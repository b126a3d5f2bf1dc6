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
import secrets
import time
from collections.abc import AsyncIterator
from typing import Any

from grpc import aio

from drvs.tools.fakes import AckingCamera
from drvs.v1 import detection_pb2, detection_pb2_grpc, geometry_pb2
from drvs.wire import _grpc

from .common import peak_rss_bytes
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


async def capture_snapshots(
    server: str, filter_def: str, region: tuple[float, float, float, float], rate: float, cameras: int
) -> list[detection_pb2.DetectionReply]:
    """Real snapshot replies, as the DRVS server at `server` sends them to a robot: a fused track
    (boxes only) of one second over `region` on a bare DetectStream, the replies that merged every
    camera kept as they came (the first reply, the dispatch, left out)."""
    x0, y0, x1, y1 = region
    request = detection_pb2.DetectionRequest(
        request_id=f"{secrets.token_urlsafe(3)}0",  # as long as a DRVS client's first id
        robot_id="bench",
        filter_def=filter_def,
        region=geometry_pb2.Region(box=geometry_pb2.Box(x_lower=x0, y_lower=y0, x_upper=x1, y_upper=y1)),
        continuous=detection_pb2.ContinuousMode(rate_hz=rate, duration_s=1.0),
        omit_outlines=True,
        fusion=detection_pb2.FusionOptions(compact_geometry=True),  # as a DrvsClient asks
    )
    kept: list[detection_pb2.DetectionReply] = []
    async with _grpc.insecure_channel(server) as channel:
        call = detection_pb2_grpc.DetectObjectBoundaryStub(channel).DetectStream()
        await call.write(request)
        async for reply in call:
            if reply.HasField("error"):
                raise SystemExit(f"the DRVS server refused the capture track: {reply.error.message}")
            if not reply.HasField("snapshot"):
                continue
            if len(reply.snapshot.camera_ids) == cameras and not reply.snapshot.final:
                kept.append(reply)
            if reply.snapshot.final:
                break
        call.cancel()
    if not kept:
        raise SystemExit(f"no snapshot from {server} merged {cameras} cameras")
    return kept


class _TrackFloorServer(detection_pb2_grpc.DetectObjectBoundaryServicer):
    """Answers each request on the stream with snapshots pushed at its rate for its duration, as
    DRVS's server answers a track (one at half of each period, the last final): captured DRVS
    replies in turn, each with its sequence, final flag and the request's id set. Nothing else."""

    def __init__(self, snapshots: list[detection_pb2.DetectionReply]) -> None:
        self._snapshots = snapshots

    async def DetectStream(
        self,
        request_iterator: AsyncIterator[detection_pb2.DetectionRequest],
        context: aio.ServicerContext[Any, Any],
    ) -> AsyncIterator[detection_pb2.DetectionReply]:
        loop = asyncio.get_running_loop()
        async for request in request_iterator:
            rate = request.continuous.rate_hz
            count = round(request.continuous.duration_s * rate) + 1
            yield detection_pb2.DetectionReply(request_id=request.request_id, camera_ids=["bare0", "bare1"])
            t0 = loop.time()
            for k in range(count):
                delay = t0 + (k + 0.5) / rate - loop.time()
                if delay > 0:
                    await asyncio.sleep(delay)
                reply = detection_pb2.DetectionReply()
                reply.CopyFrom(self._snapshots[k % len(self._snapshots)])
                reply.request_id = request.request_id
                reply.snapshot.sequence = k
                reply.snapshot.final = k == count - 1
                yield reply


async def track_floor_server(args: argparse.Namespace) -> None:
    snapshots = await capture_snapshots(args.drvs_server, args.filter, args.region, args.rate, args.cameras)
    sizes = sorted(s.ByteSize() for s in snapshots)
    print(f"CAPTURED {len(snapshots)} snapshot replies of {sizes[0]}-{sizes[-1]} bytes", flush=True)
    await serve_detection(_TrackFloorServer(snapshots))


async def follow_track(call: aio.StreamStreamCall[Any, Any], request_id: str, snapshots: int, rate: float) -> int:
    """One track of `snapshots` at `rate` on the DetectStream `call`, its snapshot messages only
    received (protobuf-parsed by the stub, nothing more) until the final one; returns how many came."""
    duration = max(1, snapshots - 1) / rate
    continuous = detection_pb2.ContinuousMode(rate_hz=rate, duration_s=duration)
    await call.write(detection_pb2.DetectionRequest(request_id=request_id, continuous=continuous))
    received = 0
    async for reply in call:
        if reply.HasField("snapshot"):
            received += 1
            if reply.snapshot.final:
                break
    return received


async def track_floor_robot(args: argparse.Namespace) -> None:
    """The floor of a robot that follows a track: one request on a long-lived DetectStream, then only
    receiving the snapshot messages pushed on it (protobuf-parsed by the stub, nothing more) until
    the final one. A short stream first (--warmup-snapshots), as the DRVS track robot's warm-up;
    measured from START (before the request) to the final snapshot, as it is."""
    loop = asyncio.get_running_loop()
    prefix = secrets.token_urlsafe(3)
    async with _grpc.insecure_channel(args.server) as channel:
        call = detection_pb2_grpc.DetectObjectBoundaryStub(channel).DetectStream()
        print("READY 0", flush=True)

        await follow_track(call, f"{prefix}0", args.warmup_snapshots, args.rate)
        print("START", flush=True)
        cpu_start = time.process_time()
        start = loop.time()
        received = await follow_track(call, f"{prefix}1", args.requests, args.rate)
        cpu = time.process_time() - cpu_start
        wall = loop.time() - start
        call.cancel()
    print(
        "DONE " + json.dumps({"cpu_s": cpu, "wall_s": wall, "requests": args.requests, "snapshots": received}),
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


def _region(text: str) -> tuple[float, float, float, float]:
    x0, y0, x1, y1 = (float(v) for v in text.split(","))
    return x0, y0, x1, y1


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
    ts = sub.add_parser("track-floor-server", help="(internal) bare grpc.aio: push captured DRVS snapshots")
    ts.add_argument("--drvs-server", required=True, help="the DRVS server to capture real snapshot replies from")
    ts.add_argument("--filter", required=True)
    ts.add_argument("--region", type=_region, required=True, help="X0,Y0,X1,Y1")
    ts.add_argument("--rate", type=float, required=True, help="the capture track's rate")
    ts.add_argument("--cameras", type=int, required=True, help="cameras a captured snapshot must merge")
    ts.set_defaults(func=lambda args: asyncio.run(track_floor_server(args)) or 0)
    tr = sub.add_parser("track-floor-robot", help="(internal) bare grpc.aio robot: one request, snapshots received")
    tr.add_argument("--server", required=True)
    tr.add_argument("--requests", type=int, required=True, help="snapshots to receive")
    tr.add_argument("--rate", type=float, required=True, help="snapshots a second")
    tr.add_argument("--warmup-snapshots", type=int, default=10, help="a short stream of these first, not counted")
    tr.set_defaults(func=lambda args: asyncio.run(track_floor_robot(args)) or 0)
    i = sub.add_parser("idle-robot", help="(internal) a robot that only wakes at the request rate")
    i.add_argument("--requests", type=int, required=True)
    i.add_argument("--rate", type=float, required=True)
    i.set_defaults(func=lambda args: asyncio.run(idle_robot(args)) or 0)

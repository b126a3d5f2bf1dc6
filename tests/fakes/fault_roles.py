"""Stand-in processes for the fault tests, run as `python tests/fakes/fault_roles.py ROLE ...` so each is a
real process on real sockets (not collected by pytest: the name does not start with test_).

slow-camera: a camera node that registers with a DRVS server, keeps its lease, accepts every
    forwarded request (after --accept-delay) and sends its final report only after --report-delay:
    a camera whose detection takes seconds. drvs-camera has no option to make detection slow, and
    no source is slow enough to detect on (even a 100-megapixel frame takes well under a second).
stalled-camera: a hostile camera: it registers and heartbeats (every --heartbeat seconds), and never
    reads the request streams the server opens to it. It prints `STREAM n OPENED` and `STREAM n
    CLOSED` as the server opens and ends them.
probe-robot: a DrvsClient that sends one single-shot request every --period seconds and prints one
    `RESULT {json}` line per request (for the network-namespace test, where the robot must run
    inside a namespace of its own).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import sys
import time
from collections.abc import AsyncIterator
from typing import Any

import grpc
from grpc import aio

from drvs.core.errors import DrvsError
from drvs.robot import DrvsClient
from drvs.tools.fakes import AckingCamera, register_message, serve_camera
from drvs.v1 import detection_pb2, detection_pb2_grpc, registry_pb2, registry_pb2_grpc
from drvs.wire._cli import shutdown_event

YELLOW = "hsv_014110130035225200"


class _Reporter:
    """One report stream per robot address, as a camera node keeps them."""

    def __init__(self) -> None:
        self._channels: dict[str, aio.Channel] = {}
        self._calls: dict[str, Any] = {}
        self._lock = asyncio.Lock()

    async def send(self, address: str, report: detection_pb2.DetectionReport) -> None:
        async with self._lock:
            call = self._calls.get(address)
            if call is None or call.done():
                channel = self._channels.get(address) or aio.insecure_channel(address)
                self._channels[address] = channel
                call = detection_pb2_grpc.CallbackCoordinatesStub(channel).ReportDetections()
                self._calls[address] = call
            await asyncio.wait_for(call.write(report), 5.0)

    async def close(self) -> None:
        for call in self._calls.values():
            call.cancel()
        for channel in self._channels.values():
            await channel.close()


class _SlowCamera(AckingCamera):
    def __init__(self, camera_id: str, accept_delay: float, report_delay: float) -> None:
        super().__init__(camera_id)
        self.accept_delay = accept_delay
        self.report_delay = report_delay
        self.reporter = _Reporter()
        self.jobs: set[asyncio.Task[None]] = set()
        self.callback = ""

    async def _report_later(self, request_id: str, callback: str, key: bytes) -> None:
        await asyncio.sleep(self.report_delay)  # the "detection" that takes seconds
        report = detection_pb2.DetectionReport(
            request_id=request_id, camera_id=self.camera_id, sequence=0, final=True, report_key=key
        )
        report.capture_time.FromNanoseconds(time.time_ns())
        try:
            await self.reporter.send(callback, report)
            print(f"REPORTED {request_id}", flush=True)
        except (grpc.RpcError, asyncio.TimeoutError, asyncio.InvalidStateError) as exc:
            print(f"REPORT FAILED {request_id}: {exc!r}", flush=True)

    async def accept(self, message: detection_pb2.DetectionRequest) -> detection_pb2.DetectionReply:
        # The server elides nothing towards cameras, but keep the last callback like a real node would.
        self.callback = message.callback_address or self.callback
        print(f"REQUEST {message.request_id}", flush=True)
        if self.accept_delay:
            await asyncio.sleep(self.accept_delay)
        job = asyncio.get_running_loop().create_task(
            self._report_later(message.request_id, self.callback, message.report_key)
        )
        self.jobs.add(job)
        job.add_done_callback(self.jobs.discard)
        return await super().accept(message)


class _StalledCamera(_SlowCamera):
    def __init__(self, camera_id: str) -> None:
        super().__init__(camera_id, 0.0, 0.0)
        self.streams = 0

    async def DetectBatches(
        self,
        request_iterator: AsyncIterator[detection_pb2.DetectionRequests],
        context: aio.ServicerContext[Any, Any],
    ) -> AsyncIterator[detection_pb2.DetectionReplies]:
        self.streams += 1
        n = self.streams
        print(f"STREAM {n} OPENED", flush=True)
        try:
            await asyncio.Event().wait()  # never reads: the server's writes pile up, unread
        finally:
            print(f"STREAM {n} CLOSED", flush=True)
        yield detection_pb2.DetectionReplies()  # never reached


async def slow_camera(args: argparse.Namespace) -> None:
    stop = shutdown_event()
    camera = (
        _StalledCamera(args.id)
        if args.role == "stalled-camera"
        else _SlowCamera(args.id, args.accept_delay, args.report_delay)
    )
    server, address = await serve_camera(camera)
    print(f"LISTENING {address}", flush=True)
    register = register_message(args.id, x=args.x, address=address)

    secret = ""

    async def keep_registered(channel: aio.Channel) -> None:
        nonlocal secret
        stub = registry_pb2_grpc.RegisterVisionServiceStub(channel)
        reply = await stub.Register(register, timeout=5)
        lease, secret = reply.lease_ttl_s, reply.registration_secret
        print(f"REGISTERED {args.id} lease {lease:g}", flush=True)
        while True:
            await asyncio.sleep(args.heartbeat or lease / 3)
            try:
                await stub.Heartbeat(
                    registry_pb2.HeartbeatRequest(camera_id=args.id, registration_secret=secret), timeout=lease / 3
                )
            except grpc.RpcError:
                register.registration_secret = secret  # the same camera coming back
                reply = await stub.Register(register, timeout=5)
                lease, secret = reply.lease_ttl_s, reply.registration_secret

    async with aio.insecure_channel(args.server) as channel:
        registrar = asyncio.get_running_loop().create_task(keep_registered(channel))
        await stop.wait()
        registrar.cancel()
        await asyncio.gather(registrar, return_exceptions=True)
        await registry_pb2_grpc.RegisterVisionServiceStub(channel).Deregister(
            registry_pb2.DeregisterRequest(camera_id=args.id, registration_secret=secret), timeout=2
        )
    for job in list(camera.jobs):
        job.cancel()
    await asyncio.gather(*camera.jobs, return_exceptions=True)
    await camera.reporter.close()
    await server.stop(0.5)


async def probe_robot(args: argparse.Namespace) -> None:
    stop = shutdown_event()
    region = [float(v) for v in args.region.split(",")]
    async with DrvsClient(args.server, robot_id=args.robot_id, listen=args.listen) as client:
        print(f"READY {client.callback_address}", flush=True)
        loop = asyncio.get_running_loop()
        n = 0
        while not stop.is_set():
            n += 1
            t0 = loop.time()
            line: dict[str, Any] = {"n": n}
            try:
                sub = await client.subscribe(YELLOW, region, timeout_s=args.timeout, rpc_timeout_s=args.timeout)
                result = await sub.collect()
                line |= {
                    "cameras": sorted(result.camera_ids),
                    "complete": result.complete,
                    "missing": sorted(result.missing_cameras),
                    "reported": sorted(result.finished_cameras),
                    "detections": len(result.detections),
                    "errors": result.errors,
                }
            except DrvsError as exc:
                line |= {"failed": type(exc).__name__, "message": str(exc)}
            line["seconds"] = round(loop.time() - t0, 3)
            print("RESULT " + json.dumps(line), flush=True)
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(stop.wait(), max(0.0, args.period - (loop.time() - t0)))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="fault_roles")
    sub = parser.add_subparsers(dest="role", required=True)
    s = sub.add_parser("slow-camera")
    s.add_argument("--server", required=True)
    s.add_argument("--id", default="slow")
    s.add_argument("--x", type=float, default=40.0, help="camera position along x; it sees x-6..x+6, y 1.5..7.5")
    s.add_argument("--accept-delay", type=float, default=0.0)
    s.add_argument("--report-delay", type=float, default=3.0)
    s.add_argument("--heartbeat", type=float, default=0.0, help="seconds between heartbeats (default: lease / 3)")
    s.set_defaults(run=slow_camera)
    h = sub.add_parser("stalled-camera")
    h.add_argument("--server", required=True)
    h.add_argument("--id", default="stalled")
    h.add_argument("--x", type=float, default=40.0, help="camera position along x; it sees x-6..x+6, y 1.5..7.5")
    h.add_argument("--heartbeat", type=float, default=0.0, help="seconds between heartbeats (default: lease / 3)")
    h.set_defaults(run=slow_camera)
    p = sub.add_parser("probe-robot")
    p.add_argument("--server", required=True)
    p.add_argument("--listen", required=True)
    p.add_argument("--robot-id", default="probe")
    p.add_argument("--region", required=True, help="X0,Y0,X1,Y1")
    p.add_argument("--period", type=float, default=0.3)
    p.add_argument("--timeout", type=float, default=1.5)
    p.set_defaults(run=probe_robot)
    args = parser.parse_args(argv)
    asyncio.run(args.run(args))
    return 0


if __name__ == "__main__":
    sys.exit(main())

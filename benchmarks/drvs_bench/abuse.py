"""`drvs-bench load-abuse`: the load benchmark's abuse mix (issue 14), beside the normal robots.

One process, loopback only, bounded in count and in time (--seconds), that does what a hostile or
broken client on the building's network could do cheaply:

- a **registration flood**: up to --registrations fake cameras, far from the robots' region (so
  they measure the cost of the flood, not a routing capture), at up to --registration-rate a second;
- **oversized regions**: single-shot requests with a --vertices-point polygon over all three real
  cameras, at --oversized-rate a second, whose reports go to a stalled reader;
- **stalled readers**: --stalled DetectStream calls that write requests and never read a reply, and
  a report listener (CallbackCoordinates) that accepts the cameras' report streams and never reads
  them, fed by the oversized requests and by --continuous continuous requests;
- **teleporting poses**: --teleports mobile cameras (their address the stalled listener) that jump
  between far away and the middle of the robots' region at every pose update they may send, to be
  routed the robots' requests and answer none;
- **report-id floods**: --report-floods report streams into the server's own report intake, each
  --flood-reports reports with --flood-id-bytes request ids (forged: no request has them);
- **live-view floods** (with --live-view URL): --view-floods Foxglove clients that publish
  --view-message-bytes messages as fast as the view takes them (on their own channels and on the
  server's `/drvs/rpc/replies`), and as many that subscribe to every channel and never read;
- **registry churn**: --churn ids that register and deregister in turn, at --churn-rate cycles a
  second in all (on an etcd registry, each cycle is etcd writes).

It only measures what it was allowed to do: at the end it prints DONE with how many of each it
sent and how many the server refused (any RPC error or an error reply).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import math
import re
import time
from collections.abc import AsyncIterator
from typing import Any

import grpc
from grpc import aio

from drvs.core.geometry import homography_from_pose
from drvs.core.mobile import Mount
from drvs.v1 import detection_pb2, detection_pb2_grpc, geometry_pb2, registry_pb2, registry_pb2_grpc
from drvs.wire import _grpc

from .common import YELLOW
from .helpers import grid_position

#: The flood's fake cameras sit this far from the robots' region (metres, along x and y).
FLOOD_OFFSET_M = 5000.0
#: Registrations in flight at once.
FLOOD_CALLERS = 8
#: Robot ids the oversized and continuous requests take in turn (ids cost an attacker nothing).
ROBOT_IDS = 16
#: The middle of the robots' region (ALL_REGION), where a teleporting camera jumps to.
REGION_CENTRE = (20.0, 5.0)


class _StalledListener(detection_pb2_grpc.CallbackCoordinatesServicer):
    """Accepts report streams and never reads them: the camera's writes back up."""

    def __init__(self, stop: asyncio.Event) -> None:
        self.stop = stop
        self.streams = 0

    async def ReportDetections(
        self,
        request_iterator: AsyncIterator[detection_pb2.DetectionReport],
        context: aio.ServicerContext[Any, Any],
    ) -> None:
        self.streams += 1
        await self.stop.wait()


def big_polygon(vertices: int, cx: float = 20.0, cy: float = 4.0, r: float = 30.0) -> geometry_pb2.Region:
    """A convex polygon of `vertices` points, over all three cameras of the benchmark scene."""
    points = [
        geometry_pb2.Point2(
            x=cx + r * math.cos(2 * math.pi * k / vertices), y=cy + r * math.sin(2 * math.pi * k / vertices)
        )
        for k in range(vertices)
    ]
    return geometry_pb2.Region(polygon=geometry_pb2.Polygon(points=points))


async def abuse(args: argparse.Namespace) -> None:
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    listener = _StalledListener(stop)
    server = _grpc.new_server()
    detection_pb2_grpc.add_CallbackCoordinatesServicer_to_server(listener, server)
    port = _grpc.bind(server, "127.0.0.1:0")
    await server.start()
    stalled_callback = f"127.0.0.1:{port}"
    counts = {
        "registrations_sent": 0,
        "registrations_refused": 0,
        "oversized_sent": 0,
        "oversized_refused": 0,
        "continuous_sent": 0,
        "continuous_refused": 0,
        "stalled_streams": 0,
        "stalled_requests_written": 0,
        "stalled_write_errors": 0,
        "teleports_sent": 0,
        "teleports_refused": 0,
        "teleport_registrations_refused": 0,
        "flood_reports_sent": 0,
        "flood_streams_refused": 0,
        "view_messages_sent": 0,
        "view_clients_refused": 0,
        "view_stalled_subscribers": 0,
        "churn_cycles_sent": 0,
        "churn_refused": 0,
    }
    refusals: dict[str, int] = {}

    def refused(kind: str, what: str) -> None:
        counts[f"{kind}_refused"] += 1
        what = re.sub(r"\d+", "N", what[:160])  # one key per kind of refusal, not per figure in it
        refusals[what] = refusals.get(what, 0) + 1

    end = loop.time() + args.seconds
    print("READY", flush=True)
    async with _grpc.insecure_channel(args.server) as channel:
        registry = registry_pb2_grpc.RegisterVisionServiceStub(channel)
        detect = detection_pb2_grpc.DetectObjectBoundaryStub(channel)

        next_id = iter(range(args.registrations))

        async def flood() -> None:
            """One of FLOOD_CALLERS registrars: together at most --registration-rate a second."""
            for i in next_id:
                if loop.time() >= end:
                    return
                t0 = loop.time()
                x, y = grid_position(i)
                h = homography_from_pose((x + FLOOD_OFFSET_M, y + FLOOD_OFFSET_M, 3.0), 90.0, 40.0, 60.0, (640, 480))
                counts["registrations_sent"] += 1
                try:
                    await registry.Register(
                        registry_pb2.RegisterRequest(
                            camera_id=f"abuse{i}", address=stalled_callback,
                            homography=registry_pb2.Homography(m=h.to_list()), image_width=640, image_height=480,
                            max_range_m=6.0, detector_kinds=["hsv"],
                        ),
                        timeout=5,
                    )  # fmt: skip
                except grpc.RpcError as exc:
                    refused("registrations", f"{exc.code().name}: {exc.details()}")
                await asyncio.sleep(max(0.0, t0 + FLOOD_CALLERS / args.registration_rate - loop.time()))

        async def single(kind: str, message: detection_pb2.DetectionRequest) -> None:
            counts[f"{kind}_sent"] += 1
            try:
                reply = await detect.DetectObjects(message, timeout=5)
            except grpc.RpcError as exc:
                refused(kind, f"{exc.code().name}: {exc.details()}")
                return
            if reply.HasField("error"):
                refused(kind, f"{reply.error.code}: {reply.error.message}")

        async def oversized() -> None:
            region = big_polygon(args.vertices)
            tasks = []
            i = 0
            while loop.time() < end and i < int(args.oversized_rate * args.seconds):
                message = detection_pb2.DetectionRequest(
                    request_id=f"big{i}", robot_id=f"abuser{i % ROBOT_IDS}", filter_def=YELLOW, region=region,
                    callback_address=stalled_callback,
                )  # fmt: skip
                tasks.append(loop.create_task(single("oversized", message)))
                i += 1
                await asyncio.sleep(1 / args.oversized_rate)
            await asyncio.gather(*tasks)

        async def continuous() -> None:
            for i in range(args.continuous):
                message = detection_pb2.DetectionRequest(
                    request_id=f"cont{i}", robot_id=f"abuser{i % ROBOT_IDS}", filter_def=YELLOW, region=big_polygon(8),
                    callback_address=stalled_callback,
                    continuous=detection_pb2.ContinuousMode(rate_hz=20.0, duration_s=max(1.0, args.seconds)),
                )  # fmt: skip
                await single("continuous", message)

        small = big_polygon(8)

        async def stalled(k: int) -> None:
            call = detect.DetectStream()
            counts["stalled_streams"] += 1
            try:
                for i in range(args.stalled_requests):
                    if loop.time() >= end:
                        break
                    message = detection_pb2.DetectionRequest(
                        request_id=f"st{k}-{i}", robot_id=f"abuser-stalled{k}", filter_def=YELLOW,
                        region=small, callback_address=stalled_callback,
                    )  # fmt: skip
                    await asyncio.wait_for(call.write(message), timeout=max(0.01, end - loop.time()))
                    counts["stalled_requests_written"] += 1
                    await asyncio.sleep(0.01)
            except (grpc.RpcError, asyncio.TimeoutError, aio.AioRpcError):
                counts["stalled_write_errors"] += 1
            await asyncio.sleep(max(0.0, end - loop.time()))  # holds the stream open, never reading
            call.cancel()

        def mobile_registration(camera_id: str) -> registry_pb2.RegisterRequest:
            base = Mount(0.1, 0.0, 0.8, 0.0, 30.0, hfov_deg=70.0).base_homography((640, 480))
            return registry_pb2.RegisterRequest(
                camera_id=camera_id, address=stalled_callback, homography=registry_pb2.Homography(m=base.to_list()),
                image_width=640, image_height=480, max_range_m=6.0, detector_kinds=["hsv"], mobile=True,
            )  # fmt: skip

        async def teleport(k: int) -> None:
            """A mobile camera that jumps 5 km and back at every update the server lets it send."""
            camera_id = f"teleport{k}"
            try:
                reply = await registry.Register(mobile_registration(camera_id), timeout=5)
            except grpc.RpcError as exc:
                refused("teleport_registrations", f"{exc.code().name}: {exc.details()}")
                return
            interval = max(0.02, reply.min_pose_interval_s)
            i = 0
            while loop.time() < end:
                far = i % 2 == 0
                x, y = (REGION_CENTRE[0] + FLOOD_OFFSET_M, REGION_CENTRE[1]) if far else REGION_CENTRE
                counts["teleports_sent"] += 1
                try:
                    await registry.UpdatePose(
                        registry_pb2.UpdatePoseRequest(
                            camera_id=camera_id, registration_secret=reply.registration_secret,
                            pose=geometry_pb2.Pose2(x=x, y=y, yaw=0.0), pose_time_unix=time.time(),
                        ),
                        timeout=5,
                    )  # fmt: skip
                except grpc.RpcError as exc:
                    refused("teleports", f"{exc.code().name}: {exc.details()}")
                i += 1
                await asyncio.sleep(interval)

        async def report_flood(k: int) -> None:
            """Forged reports with huge request ids into the server's report intake."""
            big = "r" * args.flood_id_bytes

            async def reports() -> AsyncIterator[detection_pb2.DetectionReport]:
                for i in range(args.flood_reports):
                    if loop.time() >= end:
                        return
                    counts["flood_reports_sent"] += 1
                    yield detection_pb2.DetectionReport(
                        request_id=f"{big}{k}-{i}", camera_id="cam0", sequence=i, final=True
                    )
                    await asyncio.sleep(0)

            callback = detection_pb2_grpc.CallbackCoordinatesStub(channel)
            try:
                async for _ in callback.ReportDetections(reports(), timeout=max(1.0, end - loop.time())):
                    pass
            except grpc.RpcError as exc:
                refused("flood_streams", f"report flood: {exc.code().name}: {(exc.details() or '')[:120]}")

        async def churn(k: int) -> None:
            """Register and deregister one id in turn: each cycle is registry (etcd) writes."""
            per_caller = max(args.churn_rate / max(1, args.churn), 0.01)
            while loop.time() < end:
                t0 = loop.time()
                counts["churn_cycles_sent"] += 1
                try:
                    reply = await registry.Register(mobile_registration(f"churn{k}"), timeout=5)
                    await registry.Deregister(
                        registry_pb2.DeregisterRequest(
                            camera_id=f"churn{k}", registration_secret=reply.registration_secret
                        ),
                        timeout=5,
                    )
                except grpc.RpcError as exc:
                    refused("churn", f"{exc.code().name}: {exc.details()}")
                await asyncio.sleep(max(0.0, t0 + 1 / per_caller - loop.time()))

        jobs = [
            *(flood() for _ in range(FLOOD_CALLERS)),
            oversized(),
            continuous(),
            *(stalled(k) for k in range(args.stalled)),
            *(teleport(k) for k in range(args.teleports)),
            *(report_flood(k) for k in range(args.report_floods)),
            *(churn(k) for k in range(args.churn)),
            *((view_flood(args, counts, refusals, end),) if args.live_view and args.view_floods else ()),
        ]
        await asyncio.wait_for(asyncio.gather(*jobs, return_exceptions=True), timeout=args.seconds + 30)
    stop.set()
    counts["stalled_report_streams"] = listener.streams
    await server.stop(0.5)
    print("DONE " + json.dumps({**counts, "refusals": refusals}), flush=True)


async def view_flood(args: argparse.Namespace, counts: dict[str, int], refusals: dict[str, int], end: float) -> None:
    """--view-floods publishers and as many subscribers that never read, on the live view."""
    from drvs.live.foxglove_client import FoxgloveClient

    loop = asyncio.get_running_loop()
    payload = b"x" * args.view_message_bytes

    async def publisher(k: int) -> None:
        try:
            async with await FoxgloveClient.connect(args.live_view) as client:
                channels = [
                    await client.advertise(f"/abuse/{k}", "json", "abuse"),
                    await client.advertise("/drvs/rpc/replies", "json", "drvs.rpc"),
                ]
                i = 0
                while loop.time() < end:
                    await asyncio.wait_for(client.publish(channels[i % 2], payload), max(0.01, end - loop.time()))
                    counts["view_messages_sent"] += 1
                    i += 1
                    await asyncio.sleep(0)
        except Exception as exc:  # a refusal or a dropped connection: what the view did to the flood
            counts["view_clients_refused"] += 1
            what = f"view publisher: {type(exc).__name__}: {str(exc)[:120]}"
            refusals[what] = refusals.get(what, 0) + 1

    async def stalled_subscriber() -> None:
        try:
            client = await FoxgloveClient.connect(args.live_view)
        except Exception as exc:
            counts["view_clients_refused"] += 1
            what = f"view subscriber: {type(exc).__name__}: {str(exc)[:120]}"
            refusals[what] = refusals.get(what, 0) + 1
            return
        try:
            with contextlib.suppress(Exception):
                await client.subscribe(list(client.channels.values()))
            counts["view_stalled_subscribers"] += 1
            if client._reader is not None:  # stop reading: the view's backlog for this client grows
                client._reader.cancel()
            await asyncio.sleep(max(0.0, end - loop.time()))
        finally:
            with contextlib.suppress(Exception):
                await client.close()

    await asyncio.gather(
        *(publisher(k) for k in range(args.view_floods)),
        *(stalled_subscriber() for _ in range(args.view_floods)),
        return_exceptions=True,
    )


def add_abuse_parser(sub: Any) -> None:
    a = sub.add_parser("load-abuse", help="(internal) the load benchmark's abuse mix")
    a.add_argument("--server", required=True)
    a.add_argument("--seconds", type=float, required=True, help="how long the abuse lasts (it then stops)")
    a.add_argument("--registrations", type=int, default=2000, help="fake cameras registered at most")
    a.add_argument("--registration-rate", type=float, default=200.0, help="registrations a second at most")
    a.add_argument("--vertices", type=int, default=20000, help="points of each oversized region")
    a.add_argument("--oversized-rate", type=float, default=5.0, help="oversized requests a second")
    a.add_argument("--continuous", type=int, default=8, help="continuous requests reporting to the stalled reader")
    a.add_argument("--stalled", type=int, default=8, help="DetectStream calls that are never read")
    a.add_argument("--stalled-requests", type=int, default=500, help="requests written on each stalled stream")
    a.add_argument("--teleports", type=int, default=0, help="mobile cameras that teleport into the region")
    a.add_argument("--report-floods", type=int, default=0, help="forged report streams into the server's intake")
    a.add_argument("--flood-reports", type=int, default=300, help="reports on each forged report stream")
    a.add_argument("--flood-id-bytes", type=int, default=1_000_000, help="request id length of each forged report")
    a.add_argument("--live-view", default="", help="the server's live view (ws://HOST:PORT) to flood")
    a.add_argument("--view-floods", type=int, default=0, help="live-view publishers (and as many stalled subscribers)")
    a.add_argument("--view-message-bytes", type=int, default=65536, help="size of each published message")
    a.add_argument("--churn", type=int, default=0, help="ids that register and deregister in turn")
    a.add_argument("--churn-rate", type=float, default=50.0, help="register-deregister cycles a second in all")
    a.set_defaults(func=lambda args: asyncio.run(abuse(args)) or 0)

"""Reports go only where they belong: the robot takes a request's reports only from the cameras it
was dispatched to, each on its own stream; the callback the server checked is the one cameras dial;
and a request whose cameras failed, were skipped or are gone says so instead of reading as a
complete answer with nothing there. Hostile peers are built from the raw drvs.v1 stubs."""

from __future__ import annotations

import asyncio
import ipaddress
import secrets
from collections.abc import Sequence
from typing import Any

import grpc
import pytest
from grpc import aio
from shapely.geometry import box
from shapely.ops import unary_union

from drvs.core.errors import PermissionDenied
from drvs.core.net import parse_address
from drvs.robot import DrvsClient
from drvs.server import DrvsServer
from drvs.server.policy import CallbackPolicy, IPAddress
from drvs.sim.scene import RecordedCamera
from drvs.tools.launch import ManagedProcess, start_camera, start_server
from drvs.v1 import detection_pb2, detection_pb2_grpc, geometry_pb2, registry_pb2, registry_pb2_grpc
from drvs.wire.report_auth import KEY_BYTES, report_key
from tests.fakes import serve_camera
from tests.helpers import CAM1_REGION, CAM2_REGION, MAX_RANGE, YELLOW, CapturingCamera, detect_message, register_message


def _report(request_id: str, camera_id: str, sequence: int, final: bool, key: bytes = b"", x: float = 0.5) -> Any:
    """A report with one detection at (x, 5): the forged obstacle."""
    detection = detection_pb2.Detection(
        bounds=geometry_pb2.FloorBox(x_lower=x - 0.1, y_lower=4.9, x_upper=x + 0.1, y_upper=5.1),
        centroid=geometry_pb2.FloorPoint(x=x, y=5.0),
        ground_contact=geometry_pb2.FloorPoint(x=x, y=4.9),
    )
    return detection_pb2.DetectionReport(
        request_id=request_id,
        camera_id=camera_id,
        sequence=sequence,
        final=final,
        detections=[detection],
        report_key=key,
    )


async def _write_reports(callback: str, reports: list[Any]) -> list[str]:
    """Dial the robot's listener as anyone can, write `reports`, and return the request ids the
    robot told this stream to stop."""
    async with aio.insecure_channel(callback) as channel:
        call = detection_pb2_grpc.CallbackCoordinatesStub(channel).ReportDetections()
        for report in reports:
            await call.write(report)
        await call.done_writing()
        cancelled: list[str] = []
        async for control in call:
            cancelled.extend(control.cancelled_request_ids)
        return cancelled


@pytest.mark.slow
async def test_reports_only_from_dispatched_cameras_on_their_own_streams(
    recorded: dict[str, RecordedCamera],
) -> None:
    """A real camera (cam1) and a hostile registered one (evil, 20 m away) report to one robot. evil,
    dispatched a request once, holds its own key and nothing more: in cam1's name, in another
    camera's name, or without a key on its stream, its reports are rejected, and so is a stranger's
    with a guessed key; in its own name, for a request that was not dispatched to it, its report is
    ignored. A forged final in cam1's name ends nothing."""
    procs: list[ManagedProcess] = []
    evil = CapturingCamera()
    evil_server, evil_address = await serve_camera(evil)
    try:
        server, address = await start_server()
        procs.append(server)
        rec = recorded["cam1"]
        procs.append(await start_camera("cam1", rec.video, rec.homography_file, address, "--max-range", MAX_RANGE))
        async with aio.insecure_channel(address) as channel:
            registration = register_message("evil", x=20.0)
            registration.address = evil_address
            await registry_pb2_grpc.RegisterVisionServiceStub(channel).Register(registration)
        async with DrvsClient(address, robot_id="r", listen="127.0.0.1:0") as robot:
            lure = await robot.subscribe(YELLOW, CAM2_REGION, timeout_s=10)
            assert lure.camera_ids == ("evil",)
            forwarded = await asyncio.wait_for(evil.requests.get(), 10)
            # evil learns its own key, never the robot's secret.
            assert forwarded.request_id == lure.request_id and not forwarded.report_secret
            evil_key = forwarded.report_key
            assert len(evil_key) == KEY_BYTES
            # The callback cameras dial is the one the server checked.
            assert forwarded.callback_address == robot.callback_address
            sub = await robot.subscribe(YELLOW, CAM1_REGION, rate_hz=2, duration_s=2, timeout_s=10)
            assert sub.camera_ids == ("cam1",)
            rid = sub.request_id
            refused = await _write_reports(
                forwarded.callback_address,
                [
                    _report(rid, "cam1", 9, True, evil_key),  # cam1's name, evil's key: a forged final
                    _report(rid, "cam1", 9, True),  # cam1's name, no key: not cam1's stream
                    _report(rid, "cam2", 0, True, evil_key),  # another camera's name
                    _report(rid, "evil", 0, True, evil_key),  # its own name: not dispatched this request
                    _report(lure.request_id, "evil", 0, True, x=21.0),  # its own request: taken
                ],
            )
            stranger = await _write_reports(
                forwarded.callback_address, [_report(rid, "cam1", 9, True, secrets.token_bytes(KEY_BYTES))]
            )
            result = await sub.collect()
            lured = await lure.collect()
        assert refused == [rid] * 3 and stranger == [rid]  # told to stop, as for unknown requests
        assert robot.reports_rejected == 5
        cam1 = [r for r in result.reports if r.camera_id == "cam1"]
        # cam1's own five reports, in order, the last one final: the forged final ended nothing.
        assert [r.sequence for r in cam1] == [0, 1, 2, 3, 4] and [r.final for r in cam1] == [False] * 4 + [True]
        assert all(len(r.detections) == 2 for r in cam1) and len(result.reports) == 5 and result.complete
        assert all(d.centroid_xy != (0.5, 5.0) for d in result.detections)
        assert lured.complete and [d.centroid_xy for d in lured.detections] == [(21.0, 5.0)]
    finally:
        await evil_server.stop(0)
        for p in reversed(procs):
            await p.stop()


async def test_server_rewrites_a_callback_name_to_the_address_it_checked() -> None:
    """A robot names its callback by host name; the camera gets the address the name resolved to and
    was checked, so a later answer for the name (DNS rebinding) changes nothing."""
    evil = CapturingCamera()
    camera, camera_address = await serve_camera(evil)
    try:
        async with DrvsServer("127.0.0.1:0") as server, aio.insecure_channel(server.address) as channel:
            registration = register_message("cam1")
            registration.address = camera_address
            await registry_pb2_grpc.RegisterVisionServiceStub(channel).Register(registration)
            stub = detection_pb2_grpc.DetectObjectBoundaryStub(channel)
            request = detect_message(request_id="named", callback_address="localhost:4321")
            request.report_secret = b"s" * 16
            reply = await stub.DetectObjects(request)
            assert list(reply.camera_ids) == ["cam1"]
            forwarded = await asyncio.wait_for(evil.requests.get(), 10)
            host, port = parse_address(forwarded.callback_address)
            assert ipaddress.ip_address(host).is_loopback and port == 4321
            assert forwarded.report_key == report_key(b"s" * 16, "cam1") and not forwarded.report_secret
            # A secret longer than 64 bytes is refused, naming the field.
            request.request_id, request.report_secret = "long", b"s" * 65
            with pytest.raises(aio.AioRpcError) as err:
                await stub.DetectObjects(request)
            assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
            assert "report_secret: longer than 64 bytes" in (err.value.details() or "")
    finally:
        await camera.stop(0)


async def test_every_address_a_callback_name_resolves_to_must_pass() -> None:
    """Not any one of them: a name that resolves to the robot and to a third party is refused."""
    answers = {
        "robot.lan": ["10.0.0.5"],
        "split.lan": ["10.0.0.5", "192.0.2.7"],
        "net.lan": ["10.1.2.3", "10.9.9.9"],
    }

    async def resolve(host: str, port: int) -> list[IPAddress]:
        return [ipaddress.ip_address(a) for a in answers[host]]

    peer = ipaddress.ip_address("10.0.0.5")
    policy = CallbackPolicy(resolve=resolve)
    assert await policy.check("robot.lan:7000", peer) == "10.0.0.5:7000"
    assert await policy.check("10.0.0.5:7000", peer) == "10.0.0.5:7000"
    with pytest.raises(PermissionDenied, match=r"split\.lan \(resolves to 192\.0\.2\.7\) is not the requesting"):
        await policy.check("split.lan:7000", peer)
    with pytest.raises(PermissionDenied, match=r"net\.lan"):
        await policy.check("net.lan:7000", peer)
    # --allow-callback: every address in the allowed network, rewritten to the first.
    allowed = CallbackPolicy(["10.0.0.0/8"], resolve=resolve)
    assert await allowed.check("net.lan:7000", peer) == "10.1.2.3:7000"
    with pytest.raises(PermissionDenied):
        await allowed.check("split.lan:7000", peer)
    # --allow-any-callback: anything goes, unchanged.
    assert await CallbackPolicy(allow_any=True, resolve=resolve).check("split.lan:7000", peer) == "split.lan:7000"


async def test_skipped_and_vanished_cameras_are_missing_with_the_floor_nobody_saw() -> None:
    """A camera that cannot be reached: the first request hears UNAVAILABLE in its name; the next
    ones skip it and say so; once its lease runs out it is gone from routing but still named, with
    the part of the region only it saw. A camera that deregisters is simply gone."""
    server, address = await start_server("--lease-ttl", "1", "--forward-timeout", "1")
    try:
        async with (
            aio.insecure_channel(address) as channel,
            DrvsClient(address, robot_id="r", listen="127.0.0.1:0") as robot,
        ):
            registry = registry_pb2_grpc.RegisterVisionServiceStub(channel)
            first_reg = await registry.Register(register_message("dead"))  # 127.0.0.1:9: nothing listens there
            dead_floor = next(c.field_of_view for c in await robot.cameras()).intersection(box(*CAM1_REGION))
            first = await robot.detect(YELLOW, CAM1_REGION, timeout_s=5)
            assert first.camera_ids == ("dead",) and not first.complete
            assert first.camera_errors["dead"].code == "UNAVAILABLE" and first.detections == []
            skipped = await robot.detect(YELLOW, CAM1_REGION, timeout_s=5)
            assert skipped.camera_ids == () and skipped.missing_cameras == {"dead"} and not skipped.complete
            assert "skipped until it heartbeats" in skipped.camera_errors["dead"].message
            # Nobody asked: all of the region is uncovered, its floor with it.
            assert unary_union(skipped.uncovered).covers(dead_floor.buffer(-0.01))
            assert abs(sum(p.area for p in skipped.uncovered) - box(*CAM1_REGION).area) < 0.01
            # Its lease runs out (no heartbeat): still named, now as gone without deregistering.
            await server.wait_for_line(r"camera dead left routing: lease expired", timeout=10)
            gone = await robot.detect(YELLOW, CAM1_REGION, timeout_s=5)
            assert gone.camera_ids == () and not gone.complete
            assert "lease ran out without it deregistering" in gone.camera_errors["dead"].message
            assert abs(sum(p.area for p in gone.uncovered) - box(*CAM1_REGION).area) < 0.01
            # A region it never saw is complete; a camera that registers again and deregisters is gone.
            assert (await robot.detect(YELLOW, (30, 0, 31, 1), timeout_s=5)).complete
            # (The same anonymous registration, proving itself with its secret: the id is still held.)
            again = register_message("dead")
            again.registration_secret = first_reg.registration_secret
            reg = await registry.Register(again)
            await registry.Deregister(
                registry_pb2.DeregisterRequest(camera_id="dead", registration_secret=reg.registration_secret)
            )
            assert (await robot.detect(YELLOW, CAM1_REGION, timeout_s=5)).complete
    finally:
        await server.stop()


async def test_a_restarted_server_says_coverage_is_uncertain_for_a_lease() -> None:
    """Just after a start the server cannot know the cameras of its previous run that have not
    registered again: replies say so for a lease (or --warm-up), then stop saying it."""
    async with (
        DrvsServer("127.0.0.1:0", lease_ttl_s=30.0) as server,
        DrvsClient(server.address, robot_id="r", listen="127.0.0.1:0") as robot,
    ):
        result = await robot.detect(YELLOW, CAM1_REGION, timeout_s=1)
        assert 25 < result.coverage_uncertain_s <= 30
    async with (
        DrvsServer("127.0.0.1:0", lease_ttl_s=30.0, warm_up_s=0) as server,
        DrvsClient(server.address, robot_id="r", listen="127.0.0.1:0") as robot,
    ):
        assert (await robot.detect(YELLOW, CAM1_REGION, timeout_s=1)).coverage_uncertain_s == 0
    proc = await ManagedProcess.entry_point(
        "server", "drvs-server", "--listen", "127.0.0.1:0", "--warm-up", "-1"
    ).start()
    try:
        assert await proc.wait(timeout=30) == 2
        assert "warm_up_s (--warm-up): -1 must be in [0, 3600]" in proc.output()
    finally:
        await proc.stop()


class _LateCamera(CapturingCamera):
    """Accepts each request after `delay` seconds."""

    def __init__(self) -> None:
        super().__init__()
        self.delay = 0.0

    async def batch(self, requests: Sequence[detection_pb2.DetectionRequest]) -> None:
        # Seen on arrival: the server may cut a stream whose acceptance is overdue.
        await super().batch(requests)
        await asyncio.sleep(self.delay)


async def test_a_camera_the_server_answered_for_keeps_its_own_stream() -> None:
    """The server answers for a camera that accepted too late, on its own stream and with the
    camera's key; the camera's own stream, which presented the key before, still counts after."""
    camera = _LateCamera()
    camera_server, camera_address = await serve_camera(camera)
    try:
        async with (
            DrvsServer("127.0.0.1:0", forward_timeout_s=0.5) as server,
            aio.insecure_channel(server.address) as channel,
            DrvsClient(server.address, robot_id="r", listen="127.0.0.1:0") as robot,
            aio.insecure_channel(robot.callback_address) as to_robot,
        ):
            registry = registry_pb2_grpc.RegisterVisionServiceStub(channel)
            registration = register_message("cam1")
            registration.address = camera_address
            registered = await registry.Register(registration)
            reports = detection_pb2_grpc.CallbackCoordinatesStub(to_robot).ReportDetections()
            first = await robot.subscribe(YELLOW, CAM1_REGION, timeout_s=5)
            key = (await asyncio.wait_for(camera.requests.get(), 5)).report_key
            await reports.write(_report(first.request_id, "cam1", 0, True, key))
            assert (await first.collect()).complete
            camera.delay = 1.0  # past the forward timeout: the server answers for it
            late = await (await robot.subscribe(YELLOW, CAM1_REGION, timeout_s=5)).collect()
            assert late.camera_errors["cam1"].code == "UNAVAILABLE"  # a forward timeout is opaque to robots
            camera.delay = 0.0
            await camera.requests.get()  # the late one
            heartbeat = registry_pb2.HeartbeatRequest(
                camera_id="cam1", registration_secret=registered.registration_secret
            )
            await registry.Heartbeat(heartbeat)  # routable again
            third = await robot.subscribe(YELLOW, CAM1_REGION, timeout_s=5)
            assert (await asyncio.wait_for(camera.requests.get(), 5)).request_id == third.request_id
            await reports.write(_report(third.request_id, "cam1", 0, True))  # key already presented
            result = await third.collect()
            assert result.complete and [r.detections[0].centroid_xy for r in result.reports] == [(0.5, 5.0)]
            assert robot.reports_rejected == 0
            await reports.done_writing()
    finally:
        await camera_server.stop(0)

"""Several drvs-server processes sharing one registry in a real etcd (--registry etcd://...): a
camera registered through one server is routed by the others, the id's holder is the same on every
server, a lease that nobody renews ends everywhere, and while etcd is down the servers route on what
they knew and refuse registrations, then resynchronise when it is back."""

from __future__ import annotations

import asyncio
import math
import re
import shutil
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path

import grpc
import pytest
import pytest_asyncio
from grpc import aio
from grpc_health.v1 import health_pb2, health_pb2_grpc
from shapely.geometry import box as floor_box
from shapely.ops import unary_union

from drvs import DrvsClient
from drvs.core.mobile import Mount
from drvs.sim.scene import RecordedCamera
from drvs.tools.certs import make_all
from drvs.tools.launch import EtcdMember, ManagedProcess, start_camera, start_etcd, start_server
from drvs.v1 import geometry_pb2, registry_pb2, registry_pb2_grpc
from tests.helpers import BOTH_REGION, CAM1_REGION, CAM2_REGION, MAX_RANGE, YELLOW, register_message

pytestmark = pytest.mark.skipif(
    shutil.which("etcd") is None, reason="etcd is not installed (./run test installs it as root)"
)


@dataclass
class Site:
    etcd: list[EtcdMember]
    servers: list[tuple[ManagedProcess, str]]

    @property
    def registry(self) -> str:
        return "etcd://" + ",".join(m.address for m in self.etcd)


@pytest_asyncio.fixture
async def site(tmp_path: Path) -> AsyncIterator[Site]:
    """One etcd member and two servers on it (lease 2 s; pose updates as often as a test sends them;
    DEBUG logs)."""
    etcd = await start_etcd(tmp_path)
    site = Site(etcd, [])
    try:
        for _ in range(2):
            site.servers.append(
                await start_server(  # DEBUG: the tests wait on the poses a server logs it applied
                    "--registry", site.registry, "--lease-ttl", "2", "--min-pose-interval", "0", "--log-level", "DEBUG"
                )
            )
        yield site
    finally:
        for proc, _ in site.servers:
            await proc.stop()
        for m in etcd:
            await m.stop()


async def call(address: str, method: str, message: object) -> object:
    async with aio.insecure_channel(address) as channel:
        return await getattr(registry_pb2_grpc.RegisterVisionServiceStub(channel), method)(message)


async def listed(address: str) -> list[str]:
    reply = await call(address, "ListCameras", registry_pb2.ListCamerasRequest())
    assert isinstance(reply, registry_pb2.ListCamerasReply)
    return [c.camera_id for c in reply.cameras]


REGISTRATION = "drvs.v1.RegisterVisionService"


async def health(address: str, service: str) -> int:
    async with aio.insecure_channel(address) as channel:
        reply = await health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(service=service))
        return int(reply.status)


def registered_line(camera_id: str) -> re.Pattern[str]:
    return re.compile(rf"camera {camera_id} registered at \S+ through")


def left_line(camera_id: str) -> re.Pattern[str]:
    return re.compile(rf"camera {camera_id} left routing: ")


async def test_a_camera_registered_through_one_server_is_routed_by_the_other(site: Site) -> None:
    (a, a_address), (b, b_address) = site.servers
    message = register_message("cam1")
    message.frame = "building-a/floor-2"
    reply = await call(a_address, "Register", message)
    assert isinstance(reply, registry_pb2.RegisterReply) and reply.registration_secret
    await b.wait_for_line(registered_line("cam1"), timeout=10)  # B's watch saw it
    assert await listed(b_address) == ["cam1"] == await listed(a_address)
    # In its frame, as registered.
    on_floor = await call(b_address, "ListCameras", registry_pb2.ListCamerasRequest(frame="building-a/floor-2"))
    assert isinstance(on_floor, registry_pb2.ListCamerasReply) and [c.camera_id for c in on_floor.cameras] == ["cam1"]
    # Its holder heartbeats through B, with the secret A handed out; then leaves through B.
    secret = reply.registration_secret
    await call(b_address, "Heartbeat", registry_pb2.HeartbeatRequest(camera_id="cam1", registration_secret=secret))
    seen = len(a.lines)
    await call(b_address, "Deregister", registry_pb2.DeregisterRequest(camera_id="cam1", registration_secret=secret))
    await a.wait_for_line(left_line("cam1"), timeout=10, start=seen)
    assert await listed(a_address) == [] == await listed(b_address)


async def test_the_ids_holder_is_the_same_on_every_server(site: Site) -> None:
    (_, a_address), (b, b_address) = site.servers
    first = await call(a_address, "Register", register_message("cam1"))
    assert isinstance(first, registry_pb2.RegisterReply)
    await b.wait_for_line(registered_line("cam1"), timeout=10)
    # Another (anonymous) caller, without the registration's secret, cannot take the id through B.
    with pytest.raises(aio.AioRpcError) as err:
        await call(b_address, "Register", register_message("cam1", address="127.0.0.1:7"))
    assert err.value.code() == grpc.StatusCode.PERMISSION_DENIED
    assert "camera_id: 'cam1' belongs to another credential" in str(err.value.details())
    # Nor renew or deregister it through A with a guessed secret.
    for method, message in (
        ("Heartbeat", registry_pb2.HeartbeatRequest(camera_id="cam1", registration_secret="guess")),
        ("Deregister", registry_pb2.DeregisterRequest(camera_id="cam1", registration_secret="guess")),
    ):
        with pytest.raises(aio.AioRpcError) as err:
            await call(a_address, method, message)
        assert err.value.code() == grpc.StatusCode.FAILED_PRECONDITION, method
    # The holder registers again through B (proving it with its secret): a new secret, and the old
    # one is refused on A as well.
    again = register_message("cam1")
    again.registration_secret = first.registration_secret
    second = await call(b_address, "Register", again)
    assert isinstance(second, registry_pb2.RegisterReply) and second.registration_secret != first.registration_secret
    with pytest.raises(aio.AioRpcError) as err:
        await call(
            a_address,
            "Heartbeat",
            registry_pb2.HeartbeatRequest(camera_id="cam1", registration_secret=first.registration_secret),
        )
    assert err.value.code() == grpc.StatusCode.FAILED_PRECONDITION
    assert await listed(a_address) == ["cam1"]


async def test_a_lease_nobody_renews_ends_on_every_server(site: Site) -> None:
    (a, a_address), (b, b_address) = site.servers
    await call(a_address, "Register", register_message("cam1"))
    await b.wait_for_line(registered_line("cam1"), timeout=10)
    # No heartbeat: etcd ends the 2 s lease, and both servers' watches drop the camera.
    await a.wait_for_line(left_line("cam1"), timeout=15)
    await b.wait_for_line(left_line("cam1"), timeout=15)
    assert await listed(a_address) == [] == await listed(b_address)


async def test_without_etcd_servers_route_on_what_they_knew_and_refuse_registrations(site: Site) -> None:
    (a, a_address), (b, b_address) = site.servers
    reply = await call(a_address, "Register", register_message("cam1"))
    assert isinstance(reply, registry_pb2.RegisterReply)
    await b.wait_for_line(registered_line("cam1"), timeout=10)
    (member,) = site.etcd
    await member.stop()
    await a.wait_for_line(re.compile("registry: etcd unreachable"), timeout=15)
    # Health says registrations cannot be taken now; the process as a whole still serves (routing).
    assert await health(a_address, REGISTRATION) == health_pb2.HealthCheckResponse.NOT_SERVING
    assert await health(a_address, "") == health_pb2.HealthCheckResponse.SERVING
    # Routing goes on with the last registry known (the lease is not counted down without etcd).
    assert await listed(a_address) == ["cam1"] == await listed(b_address)
    with pytest.raises(aio.AioRpcError) as err:
        await call(b_address, "Register", register_message("cam2", x=10.0))
    assert err.value.code() == grpc.StatusCode.UNAVAILABLE
    assert "registrations wait until etcd answers" in str(err.value.details())
    # etcd back (the same member, on its data): both resynchronise; registrations work again.
    seen = len(b.lines)
    await member.start(f"{member.name}={member.peer_url}", state="existing")
    await b.wait_for_line(re.compile("registry: etcd .* answers again"), timeout=30, start=seen)
    assert await health(b_address, REGISTRATION) == health_pb2.HealthCheckResponse.SERVING
    await call(b_address, "Register", register_message("cam2", x=10.0))
    await a.wait_for_line(registered_line("cam2"), timeout=10)
    assert "cam2" in await listed(a_address)


@pytest.mark.slow
async def test_a_camera_that_knows_several_servers_survives_one_being_killed(
    tmp_path: Path, recorded: dict[str, RecordedCamera]
) -> None:
    """Three servers on one etcd; a real drvs-camera given all three (`--server A,B,C`) registers
    through A. A robot's fused request through B gets the camera's report (the camera reports to
    the server that asked, B, not to A). A is killed (SIGKILL): the camera's heartbeats move on to
    another server, so its registration outlives A, and a robot asking C still gets its detections."""
    etcd = await start_etcd(tmp_path)
    registry = "etcd://" + etcd[0].address
    procs: list[ManagedProcess] = []
    try:
        # (DEBUG: the servers log each heartbeat they take.)
        servers = [
            await start_server("--registry", registry, "--lease-ttl", "2", "--log-level", "DEBUG") for _ in range(3)
        ]
        procs += [p for p, _ in servers]
        (a, a_address), (b, b_address), (c, c_address) = servers
        rec = recorded["cam1"]
        camera = await start_camera(
            "cam1", rec.video, rec.homography_file, f"{a_address},{b_address},{c_address}", "--max-range", MAX_RANGE
        )
        procs.append(camera)
        await b.wait_for_line(registered_line("cam1"), timeout=10)
        await c.wait_for_line(registered_line("cam1"), timeout=10)
        async with DrvsClient.connect(b_address, robot_id="r1") as drvs:
            snapshot = await drvs.snapshot(YELLOW, CAM1_REGION, timeout_s=10)
            assert snapshot.camera_ids == ("cam1",) and len(snapshot.objects) == 2, snapshot
        a.kill()
        # gRPC moves the camera's channel on to B (it may not even see a heartbeat fail): the next
        # heartbeats renew its etcd lease through B or C, so its 2 s lease outlives A.
        beat = re.compile(r"camera cam1: heartbeat; its lease in etcd renewed")
        marks = [len(b.lines), len(c.lines)]
        for _ in range(4):  # four heartbeats after the kill (one every 2/3 s): longer than the lease
            waits = [
                asyncio.get_running_loop().create_task(s.wait_for_line(beat, timeout=30, start=m))
                for s, m in zip((b, c), marks, strict=True)
            ]
            done, pending = await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
            for task in pending:
                task.cancel()
            await asyncio.gather(*pending, return_exceptions=True)
            (first,) = list(done)[:1]
            first.result()
            marks = [len(b.lines), len(c.lines)]
        # Both still route to it, and answer for it.
        assert await listed(c_address) == ["cam1"]
        async with DrvsClient.connect(c_address, robot_id="r2") as drvs:
            result = await drvs.detect(YELLOW, CAM1_REGION, timeout_s=10)
            assert result.camera_ids == ("cam1",) and not result.errors and len(result.detections) == 2, result
    finally:
        for proc in reversed(procs):
            await proc.stop()
        for m in etcd:
            await m.stop()


@pytest.mark.slow
async def test_a_robots_track_resumes_through_another_server_when_its_server_dies(
    tmp_path: Path, recorded: dict[str, RecordedCamera]
) -> None:
    """Two servers on one etcd, a camera and a robot that know both. The robot's track runs through
    A; A is SIGKILLed mid-track; without the robot's code doing anything, the track is sent again
    through B for what remains, its snapshots go on (the camera's objects in them), it ends with its
    final snapshot, and the gap the robot saw is measured (`track.gaps_s`)."""
    etcd = await start_etcd(tmp_path)
    registry = "etcd://" + etcd[0].address
    procs: list[ManagedProcess] = []
    try:
        servers = [await start_server("--registry", registry, "--lease-ttl", "2") for _ in range(2)]
        procs += [p for p, _ in servers]
        (a, a_address), (b, b_address) = servers
        both = f"{a_address},{b_address}"
        rec = recorded["cam1"]
        procs.append(await start_camera("cam1", rec.video, rec.homography_file, both, "--max-range", MAX_RANGE))
        await b.wait_for_line(registered_line("cam1"), timeout=10)
        async with DrvsClient.connect(both, robot_id="r1") as drvs:
            before: list[int] = []
            after: list[int] = []
            final = False
            async with drvs.track(YELLOW, CAM1_REGION, rate_hz=5, duration_s=8) as track:
                async for snapshot in track:
                    if track.resumes == 0:
                        before.append(len(snapshot.objects))
                        if len(before) == 3:
                            a.kill()  # the server the robot's requests go to: no goodbye
                    else:
                        after.append(len(snapshot.objects))
                    final = snapshot.final
            assert final and track.resumes == 1 and len(track.gaps_s) == 1, (track.resumes, track.gaps_s)
            assert before[:3] == [2, 2, 2] and after and after[-1] == 2, (before, after)
            # The gap: from the stream's end to the first snapshot from B (published in the benchmark).
            assert 0 < track.gaps_s[0] < 8
    finally:
        for proc in reversed(procs):
            await proc.stop()
        for m in etcd:
            await m.stop()


async def test_servers_reach_etcd_over_mutual_tls_and_not_without_a_certificate(tmp_path: Path) -> None:
    """etcd asking for client certificates (a CA of drvs-certs): a server given --etcd-ca,
    --etcd-cert and --etcd-key registers through it and another such server routes; a server
    without a certificate cannot reach etcd, says so, and refuses registrations."""
    made = make_all(tmp_path / "certs", ["server", "server-etcd"], [])
    ca = tmp_path / "certs" / "ca.pem"
    etcd_cert, etcd_key = made["server-etcd"]
    cert, key = made["server"]
    etcd = await start_etcd(tmp_path / "etcd", tls=(ca, etcd_cert, etcd_key), client_tls=(cert, key))
    registry = "etcd://" + etcd[0].address
    tls = ("--etcd-ca", str(ca), "--etcd-cert", str(cert), "--etcd-key", str(key))
    procs: list[ManagedProcess] = []
    try:
        servers = [await start_server("--registry", registry, *tls) for _ in range(2)]
        procs += [p for p, _ in servers]
        (_, a_address), (b, b_address) = servers
        await call(a_address, "Register", register_message("cam1"))
        await b.wait_for_line(registered_line("cam1"), timeout=10)
        assert await listed(b_address) == ["cam1"]
        stranger, stranger_address = await start_server("--registry", registry)
        procs.append(stranger)
        await stranger.wait_for_line(re.compile("registry: etcd unreachable"), timeout=15)
        assert await listed(stranger_address) == []
        with pytest.raises(aio.AioRpcError) as err:
            await call(stranger_address, "Register", register_message("cam2"))
        assert err.value.code() == grpc.StatusCode.UNAVAILABLE
    finally:
        for proc in reversed(procs):
            await proc.stop()
        for m in etcd:
            await m.stop()


async def test_servers_on_a_three_member_cluster_go_on_when_a_member_is_killed(tmp_path: Path) -> None:
    """Two servers given all three members of an etcd cluster; one member is SIGKILLed: the
    servers' channels skip it, the two left keep a quorum, and a registration through B (once they
    have a leader again, if the dead member led) reaches A."""
    etcd = await start_etcd(tmp_path, members=3)
    registry = "etcd://" + ",".join(m.address for m in etcd)
    procs: list[ManagedProcess] = []
    try:
        servers = [await start_server("--registry", registry) for _ in range(2)]
        procs += [p for p, _ in servers]
        (a, a_address), (_, b_address) = servers
        await call(a_address, "Register", register_message("cam1"))
        etcd[0].kill()
        deadline = asyncio.get_running_loop().time() + 20
        while True:  # as a camera does: register again until a server takes it
            try:
                await call(b_address, "Register", register_message("cam2", x=10.0))
                break
            except aio.AioRpcError as exc:
                assert exc.code() in (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.DEADLINE_EXCEEDED), exc
                assert asyncio.get_running_loop().time() < deadline, exc
                await asyncio.sleep(0.1)  # a camera's backoff between attempts
        await a.wait_for_line(registered_line("cam2"), timeout=15)
        assert await listed(a_address) == ["cam1", "cam2"]
    finally:
        for proc in reversed(procs):
            await proc.stop()
        for m in etcd:
            await m.stop()


async def test_a_mobile_camera_on_a_shared_registry_is_routed_by_every_server_where_it_is(site: Site) -> None:
    """A mobile camera registers through A and sends its poses to A; B routes it where its latest
    pose puts it (the pose goes through etcd), not where it was, and not when it has no pose."""
    (_, a_address), (b, b_address) = site.servers
    mount = Mount(0.1, 0.0, 0.8, 0.0, 30.0, hfov_deg=70.0).base_homography((640, 480))
    message = register_message("scout")
    message.homography.CopyFrom(registry_pb2.Homography(m=mount.to_list()))
    message.mobile = True
    reply = await call(a_address, "Register", message)
    assert isinstance(reply, registry_pb2.RegisterReply)
    await b.wait_for_line(registered_line("scout"), timeout=10)
    ahead_of = {  # 2.5 m ahead of a robot at (5, 1) facing +x (yaw 0), then turned round (yaw pi)
        0.0: registry_pb2.ListCamerasRequest(region=box(7.2, 0.7, 7.8, 1.3)),
        math.pi: registry_pb2.ListCamerasRequest(region=box(2.2, 0.7, 2.8, 1.3)),
    }

    async def seen_by_b(yaw: float) -> list[str]:
        found = await call(b_address, "ListCameras", ahead_of[yaw])
        assert isinstance(found, registry_pb2.ListCamerasReply)
        return [c.camera_id for c in found.cameras]

    assert await seen_by_b(0.0) == []  # no pose yet: not routed anywhere
    # (It turns rather than jumps: a pose farther than its robot moves is refused.)
    for yaw in (0.0, math.pi):
        await call(
            a_address,
            "UpdatePose",
            registry_pb2.UpdatePoseRequest(
                camera_id="scout",
                registration_secret=reply.registration_secret,
                pose=geometry_pb2.Pose2(x=5.0, y=1.0, yaw=yaw),
            ),
        )
        # B logs (DEBUG) each pose it moves the camera to from etcd: then it routes it there.
        await b.wait_for_line(
            rf"camera scout at pose x=5\.000 y=1\.000 yaw={yaw:.4f} .*from the shared registry", timeout=10
        )
        assert await seen_by_b(yaw) == ["scout"], f"B does not route the scout at yaw={yaw}"
    assert await seen_by_b(0.0) == []  # it has turned away


def box(x0: float, y0: float, x1: float, y1: float) -> geometry_pb2.Region:
    return geometry_pb2.Region(box=geometry_pb2.Box(x_lower=x0, y_lower=y0, x_upper=x1, y_upper=y1))


async def test_a_camera_whose_lease_lapses_is_missing_on_every_server_one_that_deregisters_is_not(
    site: Site, recorded: dict[str, RecordedCamera]
) -> None:
    """Two real cameras registered through A: cam1 is SIGKILLed (its 2 s etcd lease lapses), cam2
    stops cleanly (SIGTERM: it deregisters through A). On both servers a robot asking about cam1's
    floor hears it is missing (UNAVAILABLE, its floor uncovered), as with the in-memory registry;
    nobody names cam2."""
    (a, a_address), (b, b_address) = site.servers
    cameras = {}
    try:
        for camera_id in ("cam1", "cam2"):
            rec = recorded[camera_id]
            cameras[camera_id] = await start_camera(
                camera_id, rec.video, rec.homography_file, a_address, "--max-range", MAX_RANGE
            )
            await b.wait_for_line(registered_line(camera_id), timeout=10)
        async with DrvsClient(b_address) as robot:
            cam1_floor = next(c.field_of_view for c in await robot.cameras() if c.camera_id == "cam1")
        marks = [len(a.lines), len(b.lines)]
        cameras["cam1"].kill()  # no deregistration: its lease runs out in etcd
        assert await cameras["cam2"].stop() == 0  # deregisters
        for server, mark in zip((a, b), marks, strict=True):
            await server.wait_for_line(r"camera cam2 left routing: deregistered", timeout=10, start=mark)
            await server.wait_for_line(
                r"camera cam1 left routing: its lease ran out without it deregistering", timeout=15, start=mark
            )
        for address in (a_address, b_address):
            async with DrvsClient(address) as robot:
                result = await robot.detect(YELLOW, BOTH_REGION, timeout_s=5)
                assert result.camera_ids == () and result.missing_cameras == {"cam1"}, (address, result)
                error = result.camera_errors["cam1"]
                assert error.code == "UNAVAILABLE" and "lease ran out without it deregistering" in error.message
                cam1_part = cam1_floor.intersection(floor_box(*BOTH_REGION))
                assert unary_union(result.uncovered).contains(cam1_part.buffer(-0.01))
                # Where only cam2 looked, nobody is missing: it left (the floor is uncovered all the same).
                only_cam2 = await robot.detect(YELLOW, CAM2_REGION, timeout_s=5)
                assert only_cam2.complete and only_cam2.missing_cameras == set() and only_cam2.uncovered
                fused = await robot.snapshot(YELLOW, CAM1_REGION, timeout_s=5)
                assert list(fused.camera_errors) == ["cam1"] and fused.uncovered
    finally:
        for proc in cameras.values():
            await proc.stop()

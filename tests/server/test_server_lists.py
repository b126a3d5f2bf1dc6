"""Several servers everywhere: every robot and camera path takes a server list ("A:PORT,B:PORT")
and goes on through the list when one server dies. Two drvs-server processes share one real etcd;
a drvs-camera and the robots are given both; the server first in the list (the one the camera
registered through and the robots' channels picked) is SIGKILLed, and each path is checked
through the list: per-camera detect and subscribe (DrvsClient and `drvs-robot detect`), fused
detect, track, the cameras listing, and the camera's heartbeats. Without etcd, a list whose first
entry is dead reaches the live server behind it."""

from __future__ import annotations

import asyncio
import json
import math
import re
import shutil
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio
from shapely.geometry import box

from drvs import DrvsClient
from drvs.core.errors import InvalidArgument
from drvs.core.model import Pose2
from drvs.core.net import local_ip_towards
from drvs.robot.client import RetryPolicy
from drvs.sim.scene import RecordedCamera, record_camera
from drvs.tools.launch import (
    EtcdMember,
    ManagedProcess,
    free_ports,
    running_server,
    start_camera,
    start_etcd,
    start_server,
)
from drvs.tools.meter import MeteredClient
from tests.helpers import CAM1_REGION, CAM1_SEEN, MAX_RANGE, MOBILE_SIZE, MOUNT, YELLOW, nearest, poll, roi, run_robot

needs_etcd = pytest.mark.skipif(
    shutil.which("etcd") is None, reason="etcd is not installed (./run test installs it as root)"
)

#: The yellow discs cam1 sees (tests/helpers.OBJECTS within its view).
CAM1_YELLOW = 2
#: The lease the servers grant, seconds: a camera whose heartbeats stopped leaves routing within it.
LEASE_S = 2.0
HEARTBEAT = re.compile(r"camera cam1: heartbeat; its lease in etcd renewed")


@dataclass
class Pair:
    """Two servers on one etcd, and cam1 given both (`both`), registered through the first."""

    etcd: list[EtcdMember]
    a: ManagedProcess
    b: ManagedProcess
    both: str
    camera: ManagedProcess

    async def kill_a(self) -> None:
        """SIGKILL the first server, once the camera's heartbeats are seen going through it."""
        await self.a.wait_for_line(HEARTBEAT, timeout=10)
        self.a.kill()
        await self.a.wait()


@pytest_asyncio.fixture
async def pair(tmp_path: Path, recorded: dict[str, RecordedCamera]) -> AsyncIterator[Pair]:
    etcd = await start_etcd(tmp_path)
    registry = "etcd://" + etcd[0].address
    procs: list[ManagedProcess] = []
    try:
        servers = []
        for _ in range(2):  # DEBUG: the servers log each heartbeat they take
            server = await start_server("--registry", registry, "--lease-ttl", str(LEASE_S), "--log-level", "DEBUG")
            procs.append(server[0])
            servers.append(server)
        (a, a_address), (b, b_address) = servers
        both = f"{a_address},{b_address}"
        rec = recorded["cam1"]
        procs.append(await start_camera("cam1", rec.video, rec.homography_file, both, "--max-range", MAX_RANGE))
        await b.wait_for_line(re.compile(r"camera cam1 registered at \S+ through"), timeout=10)  # B knows it
        yield Pair(etcd, a, b, both, procs[-1])
    finally:
        for proc in reversed(procs):
            await proc.stop()
        for m in etcd:
            await m.stop()


def json_lines(lines: list[str]) -> list[dict[str, Any]]:
    """The JSON objects among a drvs-robot's output lines (its notices on stderr are not JSON)."""
    return [json.loads(line) for line in lines if line.startswith("{")]


def assert_cam1_yellow(centroids: list[tuple[float, float]]) -> None:
    assert len(centroids) == CAM1_YELLOW, centroids
    for x, y in centroids:
        assert nearest(YELLOW, x, y)[1] < 0.05, (x, y)


@needs_etcd
@pytest.mark.slow
async def test_the_cameras_registration_moves_on_to_the_other_server(pair: Pair) -> None:
    """The camera's heartbeats went through A; A killed, they renew its etcd lease through B for
    longer than the lease, so the camera stays registered and listed without registering again."""
    await pair.kill_a()
    mark = len(pair.b.lines)
    loop = asyncio.get_running_loop()
    started = loop.time()
    beats = 0
    while loop.time() - started < 1.5 * LEASE_S:  # past the lease: only heartbeats through B kept it
        await pair.b.wait_for_line(HEARTBEAT, timeout=10, start=mark)
        mark = len(pair.b.lines)
        beats += 1
    assert beats >= 3, beats
    assert not any("left routing" in line for line in pair.b.lines), pair.b.output()
    assert not any("re-registered" in line for line in pair.camera.lines), pair.camera.output()
    async with DrvsClient.connect(pair.both, robot_id="lister") as drvs:
        assert [c.camera_id for c in await drvs.cameras()] == ["cam1"]


@needs_etcd
@pytest.mark.slow
async def test_per_camera_requests_of_a_running_robot_go_on_through_the_list(pair: Pair) -> None:
    """A robot connected to both asks per camera through A; A killed, its next requests (one
    retry: the first may meet A's broken stream) are answered through B, and cam1's reports reach
    the robot's listener."""
    async with DrvsClient.connect(pair.both, robot_id="r1", retry=RetryPolicy.retries(3)) as drvs:
        before = await drvs.detect(YELLOW, CAM1_REGION, timeout_s=10)
        assert before.camera_ids == ("cam1",) and not before.errors, before
        await pair.kill_a()
        after = await drvs.detect(YELLOW, CAM1_REGION, timeout_s=10)
        assert after.camera_ids == ("cam1",) and not after.errors, after
        assert_cam1_yellow([(d.centroid.x, d.centroid.y) for d in after.detections])
        async with drvs.subscribe(YELLOW, CAM1_REGION, rate_hz=10, duration_s=0.5, timeout_s=10) as sub:
            reports = [report async for report in sub]
        assert sub.result.complete and not sub.result.camera_errors, sub.result
        assert [r.sequence for r in reports] == list(range(len(reports))) and reports[-1].final
        assert len(reports) >= 5 and all(len(r.detections) == CAM1_YELLOW for r in reports), reports


@needs_etcd
@pytest.mark.slow
async def test_fused_detect_track_and_cameras_through_the_list(pair: Pair) -> None:
    """After A is killed, a robot given both gets a fused snapshot, a whole track and the cameras
    listing, each through B."""
    await pair.kill_a()
    async with DrvsClient.connect(pair.both, robot_id="r2") as drvs:
        snapshot = await drvs.snapshot(YELLOW, CAM1_REGION, timeout_s=10)
        assert snapshot.camera_ids == ("cam1",) and not snapshot.camera_errors, snapshot
        assert_cam1_yellow([o.centroid_xy for o in snapshot.objects])
        async with drvs.track(YELLOW, CAM1_REGION, rate_hz=5, duration_s=1) as track:
            snapshots = [s async for s in track]
        assert snapshots and snapshots[-1].final and track.resumes == 0, snapshots
        assert len(snapshots[-1].objects) == CAM1_YELLOW, snapshots[-1]
        listed = await drvs.cameras()
        assert [c.camera_id for c in listed] == ["cam1"], listed


@needs_etcd
@pytest.mark.slow
@pytest.mark.timeout(120)
async def test_drvs_robot_commands_through_the_list(pair: Pair) -> None:
    """`drvs-robot ... --server A,B` with A killed: detect (per camera, the default), detect --fuse,
    track and cameras each exit 0 with what cam1 sees."""
    await pair.kill_a()
    where = ("--server", pair.both, "--filter", YELLOW, "--roi", roi(CAM1_SEEN), "--json")
    code, lines = await run_robot("detect", *where)
    assert code == 0, lines
    (report,) = json_lines(lines)
    assert report["camera_id"] == "cam1" and report["final"] is True, report
    assert_cam1_yellow([(d["centroid"][0], d["centroid"][1]) for d in report["detections"]])
    code, lines = await run_robot("detect", "--fuse", *where)
    assert code == 0, lines
    (snapshot,) = json_lines(lines)
    assert snapshot["cameras"] == ["cam1"], snapshot
    assert len(snapshot["objects"]) == CAM1_YELLOW, snapshot
    code, lines = await run_robot("track", *where, "--rate", "5", "--duration", "0.6")
    assert code == 0, lines
    snapshots = json_lines(lines)
    assert snapshots and snapshots[-1]["final"] is True, lines
    code, lines = await run_robot("cameras", "--server", pair.both, "--json")
    assert code == 0, lines
    assert [c["camera_id"] for c in json_lines(lines)] == ["cam1"], lines


@pytest.mark.slow
async def test_without_etcd_a_dead_first_entry_leads_to_the_live_server(recorded: dict[str, RecordedCamera]) -> None:
    """No etcd, one live server behind a dead address (`DEAD,LIVE`): the camera registers through
    the list, and the robot's per-camera and fused requests, the cameras listing and `drvs-robot
    detect` all reach it."""
    (dead_port,) = free_ports(1)
    async with running_server() as (_, live):
        servers = f"127.0.0.1:{dead_port},{live}"
        rec = recorded["cam1"]
        camera = await start_camera("cam1", rec.video, rec.homography_file, servers, "--max-range", MAX_RANGE)
        try:
            async with DrvsClient.connect(servers, robot_id="r3") as drvs:
                assert drvs.callback_address == ""  # fused and listing need no listener
                assert [c.camera_id for c in await drvs.cameras()] == ["cam1"]
                snapshot = await drvs.snapshot(YELLOW, CAM1_REGION, timeout_s=10)
                assert_cam1_yellow([o.centroid_xy for o in snapshot.objects])
                result = await drvs.detect(YELLOW, CAM1_REGION, timeout_s=10)
                assert result.camera_ids == ("cam1",) and not result.errors, result
                assert_cam1_yellow([(d.centroid.x, d.centroid.y) for d in result.detections])
                assert drvs.callback_address.startswith("127.0.0.1:")
            # A DNS name (here standing for the one live server) on the per-camera path too.
            async with DrvsClient.connect(f"localhost:{live.rpartition(':')[2]}", robot_id="r4") as drvs:
                result = await drvs.detect(YELLOW, CAM1_REGION, timeout_s=10)
                assert result.camera_ids == ("cam1",) and len(result.detections) == CAM1_YELLOW, result
            code, lines = await run_robot(
                "detect", "--server", servers, "--filter", YELLOW, "--roi", roi(CAM1_SEEN), "--json"
            )
            assert code == 0, lines
            (report,) = json_lines(lines)
            assert len(report["detections"]) == CAM1_YELLOW, report
            # The simulated robot's metered client (drvs-sim robot --server A,B): a counting relay
            # in front of each server, their bytes added up.
            async with MeteredClient(servers, robot_id="r5") as metered:
                assert metered.client is not None
                result = await metered.client.detect(YELLOW, CAM1_REGION, timeout_s=10)
                assert result.camera_ids == ("cam1",) and len(result.detections) == CAM1_YELLOW, result
                received, sent = metered.payload_bytes()
                assert received > 0 and sent > 0, (received, sent)
        finally:
            await camera.stop()


async def test_a_list_of_dead_servers_names_the_list() -> None:
    """Nobody answers: drvs-robot exits 2 naming the whole list it tried, not a malformed address."""
    dead = ",".join(f"127.0.0.1:{port}" for port in free_ports(2))
    code, lines = await run_robot("detect", "--server", dead, "--filter", YELLOW, "--roi", "0,0,1,1")
    assert code == 2, lines
    assert lines and lines[-1].startswith(f"drvs-robot: server {dead}: not reachable"), lines


async def test_a_list_mixing_names_and_addresses_is_refused_naming_the_flag() -> None:
    """gRPC takes one DNS name or a list of IP addresses: a mix is bad input, refused before any
    network work."""
    with pytest.raises(InvalidArgument, match=r"^server: several addresses must all be IPv4 or all IPv6"):
        await DrvsClient("127.0.0.1:1,localhost:2").start()


@needs_etcd
@pytest.mark.slow
async def test_a_mobile_cameras_poses_and_deregistration_go_on_through_the_list(tmp_path: Path) -> None:
    """A mobile drvs-camera given both servers sends its robot's poses through A; A killed, the
    robot drives on and the camera's next poses reach etcd through B: B routes it where it now is.
    Stopped, it deregisters through B."""
    etcd = await start_etcd(tmp_path)
    registry = "etcd://" + etcd[0].address
    procs: list[ManagedProcess] = []
    pose = [Pose2(2.0, 1.0, math.radians(90))]  # where the robot is: the feed sends the latest

    async def feed(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        while not writer.is_closing():
            p = pose[-1]
            writer.write((json.dumps({"t": time.time(), "x": p.x, "y": p.y, "yaw": p.yaw}) + "\n").encode())
            await writer.drain()
            await asyncio.sleep(0.05)  # a localisation stack's pose rate (20 Hz), not a synchronisation

    feed_server = await asyncio.start_server(feed, "127.0.0.1", 0)
    port = feed_server.sockets[0].getsockname()[1]
    try:
        servers = []
        for _ in range(2):
            server = await start_server("--registry", registry, "--lease-ttl", str(LEASE_S), "--min-pose-interval", "0")
            procs.append(server[0])
            servers.append(server)
        (a, a_address), (b, b_address) = servers
        both = f"{a_address},{b_address}"
        recorded = record_camera(tmp_path, "video", MOUNT.base_homography(MOBILE_SIZE), MOBILE_SIZE, [], seed=1)
        mount = ("--mount", "0.1,0,0.8,0,30", "--hfov", "70", "--pose-source", f"tcp://127.0.0.1:{port}")
        procs.append(await start_camera("scout", recorded.video, None, both, *mount))
        async with DrvsClient.connect(b_address, robot_id="watcher") as drvs:

            async def routed_ahead_of(p: Pose2) -> None:
                """Until B lists the scout as seeing 2.5 m north of `p` (polled: no one tells the test)."""
                ahead = box(p.x - 0.3, p.y + 2.2, p.x + 0.3, p.y + 2.8)
                await poll(lambda: drvs.cameras(ahead), lambda cams: [c.pose for c in cams] == [p],
                           what=f"B routing the scout at {p}", timeout=15, every=0.1)  # fmt: skip

            await routed_ahead_of(pose[-1])
            a.kill()
            await a.wait()
            pose.append(Pose2(6.0, 1.0, math.radians(90)))  # the robot drives on
            await routed_ahead_of(pose[-1])
        # Stopped, the camera deregisters through B (the server taking the call says so).
        await procs[-1].stop()
        await b.wait_for_line("camera scout left routing: deregistered", timeout=10)
    finally:
        feed_server.close()
        await feed_server.wait_closed()
        for proc in reversed(procs):
            await proc.stop()
        for m in etcd:
            await m.stop()


def test_the_robots_listener_takes_the_interface_of_the_first_server_with_a_route() -> None:
    """A robot given several servers binds its report listener where the first reachable one
    leads: a name that resolves to nothing (.invalid never does) is passed over."""
    assert local_ip_towards(["drvs-nowhere.invalid:1", "[::1]:5"]) == "::1"
    assert local_ip_towards("[::1]:5,127.0.0.1:6") == "::1"
    assert local_ip_towards("drvs-nowhere.invalid:1") == "127.0.0.1"  # nothing reachable: loopback

"""A mobile camera node (drvs.camera with a mount) on real pixels, with a real drvs-server process
and a real robot client: as its robot drives, a fixed object is reported at the same floor position
from every pose, the field of view the server routes by follows the robot, and a frame with no pose
near its capture is not used."""

from __future__ import annotations

import asyncio
import json
import math
import time
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
import pytest_asyncio
from shapely.geometry import box

from drvs import DrvsClient
from drvs.camera import CameraNode, PushSource
from drvs.core.errors import FailedPrecondition, InvalidArgument
from drvs.core.mobile import Mount, PoseBuffer
from drvs.core.model import Pose2
from drvs.sim.scenario import parse_scenario
from drvs.sim.scene import record_camera
from drvs.tools.launch import ManagedProcess, start_server
from tests.helpers import MOBILE_SCENE, MOBILE_SIZE, MOBILE_TARGET, MOUNT, YELLOW, mounted_camera, mounted_frame, poll

SIZE = MOBILE_SIZE
TARGET = MOBILE_TARGET
REGION = (2.5, 1.5, 3.5, 2.5)
SCENE = MOBILE_SCENE
#: Where the robot is for each frame: driving towards the disc, weaving a little.
PATH = [
    Pose2(0.6, 2.0, 0.0),
    Pose2(0.9, 1.85, math.radians(8)),
    Pose2(1.2, 2.15, math.radians(-10)),
    Pose2(1.5, 2.05, math.radians(4)),
]


camera_at = mounted_camera
frame = mounted_frame


@pytest_asyncio.fixture
async def server() -> AsyncIterator[str]:
    proc: ManagedProcess
    proc, address = await start_server("--pose-lease", "5", "--min-pose-interval", "0.02")
    try:
        yield address
    finally:
        await proc.stop()


async def test_a_fixed_object_lands_in_one_place_from_every_pose_of_a_moving_camera(server: str) -> None:
    scenario = parse_scenario(SCENE, "test")
    source = PushSource("the scout's camera")
    first = frame(scenario, PATH[0], 0)
    source.push(first, time.time())
    node = CameraNode("scout-cam", source, None, server, mount=MOUNT, max_pose_gap_s=0.5, max_pose_rate_hz=50)
    async with node, DrvsClient.connect(server, robot_id="turtle") as drvs:
        await asyncio.wait_for(node.registered.wait(), 10)
        for k, pose in enumerate(PATH):
            t = time.time()
            node.push_pose(pose, t)
            source.push(frame(scenario, pose, k), t)
            # The server routes the floor ahead of this pose to the camera once its update arrives.
            await poll(
                lambda: drvs.cameras(box(*REGION)),
                lambda cams: bool(cams) and cams[0].pose == pose,  # noqa: B023 (awaited within this pass)
                what=f"the floor routed to the camera at {pose}",
                every=0.02,
            )
            result = await drvs.detect(YELLOW, REGION, timeout_s=5)
            assert result.camera_ids == ("scout-cam",) and not result.errors, result
            (report,) = result.reports
            assert report.camera_pose == pose
            (d,) = result.detections
            error = math.dist(d.centroid_xy, TARGET)
            assert error < 0.03, (k, pose, d.centroid_xy, error)
        # Behind the robot is not its field of view any more.
        assert await drvs.cameras(box(-1.0, 1.5, 0.0, 2.5)) == []


async def test_a_frame_with_no_pose_near_its_capture_is_not_used(server: str) -> None:
    scenario = parse_scenario(SCENE, "test")
    source = PushSource()
    pose = PATH[0]
    node = CameraNode("scout-cam", source, None, server, mount=MOUNT, max_pose_gap_s=0.2, pose_lease_s=5)
    t = time.time()
    source.push(frame(scenario, pose, 0), t)
    async with node, DrvsClient.connect(server, robot_id="turtle") as drvs:
        node.push_pose(pose, t)
        await poll(lambda: drvs.cameras(box(*REGION)), what="the floor routed to the camera", every=0.02)
        assert not (await drvs.detect(YELLOW, REGION, timeout_s=5)).errors
        # A newer frame whose capture no pose is near: reported as UNAVAILABLE, not mapped.
        source.push(frame(scenario, pose, 1), t + 1.0)
        result = await drvs.detect(YELLOW, REGION, timeout_s=5)
        assert result.detections == []
        error = result.camera_errors["scout-cam"]
        assert error.code == "UNAVAILABLE" and "no pose within 0.2 s of the frame's capture" in error.message


def test_push_pose_and_push_frame_refuse_bad_input() -> None:
    source = PushSource()
    with pytest.raises(InvalidArgument, match=r"^image: "):
        source.push("not an image")  # type: ignore[arg-type]
    fixed = CameraNode("fixed", source, MOUNT.base_homography(SIZE), "127.0.0.1:9")
    with pytest.raises(FailedPrecondition, match="no mount"):
        fixed.push_pose(Pose2(0, 0, 0))
    mobile = CameraNode("scout", source, None, "127.0.0.1:9", mount=MOUNT)
    with pytest.raises(InvalidArgument, match=r"^pose.y: "):
        mobile.push_pose(Pose2(0, math.nan, 0))
    assert len(mobile.poses) == 0
    with pytest.raises(InvalidArgument, match=r"^max_pose_rate_hz: "):
        CameraNode("scout", source, None, "127.0.0.1:9", mount=MOUNT, max_pose_rate_hz=0)


def test_pose_buffer_interpolates_between_poses_and_refuses_gaps() -> None:
    poses = PoseBuffer(max_gap_s=0.25)
    poses.push(10.0, Pose2(0.0, 0.0, math.radians(170)))
    poses.push(10.2, Pose2(2.0, 1.0, math.radians(-170)))
    mid = poses.at(10.1)
    assert mid is not None and mid.x == pytest.approx(1.0) and mid.y == pytest.approx(0.5)
    assert abs(math.remainder(mid.yaw - math.pi, 2 * math.pi)) < 1e-9  # the short way, through 180°
    assert poses.at(10.3) == Pose2(2.0, 1.0, math.radians(-170))  # just after the newest: held
    assert poses.at(10.5) is None and poses.at(9.5) is None  # too far from any pose
    poses.push(10.1, Pose2(5.0, 5.0, 0.0))  # late, out of order: put in its place
    assert poses.at(10.1) == Pose2(5.0, 5.0, 0.0) and poses.latest() == (10.2, Pose2(2.0, 1.0, math.radians(-170)))


def test_a_mounts_homography_is_the_composed_pinhole_camera() -> None:
    """Base homography moved by a pose == the pinhole camera placed where the mount puts it."""
    from drvs.core.geometry import homography_from_pose
    from drvs.core.mobile import map_homography

    pose = Pose2(3.0, -1.0, math.radians(35))
    composed = map_homography(MOUNT.base_homography(SIZE), pose)
    cam = camera_at(pose)
    direct = homography_from_pose(cam.position, cam.yaw_deg, cam.pitch_deg, cam.hfov_deg, SIZE)
    pixels = [[0.0, 479.0], [320.0, 240.0], [639.0, 300.0]]
    assert composed.apply(pixels) == pytest.approx(direct.apply(pixels), abs=1e-9)
    with pytest.raises(InvalidArgument, match=r"^mount.z: "):
        Mount(0, 0, 0, 0, 30, hfov_deg=60)


@pytest.mark.slow
async def test_drvs_camera_with_a_mount_follows_a_tcp_pose_feed(server: str, tmp_path: Path) -> None:
    """The CLI: a drvs-camera process with --mount and --pose-source tcp://… reads a real socket's
    newline-delimited JSON poses (a bad line is skipped) and the server routes it where they say."""
    recorded = record_camera(tmp_path, "video", MOUNT.base_homography(SIZE), SIZE, [], seed=1)
    pose = Pose2(2.0, 1.0, math.radians(90))
    feeding = asyncio.Event()

    async def feed(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writer.write(b"not json\n")
        while not writer.is_closing():
            line = {"t": time.time(), "x": pose.x, "y": pose.y, "yaw": pose.yaw}
            writer.write((json.dumps(line) + "\n").encode())
            await writer.drain()
            feeding.set()
            await asyncio.sleep(0.05)  # a localisation stack's pose rate (20 Hz), not a synchronisation

    feed_server = await asyncio.start_server(feed, "127.0.0.1", 0)
    port = feed_server.sockets[0].getsockname()[1]
    proc = await ManagedProcess.entry_point(
        "scout-cam",
        "drvs-camera",
        *("--id", "scout-cam", "--source", str(recorded.video), "--server", server, "--listen", "127.0.0.1:0"),
        *("--mount", "0.1,0,0.8,0,30", "--hfov", "70", "--pose-source", f"tcp://127.0.0.1:{port}"),
    ).start()
    try:
        async with DrvsClient.connect(server, robot_id="turtle") as drvs:
            ahead = box(pose.x - 0.3, pose.y + 2.2, pose.x + 0.3, pose.y + 2.8)  # 2.5 m ahead: north
            deadline = time.monotonic() + 30
            while not (cams := await drvs.cameras(ahead)):
                assert time.monotonic() < deadline and proc.returncode is None, proc.output()
                await asyncio.sleep(0.1)
            (cam,) = cams
            assert cam.mobile and cam.pose == pose and cam.unroutable == ""
            assert await drvs.cameras(box(pose.x - 0.3, pose.y - 2.8, pose.x + 0.3, pose.y - 2.2)) == []
    finally:
        await proc.stop()
        feed_server.close()
        await feed_server.wait_closed()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("--mount", "0,0,0.8,0", "--hfov", "70"), "mount (--mount): '0,0,0.8,0' is not X,Y,Z,YAW,PITCH"),
        (("--mount", "0,0,0.8,0,30"), "mount (--mount): give the camera's --hfov or its --camera-matrix"),
        (("--mount", "0,0,0.8,0,30", "--hfov", "70", "--homography", "h.yaml"), "mount (--mount): a mobile camera"),
        (("--mount", "0,0,0.8,0,30", "--camera-matrix", "1,2,3"), "camera_matrix (--camera-matrix): '1,2,3'"),
        (("--homography", "h.yaml", "--hfov", "70"), "hfov_deg (--hfov): only with --mount"),
        (
            ("--mount", "0,0,0.8,0,30", "--hfov", "70", "--max-pose-rate", "0"),
            "max_pose_rate_hz (from --max-pose-rate)",
        ),
        (("--mount", "0,0,0.8,0,30", "--hfov", "70", "--pose-source", "udp://x:1"), "--pose-source: no pose source"),
    ],
)
async def test_drvs_camera_refuses_a_bad_mount_or_pose_flag(args: tuple[str, ...], message: str) -> None:
    proc = await ManagedProcess.entry_point(
        "bad", "drvs-camera", "--id", "cam", "--source", "0", "--server", "127.0.0.1:9", *args
    ).start()
    code = await proc.wait(timeout=30)
    assert code == 2 and message in proc.output() and "Traceback" not in proc.output(), proc.output()

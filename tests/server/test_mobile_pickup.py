"""A continuous fused request picks up a mobile camera that drives into its region after dispatch.

With real processes: a drvs-server process, a fixed camera that sees the region (a real gRPC
endpoint that takes its forwards and never reports, so the request runs its full time), a mobile
camera node (drvs.camera's CameraNode with a mount, on rendered pixels) that is elsewhere when the
robot starts tracking, and a robot (DrvsClient.track). When the node's pose update puts its field of
view over the region, the server forwards the request to it for what remains, and its reports are
merged into the snapshots. Two more mobile cameras move while the request runs and are not asked:
one whose field of view stays away from the region, one over the region that does not serve the
request's object type. In-process, the server's own state shows what is not picked up: a camera
skipped after a failed forward, a request with less than a period left, a fused single shot."""

from __future__ import annotations

import asyncio
import contextlib
import math
import re
import time
from collections.abc import AsyncIterator

import numpy as np
import pytest
from grpc import aio
from numpy.typing import NDArray

from drvs import DrvsClient
from drvs.camera import CameraNode, PushSource
from drvs.core.model import DetectionRequest, Pose2, Snapshot
from drvs.server import DrvsServer
from drvs.server.config import ServerConfig
from drvs.server.fusion_session import Continuous
from drvs.sim.scenario import Scenario, parse_scenario
from drvs.tools.launch import running_server
from drvs.v1 import detection_pb2, detection_pb2_grpc, geometry_pb2, registry_pb2, registry_pb2_grpc
from tests.fakes import serve_camera
from tests.helpers import (
    MOBILE_SCENE,
    MOBILE_SIZE,
    MOBILE_TARGET,
    MOUNT,
    YELLOW,
    CapturingCamera,
    metrics_port,
    mounted_frame,
    register_message,
    scrape,
)

SIZE = MOBILE_SIZE
#: MOUNT sees the floor from about 0.6 m to 6.6 m ahead.
BASE = MOUNT.base_homography(SIZE)
TARGET = MOBILE_TARGET
REGION = (2.0, 1.5, 4.0, 3.0)
#: The fixed camera, 3 m up at (3, 0) looking along +y, sees x -0.8..6.8, y 1.5..7.5: the region.
FIXED_X = 3.0
#: Facing the target 2.4 m ahead (its field of view covers the region), and facing away from it.
IN = Pose2(0.6, 2.0, 0.0)
AWAY = Pose2(0.6, 2.0, math.pi)
FAR = Pose2(20.0, 20.0, 0.0)
SCENE = MOBILE_SCENE


def frame(scenario: Scenario, pose: Pose2) -> NDArray[np.uint8]:
    """What the mounted camera of a robot at `pose` sees."""
    return mounted_frame(scenario, pose)


@contextlib.asynccontextmanager
async def capturing() -> AsyncIterator[tuple[CapturingCamera, str]]:
    camera = CapturingCamera()
    server, address = await serve_camera(camera)
    try:
        yield camera, address
    finally:
        await server.stop(0)


def mobile_message(camera_id: str, address: str, kinds: tuple[str, ...] = ("hsv",)) -> registry_pb2.RegisterRequest:
    return registry_pb2.RegisterRequest(
        camera_id=camera_id,
        address=address,
        homography=registry_pb2.Homography(m=BASE.to_list()),
        image_width=SIZE[0],
        image_height=SIZE[1],
        max_range_m=6.0,
        detector_kinds=list(kinds),
        mobile=True,
        pose_lease_s=5.0,
    )


def pose_message(camera_id: str, secret: str, pose: Pose2) -> registry_pb2.UpdatePoseRequest:
    return registry_pb2.UpdatePoseRequest(
        camera_id=camera_id,
        registration_secret=secret,
        pose=geometry_pb2.Pose2(x=pose.x, y=pose.y, yaw=pose.yaw),
        pose_time_unix=time.time(),
    )


def near(snapshot: Snapshot, xy: tuple[float, float], camera_id: str, within: float = 0.1) -> bool:
    return any(camera_id in o.camera_ids and math.dist(o.centroid_xy, xy) < within for o in snapshot.objects)


@pytest.mark.slow
async def test_a_mobile_camera_that_drives_into_a_tracked_region_joins_the_track(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    scenario = parse_scenario(SCENE, "test")
    async with (
        running_server("--pose-lease", "5", "--min-pose-interval", "0.02", "--metrics-port", "0") as (proc, address),
        capturing() as (fixed, fixed_address),
        capturing() as (far, far_address),
        capturing() as (blind, blind_address),
        aio.insecure_channel(address) as channel,
    ):
        registry = registry_pb2_grpc.RegisterVisionServiceStub(channel)
        await registry.Register(register_message("post", x=FIXED_X, address=fixed_address))
        far_secret = (await registry.Register(mobile_message("far", far_address))).registration_secret
        blind_secret = (await registry.Register(mobile_message("blind", blind_address, ("aruco",)))).registration_secret

        source = PushSource("the scout's camera")
        source.push(frame(scenario, AWAY), time.time())
        node = CameraNode(
            "scout", source, None, address, mount=MOUNT, max_frame_age_s=60, max_pose_rate_hz=50, pose_lease_s=5
        )
        # The node's own pose updates, as the server answered them; the requests it was asked.
        sent: asyncio.Queue[Pose2] = asyncio.Queue()
        update_pose = node.registration.update_pose

        async def updating(pose: Pose2, pose_time_unix: float, timeout_s: float) -> registry_pb2.UpdatePoseReply:
            reply = await update_pose(pose, pose_time_unix, timeout_s)
            sent.put_nowait(pose)
            return reply

        monkeypatch.setattr(node.registration, "update_pose", updating)
        asked: asyncio.Queue[DetectionRequest] = asyncio.Queue()
        accept = node.accept

        def accepting(request: DetectionRequest, requester: str = "") -> None:
            accept(request, requester)
            asked.put_nowait(request)

        monkeypatch.setattr(node, "accept", accepting)

        async def moved(pose: Pose2) -> None:
            """The node has sent `pose` and the server took it."""
            while (await asyncio.wait_for(sent.get(), 10)) != pose:
                pass

        async with node, DrvsClient.connect(address, robot_id="turtle") as drvs:
            await asyncio.wait_for(node.registered.wait(), 10)
            node.push_pose(AWAY, time.time())
            await moved(AWAY)
            shots: list[Snapshot] = []
            async with drvs.track(YELLOW, REGION, rate_hz=4, duration_s=4, request_id="pick") as tracking:
                # The scout faces away: the request goes to the fixed camera alone.
                assert tracking.camera_ids == ("post",)
                # Two mobile cameras move while it runs: one stays away from the region, the other
                # is over it but serves no colour detector.
                await registry.UpdatePose(pose_message("far", far_secret, FAR))
                await registry.UpdatePose(pose_message("blind", blind_secret, IN))
                # The scout turns to face the region.
                t = time.time()
                node.push_pose(IN, t)
                source.push(frame(scenario, IN), t)
                await moved(IN)
                line = await proc.wait_for_line(
                    r"fused request pick: mobile camera scout entered its region; asked for the remaining "
                    r"(\d+\.\d) s",
                    timeout=10,
                )
                forwarded = await asyncio.wait_for(asked.get(), 10)
                # It moves on a little inside the region: it is not asked again.
                node.push_pose(Pose2(IN.x + 0.2, IN.y, IN.yaw), time.time())
                await moved(Pose2(IN.x + 0.2, IN.y, IN.yaw))
                async for snapshot in tracking:
                    shots.append(snapshot)
            metrics = await scrape(metrics_port(proc))
        assert asked.empty(), asked.get_nowait()

    # The scout was asked the fused request (reports to the server, by the id the cameras know it by)
    # for what remained of it, at its rate.
    assert forwarded.report_to_server and not forwarded.callback_address
    assert re.fullmatch(r"pick:[0-9a-f]+", forwarded.request_id)
    assert forwarded.continuous.rate_hz == 4
    remaining = float(line.group(1))
    assert 0.25 <= forwarded.continuous.duration_s < 4 and remaining == pytest.approx(
        forwarded.continuous.duration_s, abs=0.051
    )
    # Its reports were merged: snapshots before it turned hold the fixed camera's silence only, later
    # ones the scout's view of the target.
    assert [s.sequence for s in shots] == list(range(17)) and shots[-1].final
    joined = [i for i, s in enumerate(shots) if "scout" in s.camera_ids]
    assert joined, [s.camera_ids for s in shots]
    assert all("scout" not in s.camera_ids for s in shots[: joined[0]])
    assert near(shots[joined[0]], TARGET, "scout"), shots[joined[0]].objects
    assert len(joined) >= 4
    # The others were not asked, and no snapshot names them.
    assert far.requests.empty() and blind.requests.empty()
    named = {c for s in shots for c in (*s.camera_ids, *s.camera_errors)}
    assert named == {"post", "scout"}, named
    assert fixed.requests.get_nowait().request_id == forwarded.request_id
    assert metrics["drvs_mobile_pickups_total"] == 1.0


# --- in-process: what is not picked up ------------------------------------------------------------


def fused(request_id: str, rate_hz: float = 0.0, duration_s: float = 0.0) -> detection_pb2.DetectionRequest:
    x0, y0, x1, y1 = REGION
    return detection_pb2.DetectionRequest(
        request_id=request_id,
        robot_id="r",
        filter_def=YELLOW,
        region=geometry_pb2.Region(box=geometry_pb2.Box(x_lower=x0, y_lower=y0, x_upper=x1, y_upper=y1)),
        continuous=detection_pb2.ContinuousMode(rate_hz=rate_hz, duration_s=duration_s),
        fusion=detection_pb2.FusionOptions(deadline_s=30),
    )


async def test_what_a_mobile_camera_entering_the_region_does_not_join() -> None:
    """The server's sessions, after each pose update returned: a camera skipped after a failed
    forward is not asked until it heartbeats; a request with less than a period left is not
    extended; a fused single shot never is. A continuous one with time left is."""
    config = ServerConfig(listen="127.0.0.1:0", pose_lease_s=5.0, min_pose_interval_s=0.0)
    async with (
        capturing() as (_fixed, fixed_address),
        capturing() as (scout, scout_address),
        DrvsServer(config=config) as server,
        aio.insecure_channel(server.address) as channel,
    ):
        registry = registry_pb2_grpc.RegisterVisionServiceStub(channel)
        await registry.Register(register_message("post", x=FIXED_X, address=fixed_address))
        secret = (await registry.Register(mobile_message("scout", scout_address))).registration_secret
        await registry.UpdatePose(pose_message("scout", secret, AWAY))
        call = detection_pb2_grpc.DetectObjectBoundaryStub(channel).DetectStream()
        await call.write(fused("single"))
        await call.write(fused("short", rate_hz=0.5, duration_s=2))  # its last report is due in < 2 s
        await call.write(fused("long", rate_hz=1, duration_s=60))
        assert list((await asyncio.wait_for(call.read(), 10)).camera_ids) == ["post"]
        assert list((await asyncio.wait_for(call.read(), 10)).camera_ids) == ["post"]
        found = {s.request_id: s for group in server.fusion._by_id.values() for s in group}
        assert set(found) == {"single", "short", "long"}
        assert [s.request_id for s in server.fusion.continuous()] == ["short", "long"]
        server._unreachable.add("scout")  # its last forward failed
        await registry.UpdatePose(pose_message("scout", secret, IN))
        assert all(s.cameras == ("post",) for s in found.values())
        await registry.Heartbeat(registry_pb2.HeartbeatRequest(camera_id="scout", registration_secret=secret))
        await registry.UpdatePose(pose_message("scout", secret, IN))
        long = found["long"]
        assert isinstance(long, Continuous) and long.cameras == ("post", "scout") and "scout" in long.keys
        assert found["short"].cameras == ("post",) and found["single"].cameras == ("post",)
        forwarded = await asyncio.wait_for(scout.requests.get(), 10)
        assert forwarded.request_id == long.forward_id and forwarded.report_key == long.keys["scout"]
        assert 58 < forwarded.continuous.duration_s < 60
        call.cancel()

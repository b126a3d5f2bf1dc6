"""A mobile camera's poses are bounded, with a real drvs-server process: UpdatePose needs a camera
credential where the server has camera tokens; a pose farther from the last than the robot's
declared speed allows is refused (INVALID_ARGUMENT naming the speed) and changes nothing; and a
mobile camera whose field of view leaves a continuous fused request's region stops contributing
to it (the server tells it to stop sending that request's reports)."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import grpc
import pytest
from grpc import aio
from shapely.geometry import box

from drvs import DrvsClient
from drvs.camera import CameraNode, PushSource
from drvs.core.model import Pose2
from drvs.sim.scenario import parse_scenario
from drvs.tools.launch import running_server
from drvs.v1 import registry_pb2_grpc
from tests.helpers import MOUNT, YELLOW, poll
from tests.server.test_mobile_pickup import AWAY, IN, REGION, SCENE, frame, mobile_message, pose_message

TOKEN = "scout-token-0123456789abcdef"


def bearer(token: str) -> tuple[tuple[str, str], ...]:
    return (("authorization", f"Bearer {token}"),)


async def refused(call: object, code: grpc.StatusCode) -> str:
    with pytest.raises(aio.AioRpcError) as err:
        await call  # type: ignore[misc]
    assert err.value.code() == code, (err.value.code(), err.value.details())
    return err.value.details() or ""


async def test_update_pose_needs_a_camera_token(tmp_path: Path) -> None:
    (tmp_path / "cameras.txt").write_text(f"scout {TOKEN}\n")
    async with (
        running_server("--camera-tokens", str(tmp_path / "cameras.txt"), "--min-pose-interval", "0") as (_, address),
        aio.insecure_channel(address) as channel,
    ):
        registry = registry_pb2_grpc.RegisterVisionServiceStub(channel)
        reply = await registry.Register(mobile_message("scout", "127.0.0.1:9"), metadata=bearer(TOKEN))
        update = pose_message("scout", reply.registration_secret, IN)
        details = await refused(registry.UpdatePose(update), grpc.StatusCode.UNAUTHENTICATED)
        assert details == "UpdatePose: needs a valid camera token (authorization: Bearer …)"
        await registry.UpdatePose(update, metadata=bearer(TOKEN))


async def test_a_pose_faster_than_the_robot_moves_is_refused_and_changes_nothing() -> None:
    async with (
        running_server("--min-pose-interval", "0", "--pose-lease", "30", "--max-pose-lease", "30") as (_, address),
        aio.insecure_channel(address) as channel,
        DrvsClient.connect(address, robot_id="watcher") as drvs,
    ):
        registry = registry_pb2_grpc.RegisterVisionServiceStub(channel)
        secret = (await registry.Register(mobile_message("scout", "127.0.0.1:9"))).registration_secret
        await registry.UpdatePose(pose_message("scout", secret, IN))
        teleport = pose_message("scout", secret, Pose2(IN.x + 990.0, IN.y, IN.yaw))
        details = await refused(registry.UpdatePose(teleport), grpc.StatusCode.INVALID_ARGUMENT)
        assert details.startswith("pose: camera 'scout' would have moved 990.0 m in "), details
        assert "its robot moves at most 3 m/s (and jumps at most 1 m)" in details, details
        [listed] = await drvs.cameras()
        assert listed.pose == IN
        # A step a robot can make is taken.
        step = Pose2(IN.x + 0.5, IN.y, IN.yaw)
        await registry.UpdatePose(pose_message("scout", secret, step))
        [listed] = await drvs.cameras()
        assert listed.pose == step
        # A registration may declare a faster robot, within the server's bound.
        fast = mobile_message("racer", "127.0.0.1:9")
        fast.max_speed_mps = 500.0
        details = await refused(registry.Register(fast), grpc.StatusCode.INVALID_ARGUMENT)
        assert details.startswith("max_speed_mps: 500.0 must be 0 (the default) to 50"), details


async def test_a_mobile_camera_that_turns_off_the_region_leaves_the_request_until_it_turns_back() -> None:
    scenario = parse_scenario(SCENE, "test")
    async with running_server("--pose-lease", "5", "--min-pose-interval", "0.02") as (proc, address):
        source = PushSource("the scout's camera")
        t = time.time()
        source.push(frame(scenario, IN), t)
        node = CameraNode(
            "scout", source, None, address, mount=MOUNT, max_frame_age_s=60, max_pose_rate_hz=50, pose_lease_s=5
        )
        async with node, DrvsClient.connect(address, robot_id="turtle") as drvs:
            await asyncio.wait_for(node.registered.wait(), 10)
            node.push_pose(IN, t)
            await poll(lambda: drvs.cameras(box(*REGION)), what="the server routing the scout", every=0.02)
            async with drvs.track(YELLOW, REGION, rate_hz=4, duration_s=8) as tracking:
                assert tracking.camera_ids == ("scout",)
                snapshots = aiter(tracking)  # read, not closed: leaving `async for` would end the request
                while "scout" not in (await anext(snapshots)).camera_ids:
                    pass
                assert node.shares.continuous(), "the scout runs the request"
                # It turns round: its field of view leaves the region while the request runs.
                t = time.time()
                node.push_pose(AWAY, t)
                source.push(frame(scenario, AWAY), t)
                await proc.wait_for_line(r"fused request \S+: mobile camera scout left its region", timeout=10)
                # The request runs on without it: what it sees away from the region counts no more
                # (snapshots made before the server took it off may still be queued: read past them).
                without = 0
                while without < 3:
                    without = without + 1 if "scout" not in (await anext(snapshots)).camera_ids else 0
                # It turns back (a patrol's loop): its reports count again, for the same request.
                t = time.time()
                node.push_pose(IN, t)
                source.push(frame(scenario, IN), t)
                await proc.wait_for_line(r"fused request \S+: mobile camera scout is back over its region", timeout=10)
                while "scout" not in (await anext(snapshots)).camera_ids:
                    pass

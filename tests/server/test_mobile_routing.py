"""Mobile cameras on the server: the field of view routed follows the robot's pose, a stale pose
leaves routing and a fresh one restores it, a mount that sees no floor stays registered but is not
routed, pose updates never touch the index of fixed cameras, and only the id's holder may move it.

The registry tests run on an injected clock; the process tests run a real drvs-server and a real
gRPC camera endpoint, with raw registry stubs acting as the mobile camera's registration."""

from __future__ import annotations

import asyncio
import math

import grpc
import pytest
from grpc import aio
from shapely.geometry import Polygon, box

from drvs import DrvsClient
from drvs.core.errors import FailedPrecondition, InvalidArgument, NotFound, ResourceExhausted
from drvs.core.geometry import Homography
from drvs.core.mobile import Mount, map_homography, move_polygon
from drvs.core.model import Detection, DetectionReport, PixelBox, Pose2
from drvs.server.fusion import fuse
from drvs.server.registry import Registry
from drvs.tools.launch import running_server
from drvs.v1 import detection_pb2, geometry_pb2, registry_pb2, registry_pb2_grpc
from tests.fakes import AckingCamera, serve_camera
from tests.helpers import poll
from tests.server.test_registry import SIZE, Clock, camera_at

#: A camera 0.8 m up on a robot, looking forward, 30° down, 70° wide: sees the floor from about
#: 1 m to 4 m ahead of the robot.
MOUNT = Mount(0.1, 0.0, 0.8, 0.0, 30.0, hfov_deg=70.0)
BASE = MOUNT.base_homography(SIZE)
#: Pitched 20° up with a 40° wide lens: the whole image is above the horizon.
SKY = Mount(0.0, 0.0, 0.8, 0.0, -20.0, hfov_deg=40.0).base_homography(SIZE)


def ahead(pose: Pose2, metres: float = 2.5, half: float = 0.3) -> Polygon:
    """A small square `metres` in front of a robot at `pose`."""
    x = pose.x + metres * math.cos(pose.yaw)
    y = pose.y + metres * math.sin(pose.yaw)
    return box(x - half, y - half, x + half, y + half)


def mobile_registry(clock: Clock, **limits: float) -> Registry:
    reg = Registry(lease_ttl_s=10.0, clock=clock.reader(), **limits)
    reg.register("scout", "127.0.0.1:9", BASE, SIZE, {"hsv"}, 6.0, mobile=True)
    return reg


def seeing(reg: Registry, region: Polygon) -> list[str]:
    return [e.camera_id for e in reg.cameras_seeing(region)]


def test_the_routed_field_of_view_follows_the_pose() -> None:
    clock = Clock()
    reg = mobile_registry(clock)
    here, there = Pose2(2.0, 3.0, 0.0), Pose2(20.0, -5.0, math.pi / 2)
    assert seeing(reg, ahead(here)) == []  # no pose yet: not routed
    assert reg.unroutable("scout") == "no pose yet"
    entry = reg.update_pose("scout", here)
    assert seeing(reg, ahead(here)) == ["scout"] and seeing(reg, ahead(there)) == []
    state = reg.mobile_state("scout")
    assert state is not None and state.base_fov is not None
    assert entry.field_of_view.equals_exact(move_polygon(state.base_fov, here), 1e-9)
    clock.advance(7.0)  # 19.7 m away: at the default 3 m/s (and a 1 m jump) that takes 6.2 s
    reg.update_pose("scout", there)
    assert seeing(reg, ahead(there)) == ["scout"] and seeing(reg, ahead(here)) == []
    # Behind the robot is not in view: the field of view turned with it.
    assert seeing(reg, ahead(there, -2.5)) == []
    assert reg.unroutable("scout") == ""


def test_a_stale_pose_leaves_routing_and_a_fresh_one_restores_it() -> None:
    clock = Clock()
    reg = mobile_registry(clock, pose_lease_s=1.0)
    pose = Pose2(0.0, 0.0, 0.0)
    reg.update_pose("scout", pose)
    clock.advance(0.9)
    assert seeing(reg, ahead(pose)) == ["scout"]
    clock.advance(0.2)  # 1.1 s since the pose: beyond its lease
    assert seeing(reg, ahead(pose)) == []
    assert reg.unroutable("scout").startswith("pose stale")
    assert "scout" in reg and [e.camera_id for e in reg.cameras()] == ["scout"]  # still registered
    reg.update_pose("scout", pose)
    assert seeing(reg, ahead(pose)) == ["scout"]


def test_a_camera_asks_its_own_pose_lease_within_the_cap() -> None:
    clock = Clock()
    reg = Registry(lease_ttl_s=10.0, clock=clock.reader(), pose_lease_s=1.0, max_pose_lease_s=3.0)
    reg.register("slow", "127.0.0.1:9", BASE, SIZE, {"hsv"}, 6.0, mobile=True, pose_lease_s=2.0)
    reg.register("greedy", "127.0.0.1:9", BASE, SIZE, {"hsv"}, 6.0, mobile=True, pose_lease_s=60.0)
    assert reg.mobile_state("slow").pose_lease_s == 2.0  # type: ignore[union-attr]
    assert reg.mobile_state("greedy").pose_lease_s == 3.0  # type: ignore[union-attr]
    with pytest.raises(InvalidArgument, match=r"^pose_lease_s: "):
        reg.register("bad", "127.0.0.1:9", BASE, SIZE, {"hsv"}, 6.0, mobile=True, pose_lease_s=-1.0)
    assert "bad" not in reg


def test_a_mount_that_sees_no_floor_stays_registered_but_is_never_routed() -> None:
    clock = Clock()
    reg = Registry(lease_ttl_s=10.0, clock=clock.reader())
    reg.register("stargazer", "127.0.0.1:9", SKY, SIZE, {"hsv"}, 6.0, mobile=True)
    assert "stargazer" in reg and "sees no floor" in reg.unroutable("stargazer")
    reg.update_pose("stargazer", Pose2(0.0, 0.0, 0.0))
    assert seeing(reg, box(-50, -50, 50, 50)) == []
    reg.renew("stargazer")  # it may heartbeat
    # The same homography as a fixed camera is refused, as it always was.
    with pytest.raises(InvalidArgument, match="sees no floor"):
        reg.register("fixed-sky", "127.0.0.1:9", SKY, SIZE, {"hsv"}, 6.0)


def test_pose_updates_are_checked_before_anything_changes() -> None:
    clock = Clock()
    reg = mobile_registry(clock, min_pose_interval_s=0.1)
    reg.register("fixed", "127.0.0.1:9", camera_at(0.0), SIZE, {"hsv"}, 6.0)
    pose = Pose2(1.0, 1.0, 0.0)
    reg.update_pose("scout", pose)
    before = reg.get("scout")
    clock.advance(0.05)
    with pytest.raises(ResourceExhausted, match=r"^pose: camera 'scout' updated 0.050 s ago"):
        reg.update_pose("scout", Pose2(9.0, 9.0, 0.0))
    for bad, field in ((Pose2(math.nan, 0.0, 0.0), "pose.x"), (Pose2(0.0, 0.0, math.inf), "pose.yaw")):
        clock.advance(0.2)
        with pytest.raises(InvalidArgument, match=rf"^{field}: "):
            reg.update_pose("scout", bad)
    clock.advance(0.2)
    with pytest.raises(InvalidArgument, match=r"^pose: \(2e\+07, 0\) is beyond"):
        reg.update_pose("scout", Pose2(2e7, 0.0, 0.0))
    assert reg.get("scout") is before and reg.mobile_state("scout").pose == pose  # type: ignore[union-attr]
    with pytest.raises(FailedPrecondition, match="registered as a fixed camera"):
        reg.update_pose("fixed", pose)
    with pytest.raises(NotFound):
        reg.update_pose("nobody", pose)


def test_a_mobile_camera_beside_ten_thousand_fixed_ones_never_rebuilds_their_index() -> None:
    clock = Clock()
    reg = Registry(lease_ttl_s=1e6, clock=clock.reader(), min_pose_interval_s=0.0)
    for i in range(10_000):
        reg.register(f"fixed-{i:05d}", "127.0.0.1:9", camera_at(30.0 * (i % 100), 30.0 * (i // 100)), SIZE, {"hsv"}, 8)
    reg.register("scout", "127.0.0.1:9", BASE, SIZE, {"hsv"}, 6.0, mobile=True)
    near_fixed = box(-0.5, 3.0, 0.5, 4.0)  # fixed-00000 sees it
    assert seeing(reg, near_fixed) == ["fixed-00000"]
    changes = reg._tree.changes
    for k in range(50):  # the scout drives past fixed-00000's view and on
        pose = Pose2(-3.0 + 0.1 * k, 3.5, 0.0)
        clock.advance(0.01)
        reg.update_pose("scout", pose)
        found = seeing(reg, near_fixed)
        sees = reg.get("scout").field_of_view.intersection(near_fixed).area > 0
        assert found == (["fixed-00000", "scout"] if sees else ["fixed-00000"])
        assert reg._tree.changes == changes  # the static index was never touched
    assert seeing(reg, box(2900, 2900, 2910, 2910)) == []


def _report(camera_id: str, xy: tuple[float, float], pose: Pose2 | None) -> DetectionReport:
    outline = box(xy[0] - 0.1, xy[1] - 0.1, xy[0] + 0.1, xy[1] + 0.1)
    detection = Detection(outline, outline.bounds, xy, xy, PixelBox(0, 0, 10, 10), 0.04, 100.0, 1.0, "hsv_x")
    return DetectionReport("r", camera_id, 1.0, 0, True, (detection,), camera_pose=pose)


def test_fusion_weighs_a_mobile_cameras_detection_through_its_pose() -> None:
    """The mobile camera's registered homography is to its robot's base: with the report's pose its
    sigma is the same as a fixed camera with the composed homography; without it, much worse."""
    pose = Pose2(5.0, 5.0, 1.0)
    composed = map_homography(BASE, pose)
    spot = (float(composed.apply([[320.0, 400.0]])[0][0]), float(composed.apply([[320.0, 400.0]])[0][1]))
    homographies: dict[str, Homography] = {"scout": BASE, "fixed-twin": composed}
    moved = fuse([_report("scout", spot, pose)], homographies.get)[0]
    twin = fuse([_report("fixed-twin", spot, None)], homographies.get)[0]
    assert moved.uncertainty_m == pytest.approx(twin.uncertainty_m, rel=1e-6)
    unmoved = fuse([_report("scout", spot, None)], homographies.get)[0]
    assert unmoved.uncertainty_m != pytest.approx(twin.uncertainty_m, rel=0.05)


# --- a real server ----------------------------------------------------------------------------


class _Recording(AckingCamera):
    def __init__(self) -> None:
        super().__init__("scout")
        self.requests: asyncio.Queue[detection_pb2.DetectionRequest] = asyncio.Queue()

    async def batch(self, requests: object) -> None:
        for r in requests:  # type: ignore[attr-defined]
            self.requests.put_nowait(r)


def mobile_message(address: str, homography: Homography = BASE, lease: float = 0.0) -> registry_pb2.RegisterRequest:
    return registry_pb2.RegisterRequest(
        camera_id="scout",
        address=address,
        homography=registry_pb2.Homography(m=homography.to_list()),
        image_width=SIZE[0],
        image_height=SIZE[1],
        max_range_m=6.0,
        detector_kinds=["hsv"],
        mobile=True,
        pose_lease_s=lease,
    )


def pose_message(secret: str, pose: Pose2) -> registry_pb2.UpdatePoseRequest:
    return registry_pb2.UpdatePoseRequest(
        camera_id="scout",
        registration_secret=secret,
        pose=geometry_pb2.Pose2(x=pose.x, y=pose.y, yaw=pose.yaw),
        pose_time_unix=1.0,
    )


async def routed(address: str, region: Polygon) -> list[str]:
    async with DrvsClient.connect(address, robot_id="watcher") as drvs:
        return [c.camera_id for c in await drvs.cameras(region)]


async def test_a_real_server_routes_a_mobile_camera_where_its_pose_puts_it() -> None:
    camera = _Recording()
    camera_server, camera_address = await serve_camera(camera)
    try:
        async with (
            running_server("--pose-lease", "0.5", "--min-pose-interval", "0.05") as (_proc, address),
            aio.insecure_channel(address) as channel,
        ):
            registry = registry_pb2_grpc.RegisterVisionServiceStub(channel)
            reply = await registry.Register(mobile_message(camera_address))
            assert reply.unroutable == "" and reply.pose_lease_s == 0.5 and reply.min_pose_interval_s == 0.05
            assert len(reply.field_of_view.points) >= 3  # in the base frame
            here = Pose2(3.0, 2.0, 0.0)
            assert await routed(address, ahead(here)) == []
            moved = await registry.UpdatePose(pose_message(reply.registration_secret, here))
            assert moved.pose_lease_s == 0.5 and len(moved.field_of_view.points) >= 3
            assert await routed(address, ahead(here)) == ["scout"]
            async with DrvsClient.connect(address, robot_id="turtle") as drvs:
                listed = {c.camera_id: c for c in await drvs.cameras()}
                assert listed["scout"].mobile and listed["scout"].pose == here and listed["scout"].unroutable == ""
                # A request for the floor ahead of the robot is forwarded to the mobile camera ...
                async with drvs.subscribe("hsv_014110130035225200", ahead(here).bounds, timeout_s=0.5) as sub:
                    assert sub.camera_ids == ("scout",)
                forwarded = await asyncio.wait_for(camera.requests.get(), 10)
                assert forwarded.request_id.startswith(sub.request_id)
                # ... and, once its pose is stale, not any more (polled: the lease runs on the server's clock).
                await poll(lambda: routed(address, ahead(here)), lambda ids: "scout" not in ids,
                           what="the scout unrouted once its pose is stale", every=0.1)  # fmt: skip
                listed = {c.camera_id: c for c in await drvs.cameras()}
                assert listed["scout"].unroutable.startswith("pose stale")
                result = await drvs.detect("hsv_014110130035225200", ahead(here).bounds, timeout_s=0.5)
                assert result.camera_ids == ()
            await registry.UpdatePose(pose_message(reply.registration_secret, here))
            assert await routed(address, ahead(here)) == ["scout"]
    finally:
        await camera_server.stop(0)


async def test_only_the_ids_holder_moves_a_mobile_camera_and_bad_poses_change_nothing() -> None:
    async with (
        running_server("--min-pose-interval", "5", "--pose-lease", "30", "--max-pose-lease", "30") as (
            _proc,
            address,
        ),
        aio.insecure_channel(address) as channel,
    ):
        registry = registry_pb2_grpc.RegisterVisionServiceStub(channel)
        reply = await registry.Register(mobile_message("127.0.0.1:9"))
        here = Pose2(3.0, 2.0, 0.0)
        await registry.UpdatePose(pose_message(reply.registration_secret, here))
        elsewhere = Pose2(40.0, 40.0, 0.0)
        # A wrong secret (another caller, or a previous registration) may not move it.
        with pytest.raises(grpc.RpcError) as refused:
            await registry.UpdatePose(pose_message("not-the-secret", elsewhere))
        assert refused.value.code() == grpc.StatusCode.FAILED_PRECONDITION
        # Too soon after the last update.
        with pytest.raises(grpc.RpcError) as refused:
            await registry.UpdatePose(pose_message(reply.registration_secret, elsewhere))
        assert refused.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        # A pose that is not finite, or none at all.
        bad = pose_message(reply.registration_secret, Pose2(math.nan, 0.0, 0.0))
        with pytest.raises(grpc.RpcError) as refused:
            await registry.UpdatePose(bad)
        assert refused.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert (refused.value.details() or "").startswith("pose.x")
        missing = registry_pb2.UpdatePoseRequest(camera_id="scout", registration_secret=reply.registration_secret)
        with pytest.raises(grpc.RpcError) as refused:
            await registry.UpdatePose(missing)
        assert refused.value.code() == grpc.StatusCode.INVALID_ARGUMENT and refused.value.details() == "pose: missing"
        # A fixed camera has no pose.
        fixed = await registry.Register(
            registry_pb2.RegisterRequest(
                camera_id="fixed",
                address="127.0.0.1:9",
                homography=registry_pb2.Homography(m=camera_at(0.0).to_list()),
                image_width=SIZE[0],
                image_height=SIZE[1],
                max_range_m=6.0,
                detector_kinds=["hsv"],
            )
        )
        wrong = pose_message(fixed.registration_secret, here)
        wrong.camera_id = "fixed"
        with pytest.raises(grpc.RpcError) as refused:
            await registry.UpdatePose(wrong)
        assert refused.value.code() == grpc.StatusCode.FAILED_PRECONDITION
        # Nothing moved: it is still where its holder put it.
        assert await routed(address, ahead(here)) == ["scout"]
        assert await routed(address, ahead(elsewhere)) == []
        # A mount that sees no floor: registered, unroutable, and says why.
        sky = mobile_message("127.0.0.1:9", SKY)
        sky.camera_id = "stargazer"
        reply = await registry.Register(sky)
        assert "sees no floor" in reply.unroutable and not reply.HasField("field_of_view")

"""Scouts: robots of the simulation that drive a path and carry a camera (a mobile camera node).

Their frames are rendered from where they are at world time, their poses come from the world
(WatchScout), a mover serves those as the tcp:// feed a real robot's localisation would, and the
other cameras see the scout's body. With real processes: a scout's camera registers as mobile, the
server routes by its field of view as it drives, and a robot hears of what only the scout sees."""

from __future__ import annotations

import asyncio
import json
import math
import re
import time
from collections.abc import AsyncIterator, Callable

import grpc
import pytest
import pytest_asyncio
from grpc import aio
from shapely.geometry import box

from drvs import DrvsClient
from drvs.core.filters import object_type
from drvs.core.geometry import FieldOfView
from drvs.core.model import Detection, Pose2
from drvs.detectors.base import REGISTRY, CameraView, Frame, FrameAnalysis
from drvs.sim.office import start_scout
from drvs.sim.poses import Mover, SimPoseSource, parse_spec
from drvs.sim.render import CameraRenderer
from drvs.sim.scenario import Scenario, load_scenario, parse_scenario
from drvs.sim.world import WorldServer
from drvs.tools.launch import ManagedProcess, start_server
from drvs.v1 import sim_pb2, sim_pb2_grpc
from drvs.wire import _grpc
from tests.sim.test_scenario import with_change

YELLOW = "hsv_014110130035225200"
#: The default office's obstacle that only its scout sees.
HIDDEN = box(10.6, 6.25, 11.4, 7.05)


def blobs(
    scenario: Scenario, camera_id: str, world_time: float, robot: tuple[float, float] | None = None
) -> list[Detection]:
    """What the real HSV detector finds in a camera's rendered frame at `world_time`, mapped to the
    floor by where that camera is then (a scout's: by its pose at that time)."""
    scout = scenario.scout_camera(camera_id)
    camera = scout or scenario.camera(camera_id)
    h = scout.homography_at(world_time) if scout else scenario.camera(camera_id).homography
    fov = FieldOfView.compute(h, camera.resolution, camera.max_range_m)
    image = CameraRenderer(scenario, camera, seed=4).render(robot, 1, 0.0, world_time)
    view = CameraView(h, fov, camera.resolution, camera_id=camera_id)
    return list(REGISTRY["hsv"](view, None).find(FrameAnalysis(Frame(image, time.time(), 1)), object_type(YELLOW)))


@pytest.mark.parametrize("world_time", [0.0, 1.5, 3.0, 4.0])
def test_a_scout_camera_sees_a_still_object_in_one_place_as_it_drives(world_time: float) -> None:
    """Frames rendered from the scout's pose at each world time, mapped by that pose: the hidden
    obstacle lands where it is, within 3 cm, from every pose."""
    scenario = load_scenario()
    (scout,) = scenario.scouts
    found = [d for d in blobs(scenario, scout.camera_id, world_time) if d.centroid.distance(HIDDEN.centroid) < 0.5]
    assert len(found) == 1, [d.centroid for d in found]
    assert found[0].centroid.distance(HIDDEN.centroid) < 0.03, (world_time, found[0].centroid)


def test_the_other_cameras_see_a_scout_where_it_is() -> None:
    """A fixed camera that looks where a scout drives sees its body where its path puts it at
    world time, and not where it is not."""
    scenario = parse_scenario(with_change("scouts[0].path", [[4.5, 5.0], [6.0, 5.0]]), "office.yaml")
    (scout,) = scenario.scouts
    watcher = scenario.camera("cam-west")
    renderer = CameraRenderer(scenario, watcher, seed=4)
    to_image = watcher.homography.inverse()

    def colour_at(t: float, xy: tuple[float, float]) -> tuple[int, ...]:
        u, v = to_image.apply([xy])[0]
        image = renderer.render(None, 1, 0.0, t)
        return tuple(int(c) for c in image[round(v), round(u)])

    for t in (0.0, 2.0):
        here = scout.body_at(t).centroid
        assert watcher.field_of_view.floor.contains(scout.body_at(t))
        assert max(abs(a - b) for a, b in zip(colour_at(t, (here.x, here.y)), scout.bgr, strict=True)) < 30
    # Where it was at 0 s, it is not at 2 s (it drove 1 m east): there is floor.
    start = scout.body_at(0.0).centroid
    assert max(abs(a - b) for a, b in zip(colour_at(2.0, (start.x, start.y)), scout.bgr, strict=True)) > 30


@pytest_asyncio.fixture
async def world() -> AsyncIterator[WorldServer]:
    async with WorldServer(load_scenario(), "127.0.0.1:0", seed=4) as w:
        yield w


async def test_the_world_streams_a_scouts_poses_and_refuses_unknown_ones(world: WorldServer) -> None:
    (scout,) = world.state.scenario.scouts
    async with _grpc.insecure_channel(world.address) as channel:
        stub = sim_pb2_grpc.SimulatedWorldStub(channel)
        await stub.Start(sim_pb2.StartRequest())
        poses = []
        async for p in stub.WatchScout(sim_pb2.WatchScoutRequest(scout_id=scout.id, rate_hz=50)):
            poses.append(p)
            if len(poses) == 10:
                break
        for p in poses:  # each where its path puts it at the world time it names
            truth = scout.pose_at(p.world_time_s)
            assert (p.x, p.y, p.theta) == pytest.approx((truth.x, truth.y, truth.yaw))
            assert p.time_unix == pytest.approx(world.state.clock_start + p.world_time_s)
        assert poses[-1].world_time_s > poses[0].world_time_s and poses[-1].y < poses[0].y  # driving south
        with pytest.raises(aio.AioRpcError) as err:
            async for _ in stub.WatchScout(sim_pb2.WatchScoutRequest(scout_id="nobody")):
                pass
        assert err.value.code() == grpc.StatusCode.NOT_FOUND and "no scout with id 'nobody'" in str(err.value.details())
        with pytest.raises(aio.AioRpcError) as err:
            async for _ in stub.WatchScout(sim_pb2.WatchScoutRequest(scout_id=scout.id, rate_hz=-1)):
                pass
        assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "rate_hz" in str(err.value.details())


async def test_the_sim_pose_source_and_the_movers_feed_carry_the_scouts_poses(world: WorldServer) -> None:
    """The `sim://` plug-in pushes the world's poses; the mover serves them as tcp:// NDJSON lines,
    late and noisy by what it is told (its noise is seeded: the same run gives the same lines)."""
    (scout,) = world.state.scenario.scouts
    source = SimPoseSource(f"sim://{world.address}/{scout.id}")
    got: list[tuple[float, Pose2]] = []
    enough = asyncio.Event()

    def push(t: float, pose: Pose2) -> None:
        got.append((t, pose))
        if len(got) >= 3:
            enough.set()

    reading = asyncio.get_running_loop().create_task(source.run(push))
    try:
        await asyncio.wait_for(enough.wait(), 10)
    finally:
        reading.cancel()
    assert all(pose == scout.pose_at(0.0) for _, pose in got)  # the clock has not started: it waits at its start

    mover = Mover(world.address, scout.id, noise_m=0.05, noise_deg=2.0, seed=7)
    await mover.start()
    try:
        reader, writer = await asyncio.open_connection(*mover.address.rsplit(":", 1))
        lines = [json.loads(await asyncio.wait_for(reader.readline(), 10)) for _ in range(20)]
        writer.close()
    finally:
        await mover.stop()
    start = scout.pose_at(0.0)
    dx = [line["x"] - start.x for line in lines]
    assert 0 < max(abs(d) for d in dx) < 0.25 and abs(sum(dx) / len(dx)) < 0.05  # noisy, about the truth
    assert Mover(world.address, scout.id, seed=7).line(1.0, start) == Mover(world.address, scout.id, seed=7).line(
        1.0, start
    )


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("sim://127.0.0.1:1", "names no scout; expected sim://HOST:PORT/SCOUT_ID"),
        ("sim://nohost/scout-1", "--pose-source"),
        ("sim://127.0.0.1:1/bad id", "scout id"),
    ],
)
def test_bad_sim_pose_sources_are_refused(spec: str, message: str) -> None:
    with pytest.raises(Exception, match=message.replace("(", r"\(")):
        parse_spec(spec)


def test_a_mover_refuses_bad_settings() -> None:
    for kwargs, message in (
        ({"delay_s": -1.0}, "--delay-s"),
        ({"noise_m": math.nan}, "--noise-m"),
        ({"rate_hz": 0.0}, "--rate-hz"),
    ):
        with pytest.raises(Exception, match=message):
            Mover("127.0.0.1:1", "scout-1", **kwargs)  # type: ignore[arg-type]


@pytest.mark.slow
async def test_a_scout_is_a_mobile_camera_node_the_server_routes_as_it_drives(world: WorldServer) -> None:
    """Real processes: the server, the scout's mover and its mobile drvs-camera (rendering the world
    from where the scout is). A robot's request over the corner no fixed camera sees goes to the
    scout's camera and finds the obstacle there; once the world's clock runs, the field of view the
    server routes by follows the scout, and the camera's reports carry its pose at capture."""
    (scout,) = world.state.scenario.scouts
    server: ManagedProcess
    # DEBUG: the server logs every pose it moves a mobile camera to (POSE_APPLIED); the test waits on those.
    server, address = await start_server("--min-pose-interval", "0.05", "--log-level", "DEBUG")
    procs: list[ManagedProcess] = [server]
    posed = re.compile(rf"camera {re.escape(scout.camera_id)} at pose x=(\S+) y=(\S+)")

    def pose_where(accept: Callable[[float, float], bool]) -> Callable[[str], tuple[float, float] | None]:
        def check(line: str) -> tuple[float, float] | None:
            m = posed.search(line)
            xy = (float(m.group(1)), float(m.group(2))) if m else None
            return xy if xy is not None and accept(*xy) else None

        return check

    try:
        procs += await start_scout(scout, world.address, address, "--detectors", "hsv")
        async with DrvsClient.connect(address, robot_id="turtle") as drvs:
            await server.wait_for(pose_where(lambda x, y: True), "the scout's first pose", 20)
            (cam,) = await drvs.cameras(HIDDEN)
            assert cam.camera_id == scout.camera_id and cam.mobile and cam.unroutable == ""
            start = scout.pose_at(0.0)
            assert cam.pose is not None and math.dist((cam.pose.x, cam.pose.y), (start.x, start.y)) < 1e-6
            result = await drvs.detect(YELLOW, HIDDEN, timeout_s=10)
            assert result.camera_ids == (scout.camera_id,) and not result.errors, result
            (d,) = [d for d in result.detections if d.outline.area > 0.2]
            assert d.centroid.distance(HIDDEN.centroid) < 0.03
            (report,) = result.reports
            assert (
                report.camera_pose is not None
                and math.dist((report.camera_pose.x, report.camera_pose.y), (start.x, start.y)) < 0.01
            )
            # The clock starts: the scout drives; its routed field of view goes with it.
            async with _grpc.insecure_channel(world.address) as channel:
                await sim_pb2_grpc.SimulatedWorldStub(channel).Start(sim_pb2.StartRequest())
            await server.wait_for(pose_where(lambda x, y: y < start.y - 0.3), "the scout 0.3 m on", 20)
            (cam,) = [c for c in await drvs.cameras() if c.camera_id == scout.camera_id]
            assert cam.pose is not None and cam.pose.y < start.y - 0.3
            # Where it is now (by the world's clock), within what the pose-update thresholds allow.
            truth = scout.pose_at(world.state.world_time())
            assert math.dist((cam.pose.x, cam.pose.y), (truth.x, truth.y)) < 0.5
    finally:
        for proc in reversed(procs):
            await proc.stop()

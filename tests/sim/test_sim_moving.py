"""Moving obstacles in the simulator: a scenario's path and speed put an obstacle somewhere at each
world time; the cameras' rendered pixels show it there (found by the real HSV detector and mapped
through the camera's homography), and the world's bumper feels it there and nowhere else."""

from __future__ import annotations

import asyncio
import math
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from numpy.typing import NDArray
from shapely.geometry import Point

from drvs.core.filters import object_type
from drvs.core.model import Detection
from drvs.detectors.base import REGISTRY, CameraView, Frame, FrameAnalysis
from drvs.sim.render import CameraRenderer
from drvs.sim.scenario import DEFAULT_SCENARIO, Scenario, ScenarioError, load_scenario, parse_scenario
from drvs.sim.source import SimSource
from drvs.sim.world import WorldServer, WorldState
from drvs.v1 import sim_pb2, sim_pb2_grpc
from drvs.wire import _grpc
from tests.sim.test_scenario import with_change

SMALL_ROOM = Path(__file__).parents[1] / "scenarios" / "small_room.yaml"
CROSSING = Path(__file__).parents[1] / "scenarios" / "crossing.yaml"
YELLOW = "hsv_014110130035225200"


def small_room_with_trolley(loop: bool = False) -> Scenario:
    """The small room with its obstacle replaced by a 0.4 m yellow trolley pushed north across the
    robot's line (y = 2) at 0.5 m/s: its centre from (4, 0.6) to (4, 3.2), 2.6 m, 5.2 s."""
    data = yaml.safe_load(SMALL_ROOM.read_text())
    data["objects"][0] = {
        "kind": "obstacle", "color": "yellow", "polygon": [[3.8, 0.4], [4.2, 0.4], [4.2, 0.8], [3.8, 0.8]],
        "path": [[4.0, 3.2]], "speed_mps": 0.5, "loop": loop,
    }  # fmt: skip
    return parse_scenario(yaml.safe_dump(data), "small-room-trolley")


def test_a_path_puts_the_obstacle_where_its_speed_takes_it() -> None:
    trolley = small_room_with_trolley().moving_obstacles[0]
    assert trolley.path == ((4.0, 0.6), (4.0, 3.2)) and trolley.speed_mps == 0.5 and not trolley.loop
    for t, y in ((0.0, 0.6), (-1.0, 0.6), (1.0, 1.1), (2.8, 2.0), (5.2, 3.2), (60.0, 3.2)):  # stops at the end
        c = trolley.shape_at(t).centroid
        assert math.isclose(c.x, 4.0, abs_tol=1e-9) and math.isclose(c.y, y, abs_tol=1e-9), (t, c)
    assert math.isclose(trolley.shape_at(1.0).area, trolley.shape.area)
    looping = small_room_with_trolley(loop=True).moving_obstacles[0]
    for t, y in ((5.2, 3.2), (6.2, 2.7), (10.4, 0.6), (11.4, 1.1)):  # back and forth
        assert math.isclose(looping.shape_at(t).centroid.y, y, abs_tol=1e-9), t
    # Through several points, at constant speed along the polyline.
    data = yaml.safe_load(SMALL_ROOM.read_text())
    data["objects"][0] = {"kind": "obstacle", "color": "yellow", "center": [1, 1], "radius": 0.2,
                          "path": [[2, 1], [2, 3]], "speed_mps": 1.0}  # fmt: skip
    walker = parse_scenario(yaml.safe_dump(data)).moving_obstacles[0]
    assert walker.offset_at(0.5) == pytest.approx((0.5, 0.0)) and walker.offset_at(2.0) == pytest.approx((1.0, 1.0))
    assert not load_scenario(SMALL_ROOM).moving_obstacles


def test_the_default_office_has_a_trolley_crossing_the_hallway() -> None:
    office = load_scenario(DEFAULT_SCENARIO)
    (trolley,) = office.moving_obstacles
    hallway_y = (5.5, 8.0)
    ys = [trolley.shape_at(t).centroid.y for t in range(60)]
    assert min(ys) < hallway_y[0] + 0.5 and max(ys) > hallway_y[1] - 0.5, "it crosses the hallway"
    assert trolley.color is not None and trolley.color.filter_def == YELLOW  # the robot knows the colour


@pytest.mark.parametrize(
    ("path", "value", "message"),
    [
        ("objects[0].path", [], r"objects\[0\]\.path: expected a non-empty list of \[x, y\] points"),
        ("objects[0].path", [[4, 1]], r"objects\[0\]\.speed_mps: missing"),
        ("objects[0].path", [[4, "x"]], r"objects\[0\]\.path\[0\]\[1\]: x is not a finite number"),
        ("objects[0].path", [4, 1], r"objects\[0\]\.path\[0\]: expected a list of 2 numbers"),
        ("objects[0].path", [[4.0, 2.0]], r"objects\[0\]\.path: every point is where the obstacle starts"),
        ("objects[0].path", [[7.9, 2.0]], r"objects\[0\]\.path\[0\]: at \[7\.9, 2\] the obstacle is not inside"),
        ("objects[0].speed_mps", 1.0, r"objects\[0\]\.speed_mps: only with path"),
        ("objects[0].loop", True, r"objects\[0\]\.loop: only with path"),
        ("objects[1].path", [[1, 1]], r"objects\[1\]\.path: only an obstacle moves"),
        ("objects[2].speed_mps", 1, r"objects\[2\]\.speed_mps: only an obstacle moves"),
    ],
)
def test_bad_paths_name_the_key(path: str, value: object, message: str) -> None:
    with pytest.raises(ScenarioError, match=message):
        parse_scenario(with_change(path, value, SMALL_ROOM), "small_room.yaml")


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("speed_mps", 0, r"objects\[0\]\.speed_mps: 0 must be between 0\.01 and 10"),
        ("speed_mps", "fast", r"objects\[0\]\.speed_mps: fast is not a finite number"),
        ("loop", "yes", r"objects\[0\]\.loop: expected true \(back and forth along the path\) or false"),
    ],
)
def test_bad_speed_and_loop_name_the_key(key: str, value: object, message: str) -> None:
    data = yaml.safe_load(SMALL_ROOM.read_text())
    data["objects"][0].update({"path": [[4.0, 3.0]], "speed_mps": 0.5, key: value})
    with pytest.raises(ScenarioError, match=message):
        parse_scenario(yaml.safe_dump(data), "small_room.yaml")


def yellow_blobs(scenario: Scenario, world_time: float, version: int = 1) -> list[Detection]:
    """What the real HSV detector finds in the overhead camera's rendered frame at `world_time`."""
    cam = scenario.cameras[0]
    view = CameraView(cam.homography, cam.field_of_view, cam.resolution, camera_id=cam.id)
    image = CameraRenderer(scenario, cam, seed=2).render((1.0, 2.0), version, 0.0, world_time)
    found = REGISTRY["hsv"](view, None).find(FrameAnalysis(Frame(image, time.time(), version)), object_type(YELLOW))
    return list(found)


@pytest.mark.parametrize("world_time", [0.0, 1.4, 2.8, 4.0])
def test_cameras_render_the_moving_obstacle_where_it_is_at_world_time(world_time: float) -> None:
    scenario = small_room_with_trolley()
    trolley = scenario.moving_obstacles[0]
    truth = trolley.shape_at(world_time)
    blobs = [d for d in yellow_blobs(scenario, world_time) if d.outline.area > 0.1]  # not the small markers
    assert len(blobs) == 1, [d.centroid for d in blobs]
    (blob,) = blobs
    assert blob.centroid.distance(truth.centroid) < 0.03, (blob.centroid, truth.centroid)
    assert blob.outline.intersection(truth).area > 0.85 * truth.area
    # A frame is a function of the seed and the world's state, time included: the same again.
    cam = scenario.cameras[0]
    frames = [CameraRenderer(scenario, cam, seed=2).render((1.0, 2.0), 1, 0.0, world_time) for _ in range(2)]
    assert np.array_equal(frames[0], frames[1])
    # ... and nowhere it was a second earlier (the static render holds no ghost of it).
    if world_time >= 1.0:
        before = trolley.shape_at(world_time - 1.0)
        assert not blob.outline.intersects(before.difference(truth.buffer(0.02)))


def test_the_bumper_feels_a_moving_obstacle_where_it_is_now() -> None:
    scenario = small_room_with_trolley()
    trolley = scenario.moving_obstacles[0]
    state = WorldState(scenario)
    start = 1000.0
    assert state.start_clock(start) == start and state.start_clock(start + 5) == start  # it starts once
    state.pose = type(state.pose)(3.5, 2.0, 0.0, state.pose.version, start)
    # At world time 0 the trolley is at y = 0.6: a move along y = 2 across its line is free ...
    pose, contact = state.move(4.5, 2.0, 0.0, now=start)
    assert contact is None and math.isclose(pose.x, 4.5)
    # ... and at world time 2.8 it stands on that line: the same move stops at it, reporting its outline there.
    state.pose = type(state.pose)(3.5, 2.0, 0.0, pose.version, start)
    pose, contact = state.move(4.5, 2.0, 0.0, now=start + 2.8)
    assert contact is not None and contact.equals_exact(trolley.shape_at(2.8), 1e-6)
    assert pose.x < 3.8 - scenario.robot.radius + 0.011 and Point(pose.x, pose.y).distance(contact) >= 0.19
    assert state.collisions == 1
    # Once it has passed (world time 5.2: at y = 3.2, its end) the line is free again.
    pose, contact = state.move(4.5, 2.0, 0.0, now=start + 6.0)
    assert contact is None and math.isclose(pose.x, 4.5)


def test_a_world_that_was_never_started_starts_its_clock_at_the_first_move() -> None:
    state = WorldState(small_room_with_trolley())
    assert state.world_time(2000.0) == 0.0 and state.clock_start == 0.0
    state.move(1.05, 2.0, 0.0, now=2000.0)
    assert state.clock_start == 2000.0 and state.world_time(2001.5) == 1.5


def blob_near(image: NDArray[np.uint8], scenario: Scenario, at: float) -> Detection:
    """The one large yellow blob in a frame of the overhead camera (captured at `at`)."""
    cam = scenario.cameras[0]
    view = CameraView(cam.homography, cam.field_of_view, cam.resolution, camera_id=cam.id)
    found = REGISTRY["hsv"](view, None).find(FrameAnalysis(Frame(image, at, 0)), object_type(YELLOW))
    (blob,) = [d for d in found if d.outline.area > 0.1]
    return blob


async def test_a_sim_camera_shows_the_trolley_where_the_world_clock_puts_it() -> None:
    """A real world service and a sim:// camera source (its render thread, the world's pose stream):
    before the robot's Start the trolley stands at its start; after it, each frame shows it where
    its path puts it at the frame's capture time less the clock's start, which the source learns
    from the world's pose stream."""
    scenario = small_room_with_trolley()
    trolley = scenario.moving_obstacles[0]
    async with WorldServer(scenario, "127.0.0.1:0", seed=1) as world:
        source = SimSource(f"sim://{world.address}", "overhead")
        await asyncio.to_thread(source.start)
        try:
            first = await source.wait_first_frame(10)
            assert blob_near(first.image, scenario, first.capture_time).centroid.distance(trolley.shape.centroid) < 0.03
            async with _grpc.insecure_channel(world.address) as channel:
                reply = await sim_pb2_grpc.SimulatedWorldStub(channel).Start(sim_pb2.StartRequest(), timeout=5)
            clock_start = reply.clock_start_unix
            assert abs(clock_start - time.time()) < 1.0 and world.state.clock_start == clock_start
            seen: list[tuple[float, Detection]] = []
            deadline = time.monotonic() + 15
            while len(seen) < 2 and time.monotonic() < deadline:  # frames 1 s and 2 s into world time
                frame = source.latest()
                assert frame is not None
                if frame.capture_time - clock_start > 1.0 + len(seen):
                    seen.append((frame.capture_time - clock_start, blob_near(frame.image, scenario, 0.0)))
                await asyncio.sleep(0.02)
        finally:
            await asyncio.to_thread(source.stop)
    assert len(seen) == 2, "no frames of the moving trolley"
    for world_time, blob in seen:
        truth = trolley.shape_at(world_time).centroid
        assert blob.centroid.distance(truth) < 0.03, (world_time, blob.centroid, truth)
    assert seen[1][1].centroid.y - seen[0][1].centroid.y > 0.3  # it moved north between them

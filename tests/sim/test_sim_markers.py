"""ArUco markers in the simulator: rendered where the scenario puts them (on the floor, on the
robot's top plate turning with it), and found there by the aruco detector on the rendered pixels."""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from shapely.geometry import Polygon

from drvs.core.filters import object_type
from drvs.core.model import Detection
from drvs.detectors.base import REGISTRY, CameraView, Frame, FrameAnalysis
from drvs.sim.render import CameraRenderer
from drvs.sim.scenario import Scenario, load_scenario, parse_scenario

ANY_COLOUR = Path(__file__).parents[1] / "scenarios" / "any_colour.yaml"
#: Robot poses (x, y, heading in degrees) spread over the room and over every direction.
POSES = [(3.0, 1.0, 45.0), (5.0, 2.8, -120.0), (2.0, 2.0, 0.0), (6.6, 2.0, 170.0), (4.0, 3.0, 90.0), (1.0, 1.0, -60.0)]


def detect(scenario: Scenario, robot: tuple[float, float, float], version: int) -> dict[int, Detection]:
    cam = scenario.cameras[0]
    view = CameraView(cam.homography, cam.field_of_view, cam.resolution, camera_id=cam.id)
    image = CameraRenderer(scenario, cam, seed=3).render(robot[:2], version, math.radians(robot[2]))
    found = REGISTRY["aruco"](view, None).find(
        FrameAnalysis(Frame(image, time.time(), version)), object_type("aruco_4x4_50")
    )
    return {d.marker_id: d for d in found if d.marker_id is not None}


def heading_error(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def truth(scenario: Scenario, robot: tuple[float, float, float]) -> dict[int, tuple[np.ndarray, float]]:
    """Each marker's floor corners (OpenCV order) and heading, the robot's at its pose."""
    marks = {m.id: (m.corners(), m.heading_deg) for m in scenario.aruco_markers}
    mine = scenario.robot.marker
    assert mine is not None
    marks[mine.id] = (mine.corners(robot[:2], robot[2]), robot[2])
    return marks


def pixel_footprint(scenario: Scenario, corners: np.ndarray) -> float:
    """The largest floor distance one pixel step spans at these floor points."""
    cam = scenario.cameras[0]
    pixels = cam.homography.inverse().apply(corners)
    steps = [cam.homography.apply(pixels + np.array(d)) for d in ((1.0, 0.0), (0.0, 1.0))]
    return float(max(np.linalg.norm(step - corners, axis=1).max() for step in steps))


def close_up() -> Scenario:
    """The room seen from 2.2 m by a camera without noise, lighting drift or floor texture."""
    data = yaml.safe_load(ANY_COLOUR.read_text())
    data["cameras"] = [
        {"id": "close", "position": [5.0, 1.2, 2.2], "yaw_deg": 90, "pitch_deg": 60, "hfov_deg": 70,
         "resolution": [640, 480], "fps": 20}
    ]  # fmt: skip
    data["render"] = {"noise_sigma": 0, "lighting": 0, "floor_texture": 0}
    return parse_scenario(yaml.safe_dump(data), "close-up")


@pytest.mark.parametrize("robot", [(5.0, 2.4, 45.0), (4.4, 2.7, -120.0)])
def test_markers_are_found_where_they_lie_close_up(robot: tuple[float, float, float]) -> None:
    """Seen from close (about 4 mm a pixel) without noise, every marker in view is found with its
    centre within half a camera pixel's footprint on the floor of where it lies, each corner within
    one pixel's footprint and its heading within 1 degree (the detector's sub-pixel corners, not the rendering,
    set these two: measured 0.6 degrees): the renderer puts the printed marker exactly where the
    scenario says, turned as it says."""
    scenario = close_up()
    found = detect(scenario, robot, 1)
    fov = scenario.cameras[0].field_of_view.floor
    expected = {i: t for i, t in truth(scenario, robot).items() if fov.buffer(-0.3).contains(Polygon(t[0]))}
    assert set(expected) <= set(found) and len(expected) >= 2, (sorted(found), sorted(expected))
    for marker_id, (corners, heading) in expected.items():
        d = found[marker_id]
        outline = np.asarray(d.outline.exterior.coords)[:4]
        shift = min(range(4), key=lambda k: float(np.abs(np.roll(outline, -k, axis=0) - corners).max()))
        error = np.linalg.norm(np.roll(outline, -shift, axis=0) - corners, axis=1)
        assert float(error.max()) < pixel_footprint(scenario, corners), (marker_id, error)
        assert math.dist(d.centroid_xy, corners.mean(axis=0)) < pixel_footprint(scenario, corners) / 2, marker_id
        assert d.heading_deg is not None and heading_error(d.heading_deg, heading) < 1.0, (marker_id, d.heading_deg)


@pytest.mark.slow
def test_markers_from_the_ceiling_camera_with_noise() -> None:
    """The office test's ceiling camera, with sensor noise, lighting and a textured floor: every
    floor marker and the robot's, at every pose, within 1 cm and 2 degrees (measured: 4 mm, 1.0)."""
    scenario = load_scenario(ANY_COLOUR)
    for version, robot in enumerate(POSES, start=1):
        found = detect(scenario, robot, version)
        expected = truth(scenario, robot)
        assert set(found) == set(expected), (robot, sorted(found))
        for marker_id, (corners, heading) in expected.items():
            d = found[marker_id]
            assert math.dist(d.centroid_xy, corners.mean(axis=0)) < 0.01, (robot, marker_id, d.centroid_xy)
            assert d.heading_deg is not None and heading_error(d.heading_deg, heading) < 2.0, (robot, marker_id)


def test_one_id_is_the_robots_own() -> None:
    """aruco_4x4_50_1 asks for the robot's marker only, and finds it where the robot stands."""
    scenario = load_scenario(ANY_COLOUR)
    cam = scenario.cameras[0]
    view = CameraView(cam.homography, cam.field_of_view, cam.resolution, camera_id=cam.id)
    detector = REGISTRY["aruco"](view, None)
    image = CameraRenderer(scenario, cam).render((2.0, 1.5), 1, math.radians(30))
    wanted = object_type("aruco_4x4_50_1")
    mine = detector.narrow(detector.find(FrameAnalysis(Frame(image, time.time(), 1)), wanted), wanted)
    assert [d.marker_id for d in mine] == [1] and math.dist(mine[0].centroid_xy, (2.0, 1.5)) < 0.01

"""Scenario files: the built-in office loads; bad files are refused with the key named."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from drvs.core.geometry import FieldOfView
from drvs.sim.scenario import DEFAULT_SCENARIO, ScenarioError, along_path, load_scenario, parse_scenario

OFFICE = yaml.safe_load(DEFAULT_SCENARIO.read_text())


def test_default_office_matches_the_paper() -> None:
    s = load_scenario()
    assert s.mission == "navigate" and len(s.cameras) == 3
    fovs = [c.field_of_view.floor for c in s.cameras]
    for i, a in enumerate(fovs):
        for b in fovs[i + 1 :]:
            assert a.intersection(b).area == 0, "the paper's cameras have non-overlapping views"
    # Every object but one lies inside exactly one fixed camera's view (the trolley where it crosses
    # the hallway: it starts beyond the cameras, at the hallway's far end). The one in the main
    # room's north-east corner no fixed camera sees: the scout's camera does, as it sets off.
    (scout,) = s.scouts
    hidden = [obj for obj in s.objects if sum(f.contains(obj.shape_at(30.0)) for f in fovs) != 1]
    assert [(o.kind, sum(f.intersects(o.shape) for f in fovs)) for o in hidden] == [("obstacle", 0)]
    scout_view = FieldOfView.compute(scout.homography_at(0.0), scout.resolution, scout.max_range_m).floor
    assert scout_view.contains(hidden[0].shape)
    assert len(s.obstacles) == 4 and len(s.moving_obstacles) == 1 and len(s.charging_stations) == 1


def with_change(path: str, value: object, scenario: Path = DEFAULT_SCENARIO) -> str:
    """The scenario file's text with one value at `path` (e.g. objects[0].bgr) set, or removed
    (value KeyError)."""
    data = yaml.safe_load(scenario.read_text())
    node = data
    keys = [int(k) if k.isdigit() else k for k in re.split(r"[.\[\]]+", path) if k]
    for k in keys[:-1]:
        node = node.setdefault(k, {}) if isinstance(node, dict) else node[k]
    if value is KeyError:
        del node[keys[-1]]
    else:
        node[keys[-1]] = value
    return yaml.safe_dump(data)


@pytest.mark.parametrize(
    ("path", "value", "message"),
    [
        ("cameras[0].yawdeg", 3, r"cameras\[0\]\.yawdeg: unknown key"),
        ("floor_plan.doors", [], r"floor_plan\.doors: unknown key"),
        ("surprise", 1, r"surprise: unknown key"),
        ("cameras[1].pitch_deg", -30, r"cameras\[1\]: sees no floor"),
        ("cameras[0].position", [500, 500, 3], r"cameras\[0\]: its field of view does not meet floor_plan\.bounds"),
        ("cameras[0].position", [0, 0, 0], r"cameras\[0\]\.position: mounting height"),
        ("cameras[2].id", "cam-west", r"cameras\[2\]\.id: 'cam-west' is used twice"),
        ("robot.start", [3.0, 4.0], r"robot\.start: \[3\.0, 4\.0\] is inside a wall \(floor_plan\.walls\[4\]\)"),
        ("robot.goal", [30, 3], r"robot\.goal: .* not inside floor_plan\.bounds"),
        ("robot.goal", KeyError, r"robot\.goal: missing"),
        ("robot.color", "purple", r"robot\.color: 'purple' has no definition in colors"),
        ("objects[0].color", "purple", r"objects\[0\]\.color: 'purple' has no definition in colors"),
        ("objects[0].kind", "lamp", r"objects\[0\]\.kind: 'lamp' is not one of"),
        ("colors.yellow.filter_def", "hsv_12", r"colors\.yellow\.filter_def"),
        (
            "colors.yellow.bgr",
            [0, 200, 230],
            r"colors\.yellow\.bgr: \[0, 200, 230\] is HSV .* outside its own filter_def",
        ),
        ("colors.yellow.bgr", [0, 200], r"colors\.yellow\.bgr: expected \[b, g, r\]"),
        ("floor_plan.bounds", [0, 0, -1, 10], r"floor_plan\.bounds"),
        ("floor_plan.walls[0]", [[0, 0], [1, 1], [1, 0], [0, 1]], r"floor_plan\.walls\[0\]: not a simple polygon"),
        ("cameras[0].hfov_deg", float("nan"), r"cameras\[0\]\.hfov_deg: nan is not a finite number"),
        ("mission", "dance", r"mission: 'dance' is not one of"),
        ("render.noise", 1, r"render\.noise: unknown key"),
        ("scouts[0].camera.pitch_deg", -40, r"scouts\[0\]\.camera: sees no floor"),
        ("scouts[0].camera.height", KeyError, r"scouts\[0\]\.camera\.height: missing"),
        ("scouts[0].camera.zoom", 2, r"scouts\[0\]\.camera\.zoom: unknown key"),
        ("scouts[0].path", [[11.6, 9.5], [30, 3]], r"scouts\[0\]\.path\[1\]: \[30\.0, 3\.0\] .* not inside floor"),
        ("scouts[0].path", [[2.5, 4.0]], r"scouts\[0\]\.path\[0\]: \[2\.5, 4\.0\] is inside a wall"),
        ("scouts[0].path", [], r"scouts\[0\]\.path: expected a non-empty list"),
        ("scouts[0].loop", "yes", r"scouts\[0\]\.loop: expected true"),
        ("scouts[0].speed_mps", 0, r"scouts\[0\]\.speed_mps"),
        ("scouts[0].id", "cam-west", r"scouts\[0\]\.id: 'cam-west' is already a camera's or a scout's id"),
        ("scouts[0].camera.id", "cam-hall", r"scouts\[0\]\.camera\.id: 'cam-hall' is already"),
        ("scouts", {"id": "x"}, r"scouts: expected a list"),
    ],
)
def test_bad_scenarios_name_the_key(path: str, value: object, message: str) -> None:
    with pytest.raises(ScenarioError, match=message):
        parse_scenario(with_change(path, value), "office.yaml")


def test_station_mission_needs_a_station() -> None:
    data = yaml.safe_load(DEFAULT_SCENARIO.read_text())
    data["mission"] = "find_charging_station"
    data["objects"] = [o for o in data["objects"] if o["kind"] != "charging_station"]
    with pytest.raises(ScenarioError, match="charging_station"):
        parse_scenario(yaml.safe_dump(data))


def test_unreadable_and_malformed_files(tmp_path: Path) -> None:
    with pytest.raises(ScenarioError, match=r"nope\.yaml"):
        load_scenario(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: [unclosed")
    with pytest.raises(ScenarioError, match="not valid YAML"):
        load_scenario(bad)
    bad.write_text("- a list\n")
    with pytest.raises(ScenarioError, match="expected a mapping"):
        load_scenario(bad)


ANY_COLOUR = Path(__file__).parents[1] / "scenarios" / "any_colour.yaml"


def test_markers_plain_paint_and_the_robots_marker() -> None:
    s = load_scenario(ANY_COLOUR)
    box_, trolley = s.obstacles
    assert box_.color is None and box_.bgr == (40, 60, 150) and box_.paint == (40, 60, 150)
    assert trolley.bgr == (200, 200, 200)
    assert [(m.id, m.dictionary, m.size, m.center, m.heading_deg) for m in s.aruco_markers] == [
        (7, "4x4_50", 0.25, (6.0, 3.2), 30.0),
        (3, "4x4_50", 0.25, (2.5, 3.1), 0.0),
        (9, "4x4_50", 0.25, (7.2, 0.8), -90.0),
    ]
    dock = s.charging_stations[0].aruco
    assert dock is not None and dock.filter_def == "aruco_4x4_50_7"
    robot = s.robot.marker
    assert robot is not None and (robot.id, robot.size, robot.filter_def) == (1, 0.25, "aruco_4x4_50_1")
    # A marker's shape is its black square: corner 0 -> corner 1 points along its heading.
    corners = s.aruco_markers[0].corners()
    edge = corners[1] - corners[0]
    assert math.isclose(math.degrees(math.atan2(edge[1], edge[0])), 30.0)
    assert math.isclose(float(np.hypot(*edge)), 0.25) and np.allclose(corners.mean(axis=0), (6.0, 3.2))
    assert math.isclose(s.objects[3].shape.area, 0.25**2)
    # The printed square adds a quiet zone two cells wide: 4x4 bits + border = 6 cells, 10 printed.
    assert math.isclose(robot.printed_size, 0.25 * 10 / 6)


def any_colour_with(path: str, value: object) -> str:
    return with_change(path, value, ANY_COLOUR)


@pytest.mark.parametrize(
    ("path", "value", "message"),
    [
        ("objects[0].bgr", [40, 60], r"objects\[0\]\.bgr: expected \[b, g, r\]"),
        ("objects[0].bgr", [40, 60, 300], r"objects\[0\]\.bgr\[2\]: 300 must be between 0 and 255"),
        ("objects[0].color", "yellow", r"objects\[0\]\.bgr: give either color .* or bgr .*, not both"),
        ("objects[0].bgr", KeyError, r"objects\[0\]\.color: missing"),
        ("objects[4].bgr", [1, 2, 3], r"objects\[4\]\.bgr: an ArUco marker is given by aruco"),
        ("objects[3].aruco", 50, r"objects\[3\]\.aruco: 50 is not a marker id of 4x4_50 \(0 to 49\)"),
        ("objects[3].aruco", "seven", r"objects\[3\]\.aruco: seven is not a marker id"),
        ("objects[3].dictionary", "4x4_51", r"objects\[3\]\.dictionary: '4x4_51' is not an OpenCV ArUco dictionary"),
        ("objects[3].dictionary", "DICT_4X4_50", r"objects\[3\]\.dictionary: 'DICT_4X4_50' is not an OpenCV"),
        ("objects[3].size", KeyError, r"objects\[3\]\.size: missing"),
        ("objects[3].size", 0, r"objects\[3\]\.size: 0 must be between 0\.02 and 5"),
        ("objects[3].center", KeyError, r"objects\[3\]\.center: missing"),
        ("objects[3].heading", "north", r"objects\[3\]\.heading: north is not a finite number"),
        ("objects[3].radius", 0.1, r"objects\[3\]\.radius: an ArUco marker is given by aruco"),
        ("objects[0].size", 0.1, r"objects\[0\]\.size: only for a marker given by aruco"),
        ("objects[0].aruco", 4, r"objects\[0\]\.aruco: only for a marker or a charging station"),
        ("objects[0].dictionary", "4x4_50", r"objects\[0\]\.dictionary: only with aruco"),
        ("objects[4].aruco", 7, r"objects\[2\]\.aruco: 2 markers carry aruco 7; a dock's id must be unique"),
        ("objects[2].aruco", 8, r"objects\[2\]\.aruco: no marker with aruco 8 \(4x4_50\) marks this dock"),
        ("objects[2].aruco", 9, r"objects\[2\]\.aruco: its marker objects\[5\] does not lie inside the charging"),
        ("robot.marker.aruco", 9, r"robot\.marker\.aruco: 9 is also the id of objects\[5\]"),
        ("robot.marker.size", 0.3, r"robot\.marker\.size: 0\.3 m does not fit on the robot's top plate"),
        ("robot.marker.heading", 10, r"robot\.marker\.heading: unknown key"),
        ("robot.marker.aruco", KeyError, r"robot\.marker\.aruco: missing"),
    ],
)
def test_bad_markers_and_paint_name_the_key(path: str, value: object, message: str) -> None:
    with pytest.raises(ScenarioError, match=message):
        parse_scenario(any_colour_with(path, value), "any_colour.yaml")


def test_a_scout_drives_its_path_heading_the_way_it_goes() -> None:
    path = [(0.0, 0.0), (2.0, 0.0), (2.0, 2.0)]
    assert along_path(path, 1.0, loop=False) == (1.0, 0.0, 0.0)
    assert along_path(path, 3.0, loop=False) == (2.0, 1.0, math.pi / 2)
    assert along_path(path, 9.0, loop=False) == (2.0, 2.0, math.pi / 2)  # stops at the end
    # Back and forth: 5 m along a 4 m path is 1 m back from its end, heading back (south).
    x, y, heading = along_path(path, 5.0, loop=True)
    assert (x, y) == (2.0, 1.0) and heading == pytest.approx(-math.pi / 2)
    assert along_path(path, 8.0 + 1.0, loop=True)[:2] == (1.0, 0.0)  # one round trip later
    (scout,) = load_scenario().scouts
    assert scout.camera_id == "scout-1-cam" and scout.mount.z == 1.0 and scout.mount.pitch_deg == 35
    start = scout.pose_at(-5.0)  # before the clock starts: where it starts, facing its first leg
    assert (start.x, start.y) == (11.6, 9.5) and start.yaw == pytest.approx(-math.pi / 2)
    later = scout.pose_at(2.0)
    assert later.x == 11.6 and later.y == pytest.approx(9.5 - 2.0 * scout.speed_mps)

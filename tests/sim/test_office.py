"""drvs-office end to end: world, server, cameras and robot as processes, both missions, both modes."""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path
from typing import Any

import cv2
import pytest
import pytest_asyncio
from shapely.geometry import LineString, Point, Polygon, box

from drvs.sim.scenario import DEFAULT_SCENARIO, Scenario, load_scenario
from drvs.tools.launch import ManagedProcess
from tests.helpers import once_per_run

SMALL_ROOM = Path(__file__).parents[1] / "scenarios" / "small_room.yaml"
TWO_CAMERAS = Path(__file__).parents[1] / "scenarios" / "two_cameras.yaml"
#: How near a detection's centroid must be to the true object's (a few pixels on the overhead camera).
YELLOW_TOLERANCE_M = 0.03
#: Where a path must end: at the goal, within the goal's cell of the robot's 10 cm map (it stops
#: once its planned path is that single cell): half the cell's diagonal.
GOAL_TOLERANCE_M = 0.071


async def run_office(out: Path, *args: str) -> tuple[int, dict[str, Any], str]:
    proc = await ManagedProcess.entry_point("office", "drvs-office", "--out", str(out), "--quiet", *args).start()
    code = await proc.wait(timeout=150)
    result_file = out / "result.json"
    result = json.loads(result_file.read_text()) if result_file.exists() else {}
    return code, result, proc.output()


def solids(s: Scenario) -> list[Polygon]:
    outside = box(*s.bounds).buffer(10, join_style="mitre").difference(box(*s.bounds))
    return [*s.walls, *(o.shape for o in s.obstacles), outside]


def clearance(path: list[list[float]], shapes: list[Polygon]) -> float:
    line = LineString(path)
    return float(min(line.distance(shape) for shape in shapes))


def check_map(out: Path) -> None:
    image = cv2.imread(str(out / "map.png"))
    assert image is not None and image.shape[0] > 400 and image.shape[1] > 800


#: The seeded small-room run that two tests read: the navigation's checks, and the first of the
#: two runs that must agree (made once per test run: tests/helpers.py's once_per_run).
SEEDED = ("--scenario", str(SMALL_ROOM), "--seed", "7")


async def seeded_run(out: Path) -> dict[str, Any]:
    code, result, log = await run_office(out, *SEEDED)
    return {"out": str(out), "code": code, "result": result, "log": log}


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def seeded_small_room(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, int, dict[str, Any], str]:
    """drvs-office on the small room with --seed 7, to its end: (its --out, exit code, result, log)."""
    run = await once_per_run(tmp_path_factory, "seeded-small-room", seeded_run)
    return Path(run["out"]), run["code"], run["result"], run["log"]


@pytest.mark.slow
def test_navigate_with_drvs_avoids_the_unknown_obstacle(
    seeded_small_room: tuple[Path, int, dict[str, Any], str],
) -> None:
    out, code, result, log = seeded_small_room
    assert code == 0, log
    scenario = load_scenario(SMALL_ROOM)
    assert result["mission"] == "navigate" and result["drvs"] is True and result["detector"] == "hsv"
    assert result["reached_goal"] is True and result["collisions"] == 0
    assert clearance(result["path"], solids(scenario)) >= scenario.robot.radius - 1e-6
    assert result["path"][0] == list(scenario.robot.start)
    goal = scenario.robot.goal
    assert goal is not None and math.dist(result["path"][-1], goal) < GOAL_TOLERANCE_M, (result["path"][-1], goal)
    # Every yellow patch is marked (the paper's pessimistic union): the obstacle and both yellow
    # markers. Both ways, so neither a miss nor a stray hides behind a good match: every detection
    # the robot used lies within 3 cm of a true yellow object, and every true yellow object has one.
    yellow_truth = [o.shape.centroid for o in scenario.objects if o.color and o.color.name == "yellow"]
    assert len(yellow_truth) == 3 and scenario.obstacles[0].shape.centroid in yellow_truth
    seen: list[Point] = []
    for d in result["detections"]:
        assert d["filter_def"] == scenario.colors["yellow"].filter_def and d["camera_id"] == "overhead"
        seen.append(Polygon(d["outline"]).centroid)
    for s in seen:
        assert min(s.distance(t) for t in yellow_truth) < YELLOW_TOLERANCE_M, (s, yellow_truth)
    for t in yellow_truth:
        assert min((t.distance(s) for s in seen), default=math.inf) < YELLOW_TOLERANCE_M, (t, seen)
    assert result["replans"] >= 1  # the straight line was planned first, then the obstacle seen
    assert result["localisation"]["fixes"] > 0 and result["localisation"]["mean_error_m"] < 0.10
    assert result["bytes_to_robot"] > 0 and result["robot_cpu_s"] > 0
    # On an Ethernet link the same payload comes with a header per segment.
    assert result["wire_bytes_to_robot"] > result["bytes_to_robot"]
    check_map(out)


@pytest.mark.slow
async def test_navigate_without_drvs_collides_and_replans(tmp_path: Path) -> None:
    code, result, log = await run_office(tmp_path, "--scenario", str(SMALL_ROOM), "--no-drvs")
    assert code == 0, log
    assert result["drvs"] is False and result["detections"] == [] and result["bytes_to_robot"] == 0
    assert result["wire_bytes_to_robot"] == 0
    assert result["collisions"] >= 1 and result["replans"] >= 1 and result["reached_goal"] is True
    check_map(tmp_path)


@pytest.mark.slow
async def test_charging_station_is_the_true_one_over_mutual_tls(tmp_path: Path) -> None:
    code, result, log = await run_office(
        tmp_path, "--scenario", str(SMALL_ROOM), "--mission", "find_charging_station", "--tls"
    )
    assert code == 0, log
    assert (tmp_path / "certs" / "ca.pem").exists() and result["bytes_to_robot"] > 0
    scenario = load_scenario(SMALL_ROOM)
    station = scenario.charging_stations[0].shape.centroid
    assert result["charging_station"] is not None and result["reached_goal"] is True
    assert station.distance(Point(result["charging_station"])) < YELLOW_TOLERANCE_M
    assert math.dist(result["path"][-1], result["charging_station"]) < GOAL_TOLERANCE_M  # docked where it found it
    assert len(result["candidates"]) == 1  # neither the lone green nor the far-apart pair
    assert result["collisions"] == 0
    check_map(tmp_path)


@pytest.mark.slow
async def test_default_office_station_mission(tmp_path: Path) -> None:
    code, result, log = await run_office(tmp_path, "--mission", "find_charging_station")
    assert code == 0, log
    station = load_scenario(DEFAULT_SCENARIO).charging_stations[0].shape.centroid
    assert station.distance(Point(result["charging_station"])) < YELLOW_TOLERANCE_M
    assert result["reached_goal"] is True
    assert math.dist(result["path"][-1], result["charging_station"]) < GOAL_TOLERANCE_M


async def test_bad_scenario_is_refused_naming_the_key(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text(SMALL_ROOM.read_text().replace("yaw_deg: 90", "yaw_degrees: 90"))
    code, result, log = await run_office(tmp_path / "out", "--scenario", str(bad))
    assert code == 2 and result == {} and "Traceback" not in log, log
    message = f"drvs-office: {bad}: cameras[0].yaw_degrees: unknown key"
    assert any(line.startswith(message) for line in log.splitlines()), log


@pytest.mark.slow
async def test_same_seed_same_run(seeded_small_room: tuple[Path, int, dict[str, Any], str], tmp_path: Path) -> None:
    """A second run with the same seed, made here, against the seeded run the navigation's test reads."""
    _, code, a, log = seeded_small_room
    assert code == 0, log
    code, b, log = await run_office(tmp_path, *SEEDED)
    assert code == 0, log
    assert a["path"] == b["path"] and a["planned_paths"] == b["planned_paths"]
    assert a["detections"] == b["detections"] and a["replans"] == b["replans"]


@pytest.mark.slow
async def test_robot_slows_where_a_killed_camera_looked(tmp_path: Path) -> None:
    """cam-east crashes one second into the mission. The robot learns it at once (its report stream
    breaks), and where only cam-east looked it creeps instead of driving through at full speed: no
    detections there mean nobody looked, not that the way is clear."""
    code, result, log = await run_office(tmp_path, "--scenario", str(TWO_CAMERAS), "--kill-camera", "cam-east@1")
    assert code == 0, log
    scenario = load_scenario(TWO_CAMERAS)
    assert result["reached_goal"] is True and result["collisions"] == 0
    assert scenario.robot.goal is not None and math.dist(result["path"][-1], scenario.robot.goal) < GOAL_TOLERANCE_M
    lost = [e for e in result["coverage_events"] if e["event"] == "lost"]
    assert [e["camera_id"] for e in lost] == ["cam-east"], result["coverage_events"]
    assert 1.0 <= lost[0]["t"] <= 4.0, lost  # within three seconds of the crash
    fov = {c.id: c.field_of_view.floor for c in scenario.cameras}
    east_only = fov["cam-east"].difference(fov["cam-west"])
    path = result["path"]
    full_step = scenario.robot.speed_mps * 0.1
    steps = [(Point(a), math.dist(a, b)) for a, b in itertools.pairwise(path)]
    before = [d for i, (p, d) in enumerate(steps) if i < lost[0]["step"] and not east_only.contains(p)]
    after = [d for i, (p, d) in enumerate(steps) if i >= lost[0]["step"] and east_only.contains(p)]
    assert before and max(before) > 0.9 * full_step  # full speed where cam-west looks
    assert len(after) > 20 and max(after) <= 0.25 * full_step + 1e-6, max(after)
    assert result["blind_steps"] >= len(after)


ANY_COLOUR = Path(__file__).parents[1] / "scenarios" / "any_colour.yaml"


@pytest.mark.slow
async def test_foreground_avoids_obstacles_of_any_colour_and_localises_by_marker(tmp_path: Path) -> None:
    """--detector foreground: a brown box on the straight line and a grey trolley, colours no
    filter matches, are found as anything-not-empty-floor and driven around without a touch; the
    robot is not among what it avoids (it would otherwise block its own start), and its ArUco
    marker fixes its position and heading."""
    code, result, log = await run_office(tmp_path, "--scenario", str(ANY_COLOUR), "--detector", "foreground")
    assert code == 0, log
    scenario = load_scenario(ANY_COLOUR)
    assert result["detector"] == "foreground" and result["reached_goal"] is True
    assert scenario.robot.goal is not None and math.dist(result["path"][-1], scenario.robot.goal) < GOAL_TOLERANCE_M
    assert result["collisions"] == 0 and result["contacts"] == []
    assert clearance(result["path"], solids(scenario)) >= scenario.robot.radius - 1e-6
    assert (tmp_path / "cameras" / "ceiling.empty.png").exists()
    # Each obstacle is outlined within 10 cm; nothing else was taken for an obstacle: not the
    # robot, not the markers on the floor (they are in the picture of the empty floor).
    assert {d["filter_def"] for d in result["detections"]} == {"foreground"}
    obstacles = [o.shape for o in scenario.obstacles]
    for d in result["detections"]:
        seen = Polygon(d["outline"])
        nearest = max(obstacles, key=lambda o: o.intersection(seen).area)
        assert seen.hausdorff_distance(nearest) < 0.10, d
        assert seen.intersection(nearest).area > 0.8 * nearest.area
    assert len(result["detections"]) == len(obstacles) and result["replans"] >= 1
    loc = result["localisation"]
    assert loc["filter_def"] == "aruco_4x4_50_1" and loc["fixes"] >= 5
    assert loc["max_error_m"] < 0.02 and loc["max_heading_error_deg"] < 3.0, loc
    check_map(tmp_path)


@pytest.mark.slow
async def test_charging_station_marked_by_an_aruco_id(tmp_path: Path) -> None:
    """The dock is the marker with id 7; markers 3 and 9 lie elsewhere. The robot finds only id 7,
    docks there, and with foreground goes round the box of no known colour on its way."""
    code, result, log = await run_office(
        tmp_path, "--scenario", str(ANY_COLOUR), "--mission", "find_charging_station", "--detector", "foreground"
    )
    assert code == 0, log
    scenario = load_scenario(ANY_COLOUR)
    station = scenario.charging_stations[0].shape.centroid
    assert result["reached_goal"] is True and len(result["candidates"]) == 1
    assert station.distance(box(*result["charging_station"], *result["charging_station"])) < 0.01
    assert result["collisions"] == 0
    docks = [d for d in result["detections"] if d["filter_def"] == "aruco_4x4_50_7"]
    assert [d["marker_id"] for d in docks] == [7] and abs(docks[0]["heading_deg"] - 30.0) < 2.0

"""drvs-office with a moving obstacle, end to end (world, server, camera, robot as processes): the
robot plans from fused tracks and predicts the trolley from its velocity, so it neither hits it
nor re-plans for it; the same robot told to ignore velocity (--no-predict) drives into it."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest
from shapely.geometry import LineString, Point, Polygon

from drvs.sim.scenario import load_scenario
from tests.live.office_view import OfficeRun
from tests.sim.test_office import GOAL_TOLERANCE_M, check_map, run_office

CROSSING = Path(__file__).parents[1] / "scenarios" / "crossing.yaml"


def moving_tracks(result: dict[str, Any]) -> list[dict[str, Any]]:
    return [t for t in result["tracks"] if str(t["used_as"]).startswith("moving")]


@pytest.mark.slow
async def test_the_robot_lets_a_crossing_trolley_pass_and_goes_behind_it(tmp_path: Path) -> None:
    code, result, log = await run_office(tmp_path, "--scenario", str(CROSSING))
    assert code == 0, log
    scenario = load_scenario(CROSSING)
    assert result["delivery"] == "fused" and result["predict"] is True
    assert result["reached_goal"] is True and result["collisions"] == 0, result.get("contacts")
    assert scenario.robot.goal is not None and math.dist(result["path"][-1], scenario.robot.goal) < GOAL_TOLERANCE_M
    # It followed the trolley as one moving track, at about its true speed, northwards.
    trolley = moving_tracks(result)
    assert trolley, result["tracks"]
    fastest = max(trolley, key=lambda t: float(t["max_speed_mps"]))
    assert 0.2 <= float(fastest["max_speed_mps"]) <= 0.6, fastest
    vx, vy = fastest["mean_velocity"]
    assert vy > 0.1 and abs(vx) < 0.1, fastest
    # It waited for it instead of driving on or round it: every plan, and the path it drove, is
    # the straight line y = 2 (its map changed only where the trolley stood, before it set off
    # and where it was left, both off that line).
    assert result["wait_steps"] > 0
    assert all(abs(y - 2.0) < 0.05 for plan in result["planned_paths"] for _, y in plan), result["planned_paths"]
    assert max(abs(y - 2.0) for _, y in result["path"]) < 0.05
    check_map(tmp_path)


@pytest.mark.slow
async def test_a_robot_that_ignores_velocity_drives_into_the_trolley(tmp_path: Path) -> None:
    """The same run with --no-predict: the trolley is taken to stand where it was last seen, so the
    robot enters its way while it is still beside it, and it runs into the robot there."""
    _code, result, log = await run_office(tmp_path, "--scenario", str(CROSSING), "--no-predict")
    assert result["predict"] is False and moving_tracks(result), log
    assert result["collisions"] >= 1, result


@pytest.mark.slow
@pytest.mark.timeout(300)  # the run is the office's whole mission: over a minute on a loaded machine
def test_the_default_office_with_its_trolley(default_office: OfficeRun) -> None:
    """`./run office` as it ships: the trolley crosses the hallway about when the robot gets there;
    the robot reaches the goal without touching anything, having followed the trolley as a
    moving track and then seen it left standing by the south wall. (The run, watched live, is
    shared with the live view's test: see tests/live/office_view.py.)"""
    code, result, log = default_office.code, default_office.result, default_office.log
    assert code == 0, log
    assert result["reached_goal"] is True and result["collisions"] == 0, result.get("contacts")
    trolley = [t for t in moving_tracks(result) if float(t["max_speed_mps"]) > 0.2]
    assert trolley, result["tracks"]  # (a re-plan's new request follows it as a new track)
    assert any(t["used_as"] == "moving, then standing" and math.dist(t["last"], (16.8, 5.85)) < 0.05 for t in trolley)
    # The obstacle in the main room's north-east corner, which no fixed camera sees: the robot
    # learned of it from the scout's camera alone (a mobile camera picked up by its track requests,
    # or asked at once), placed it within 3 cm, and drove around it.
    hidden = next(o.shape for o in load_scenario().obstacles if o.shape.centroid.distance(Point(11.0, 6.65)) < 0.01)
    used = [d for d in result["detections"] if Polygon(d["outline"]).centroid.distance(hidden.centroid) < 0.03]
    assert used and all(d["camera_ids"] == ["scout-1-cam"] for d in used), result["detections"]
    assert LineString(result["path"]).distance(hidden) >= load_scenario().robot.radius - 1e-6

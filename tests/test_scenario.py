"""Scenario files: the built-in office loads; bad files are refused with the key named."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from drvs.sim.scenario import DEFAULT_SCENARIO, ScenarioError, load_scenario, parse_scenario

OFFICE = yaml.safe_load(DEFAULT_SCENARIO.read_text())


def test_default_office_matches_the_paper() -> None:
    s = load_scenario()
    assert s.mission == "navigate" and len(s.cameras) == 3
    fovs = [c.field_of_view.floor for c in s.cameras]
    for i, a in enumerate(fovs):
        for b in fovs[i + 1 :]:
            assert a.intersection(b).area == 0, "the paper's cameras have non-overlapping views"
    # Every object lies inside exactly one camera's view, so DRVS can see all of them.
    for obj in s.objects:
        assert sum(f.contains(obj.shape) for f in fovs) == 1, obj
    assert len(s.obstacles) == 2 and len(s.charging_stations) == 1


def with_change(path: str, value: object) -> str:
    data = yaml.safe_load(DEFAULT_SCENARIO.read_text())
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

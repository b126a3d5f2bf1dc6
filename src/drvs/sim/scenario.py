"""Scenario files: a simulated world described in YAML, validated once at load.

Unknown keys and impossible values are errors that name the key (``cameras[1].pitch_deg: ...``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
from shapely.geometry import Point, Polygon, box

from drvs.errors import InvalidArgument
from drvs.filters import HsvRange
from drvs.geometry import DEFAULT_MAX_RANGE_M, FieldOfView, Homography, homography_from_pose, polygon_region
from drvs.model import check_id

DEFAULT_SCENARIO = Path(__file__).parent / "scenarios" / "office.yaml"
MISSIONS = ("navigate", "find_charging_station")
OBJECT_KINDS = ("obstacle", "marker", "charging_station")


class ScenarioError(InvalidArgument):
    """A scenario file is malformed; the message names the key."""


@dataclass(frozen=True)
class ColorDef:
    name: str
    filter_def: str
    bgr: tuple[int, int, int]


@dataclass(frozen=True)
class CameraDef:
    id: str
    position: tuple[float, float, float]
    yaw_deg: float
    pitch_deg: float
    hfov_deg: float
    resolution: tuple[int, int]
    fps: float
    max_range_m: float = DEFAULT_MAX_RANGE_M

    @property
    def homography(self) -> Homography:
        """Image -> floor, from the pose: what calibrating this camera would give."""
        return homography_from_pose(self.position, self.yaw_deg, self.pitch_deg, self.hfov_deg, self.resolution)

    @property
    def field_of_view(self) -> FieldOfView:
        return FieldOfView.compute(self.homography, self.resolution, self.max_range_m)


@dataclass(frozen=True)
class ObjectDef:
    """A flat patch on the floor that is not on the floor plan: only cameras can see it."""

    kind: str
    shape: Polygon
    color: ColorDef | None  # None for a charging station: it is found by its markers


@dataclass(frozen=True)
class RobotDef:
    start: tuple[float, float]
    goal: tuple[float, float] | None
    radius: float
    color: ColorDef
    speed_mps: float = 1.0


@dataclass(frozen=True)
class RenderDef:
    noise_sigma: float = 3.0
    lighting: float = 0.08  # relative brightness swing over time and across the image
    floor_texture: float = 10.0  # grey levels of carpet-like texture on the floor (colourless)


@dataclass(frozen=True)
class Scenario:
    name: str
    bounds: tuple[float, float, float, float]
    walls: tuple[Polygon, ...]
    colors: Mapping[str, ColorDef]
    cameras: tuple[CameraDef, ...]
    objects: tuple[ObjectDef, ...]
    robot: RobotDef
    mission: str
    render: RenderDef = field(default_factory=RenderDef)
    source_text: str = ""

    @property
    def floor(self) -> Polygon:
        return box(*self.bounds)

    @property
    def obstacles(self) -> list[ObjectDef]:
        return [o for o in self.objects if o.kind == "obstacle"]

    @property
    def charging_stations(self) -> list[ObjectDef]:
        return [o for o in self.objects if o.kind == "charging_station"]

    def camera(self, camera_id: str) -> CameraDef:
        for cam in self.cameras:
            if cam.id == camera_id:
                return cam
        raise ScenarioError(f"cameras: no camera with id {camera_id!r}")


# --- loading ----------------------------------------------------------------------------------


def load_scenario(path: str | Path | None = None) -> Scenario:
    """Load and validate a scenario file (the built-in office when path is None)."""
    p = Path(path) if path is not None else DEFAULT_SCENARIO
    try:
        text = p.read_text()
    except OSError as exc:
        raise ScenarioError(f"scenario {p}: {exc.strerror or exc}") from None
    return parse_scenario(text, str(p))


def parse_scenario(text: str, origin: str = "scenario") -> Scenario:
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ScenarioError(f"{origin}: not valid YAML ({exc})") from None
    try:
        return _build(_Obj(data, ""), text)
    except InvalidArgument as exc:
        raise ScenarioError(f"{origin}: {exc}") from None


class _Obj:
    """A mapping being read, that remembers its key path and rejects keys nobody asked for."""

    def __init__(self, value: Any, path: str) -> None:
        if not isinstance(value, dict):
            raise ScenarioError(f"{path or 'scenario'}: expected a mapping, got {type(value).__name__}")
        self.value = value
        self.path = path

    def key(self, name: str) -> str:
        return f"{self.path}.{name}" if self.path else name

    def take(self, name: str, default: Any = ...) -> Any:
        if name in self.value:
            return self.value[name]
        if default is ...:
            raise ScenarioError(f"{self.key(name)}: missing")
        return default

    def check_keys(self, allowed: Sequence[str]) -> None:
        unknown = sorted(set(map(str, self.value)) - set(allowed))
        if unknown:
            raise ScenarioError(f"{self.key(unknown[0])}: unknown key (expected one of: {', '.join(allowed)})")


def _number(value: Any, path: str, lo: float = -math.inf, hi: float = math.inf) -> float:
    try:
        finite = not isinstance(value, bool) and isinstance(value, (int, float)) and math.isfinite(float(value))
    except OverflowError:
        finite = False
    if not finite:
        raise ScenarioError(f"{path}: {str(value)[:40]} is not a finite number")
    if not lo <= float(value) <= hi:
        raise ScenarioError(f"{path}: {value!r} must be between {lo:g} and {hi:g}")
    return float(value)


def _numbers(value: Any, path: str, count: int) -> list[float]:
    if not isinstance(value, list) or len(value) != count:
        raise ScenarioError(f"{path}: expected a list of {count} numbers")
    return [_number(v, f"{path}[{i}]") for i, v in enumerate(value)]


def _point(value: Any, path: str) -> tuple[float, float]:
    x, y = _numbers(value, path, 2)
    return x, y


def _polygon(value: Any, path: str) -> Polygon:
    if not isinstance(value, list):
        raise ScenarioError(f"{path}: expected a list of [x, y] points")
    return polygon_region([_point(p, f"{path}[{i}]") for i, p in enumerate(value)], path)


def _build(root: _Obj, text: str) -> Scenario:
    root.check_keys(["name", "floor_plan", "colors", "cameras", "objects", "robot", "mission", "render"])
    name = root.take("name")
    if not isinstance(name, str) or not name.strip():
        raise ScenarioError("name: expected a non-empty string")

    plan = _Obj(root.take("floor_plan"), "floor_plan")
    plan.check_keys(["bounds", "walls"])
    x0, y0, x1, y1 = _numbers(plan.take("bounds"), "floor_plan.bounds", 4)
    if not (x0 < x1 and y0 < y1):
        raise ScenarioError("floor_plan.bounds: expected [x_min, y_min, x_max, y_max] with min < max")
    bounds = (x0, y0, x1, y1)
    walls_raw = plan.take("walls", [])
    if not isinstance(walls_raw, list):
        raise ScenarioError("floor_plan.walls: expected a list of polygons")
    walls = tuple(_polygon(w, f"floor_plan.walls[{i}]") for i, w in enumerate(walls_raw))

    colors_raw = root.take("colors")
    if not isinstance(colors_raw, dict) or not colors_raw:
        raise ScenarioError("colors: expected a mapping of colour name to {filter_def, bgr}")
    colors = {str(k): _color(str(k), v) for k, v in colors_raw.items()}

    cams_raw = root.take("cameras")
    if not isinstance(cams_raw, list) or not cams_raw:
        raise ScenarioError("cameras: expected a non-empty list")
    cameras = tuple(_camera(_Obj(c, f"cameras[{i}]"), box(*bounds)) for i, c in enumerate(cams_raw))
    ids = [c.id for c in cameras]
    for i, cid in enumerate(ids):
        if cid in ids[:i]:
            raise ScenarioError(f"cameras[{i}].id: {cid!r} is used twice")

    objs_raw = root.take("objects", [])
    if not isinstance(objs_raw, list):
        raise ScenarioError("objects: expected a list")
    objects = tuple(_object(_Obj(o, f"objects[{i}]"), colors) for i, o in enumerate(objs_raw))

    mission = root.take("mission")
    if mission not in MISSIONS:
        raise ScenarioError(f"mission: {mission!r} is not one of {', '.join(MISSIONS)}")

    robot = _robot(_Obj(root.take("robot"), "robot"), colors, bounds, walls, mission)
    if mission == "find_charging_station" and not any(o.kind == "charging_station" for o in objects):
        raise ScenarioError("objects: mission find_charging_station needs an object of kind charging_station")

    render_raw = root.take("render", {})
    rend = _Obj(render_raw, "render")
    rend.check_keys(["noise_sigma", "lighting", "floor_texture"])
    render = RenderDef(
        noise_sigma=_number(rend.take("noise_sigma", 3.0), "render.noise_sigma", 0, 50),
        lighting=_number(rend.take("lighting", 0.08), "render.lighting", 0, 0.5),
        floor_texture=_number(rend.take("floor_texture", 10.0), "render.floor_texture", 0, 40),
    )
    return Scenario(
        name=name.strip(),
        bounds=bounds,
        walls=walls,
        colors=colors,
        cameras=cameras,
        objects=objects,
        robot=robot,
        mission=mission,
        render=render,
        source_text=text,
    )


def _color(name: str, value: Any) -> ColorDef:
    path = f"colors.{name}"
    obj = _Obj(value, path)
    obj.check_keys(["filter_def", "bgr"])
    filter_def = obj.take("filter_def")
    if not isinstance(filter_def, str):
        raise ScenarioError(f"{path}.filter_def: expected a string like hsv_014110130035225200")
    try:
        hsv_range = HsvRange.parse(filter_def)
    except InvalidArgument as exc:
        raise ScenarioError(f"{path}.{exc}") from None
    bgr_raw = obj.take("bgr")
    if not isinstance(bgr_raw, list) or len(bgr_raw) != 3:
        raise ScenarioError(f"{path}.bgr: expected [b, g, r], three integers 0-255")
    bgr = tuple(int(_number(v, f"{path}.bgr[{i}]", 0, 255)) for i, v in enumerate(bgr_raw))
    # A colour its own filter cannot see would make every camera blind to it.
    pixel = np.array([[bgr]], dtype=np.uint8)
    if not hsv_range.mask(np.asarray(cv2.cvtColor(pixel, cv2.COLOR_BGR2HSV), dtype=np.uint8))[0, 0]:
        h, s, v = (int(c) for c in cv2.cvtColor(pixel, cv2.COLOR_BGR2HSV)[0, 0])
        raise ScenarioError(
            f"{path}.bgr: {list(bgr)} is HSV ({h}, {s}, {v}), outside its own filter_def {filter_def}; "
            f"e.g. {list(hsv_range.centre_bgr())} is inside"
        )
    return ColorDef(name, filter_def, bgr)  # type: ignore[arg-type]


def _camera(obj: _Obj, floor: Polygon) -> CameraDef:
    obj.check_keys(["id", "position", "yaw_deg", "pitch_deg", "hfov_deg", "resolution", "fps", "max_range_m"])
    p = obj.path
    cid = obj.take("id")
    if not isinstance(cid, str):
        raise ScenarioError(f"{p}.id: expected a string")
    try:
        check_id(cid, f"{p}.id")
    except InvalidArgument as exc:
        raise ScenarioError(str(exc)) from None
    x, y, z = _numbers(obj.take("position"), f"{p}.position", 3)
    if z <= 0:
        raise ScenarioError(f"{p}.position: mounting height z = {z:g} must be above the floor")
    res = obj.take("resolution", [640, 480])
    w, h = (
        int(_number(v, f"{p}.resolution[{i}]", 16, 8192)) for i, v in enumerate(_numbers(res, f"{p}.resolution", 2))
    )
    cam = CameraDef(
        id=cid,
        position=(x, y, z),
        yaw_deg=_number(obj.take("yaw_deg"), f"{p}.yaw_deg", -360, 360),
        pitch_deg=_number(obj.take("pitch_deg"), f"{p}.pitch_deg", -90, 90),
        hfov_deg=_number(obj.take("hfov_deg", 60), f"{p}.hfov_deg", 1, 170),
        resolution=(w, h),
        fps=_number(obj.take("fps", 20), f"{p}.fps", 0.1, 240),
        max_range_m=_number(obj.take("max_range_m", DEFAULT_MAX_RANGE_M), f"{p}.max_range_m", 0.1, 1000),
    )
    try:
        fov = cam.field_of_view
    except InvalidArgument as exc:
        raise ScenarioError(f"{p}: sees no floor ({exc})") from None
    if fov.floor.intersection(floor).area <= 1e-6:
        raise ScenarioError(f"{p}: its field of view does not meet floor_plan.bounds; the camera sees no floor")
    return cam


def _object(obj: _Obj, colors: Mapping[str, ColorDef]) -> ObjectDef:
    p = obj.path
    obj.check_keys(["kind", "color", "polygon", "center", "radius"])
    kind = obj.take("kind")
    if kind not in OBJECT_KINDS:
        raise ScenarioError(f"{p}.kind: {kind!r} is not one of {', '.join(OBJECT_KINDS)}")
    has_polygon, has_center = "polygon" in obj.value, "center" in obj.value
    if has_polygon == has_center:
        raise ScenarioError(f"{p}: give either polygon or center (with radius)")
    if has_polygon:
        if "radius" in obj.value:
            raise ScenarioError(f"{p}.radius: only with center")
        shape = _polygon(obj.take("polygon"), f"{p}.polygon")
    else:
        cx, cy = _point(obj.take("center"), f"{p}.center")
        radius = _number(obj.take("radius", 0.3 if kind == "charging_station" else ...), f"{p}.radius", 0.01, 100)
        shape = Point(cx, cy).buffer(radius, quad_segs=16)
    color: ColorDef | None = None
    if kind == "charging_station":
        if "color" in obj.value:
            raise ScenarioError(f"{p}.color: a charging station is found by its markers and has no colour")
    else:
        cname = obj.take("color")
        if cname not in colors:
            raise ScenarioError(f"{p}.color: {cname!r} has no definition in colors")
        color = colors[cname]
    return ObjectDef(kind, shape, color)


def _robot(
    obj: _Obj,
    colors: Mapping[str, ColorDef],
    bounds: tuple[float, float, float, float],
    walls: Sequence[Polygon],
    mission: str,
) -> RobotDef:
    obj.check_keys(["start", "goal", "radius", "color", "speed_mps"])
    radius = _number(obj.take("radius", 0.2), "robot.radius", 0.05, 2.0)
    floor = box(*bounds)
    start = _point(obj.take("start"), "robot.start")
    goal_raw = obj.take("goal", None)
    if goal_raw is None and mission == "navigate":
        raise ScenarioError("robot.goal: missing; mission navigate needs a goal")
    goal = _point(goal_raw, "robot.goal") if goal_raw is not None else None
    for key, pt in (("start", start), ("goal", goal)):
        if pt is None:
            continue
        disc = Point(pt).buffer(radius)
        if not floor.contains(disc):
            raise ScenarioError(f"robot.{key}: {list(pt)} with radius {radius:g} is not inside floor_plan.bounds")
        for i, wall in enumerate(walls):
            if wall.intersects(disc):
                raise ScenarioError(f"robot.{key}: {list(pt)} is inside a wall (floor_plan.walls[{i}])")
    cname = obj.take("color")
    if cname not in colors:
        raise ScenarioError(f"robot.color: {cname!r} has no definition in colors")
    return RobotDef(
        start=start,
        goal=goal,
        radius=radius,
        color=colors[cname],
        speed_mps=_number(obj.take("speed_mps", 1.0), "robot.speed_mps", 0.05, 10),
    )

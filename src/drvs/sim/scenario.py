"""Scenario files: a simulated world described in YAML, validated once at load.

Unknown keys and impossible values are errors that name the key (``cameras[1].pitch_deg: ...``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
from shapely import affinity
from shapely.geometry import Point, Polygon, box

from drvs.core.errors import InvalidArgument
from drvs.core.filters import HsvRange
from drvs.core.geometry import DEFAULT_MAX_RANGE_M, FieldOfView, polygon_region
from drvs.core.model import check_id
from drvs.detectors.aruco import DICTIONARIES, DICTIONARY_SIZES

# The scenario's types live in drvs.sim.scenario_model; they stay importable from here.
from drvs.sim.scenario_model import DEFAULT_SCENARIO as DEFAULT_SCENARIO
from drvs.sim.scenario_model import MISSIONS as MISSIONS
from drvs.sim.scenario_model import OBJECT_KINDS as OBJECT_KINDS
from drvs.sim.scenario_model import QUIET_ZONE_CELLS as QUIET_ZONE_CELLS
from drvs.sim.scenario_model import ArucoDef as ArucoDef
from drvs.sim.scenario_model import CameraDef as CameraDef
from drvs.sim.scenario_model import ColorDef as ColorDef
from drvs.sim.scenario_model import ObjectDef as ObjectDef
from drvs.sim.scenario_model import RenderDef as RenderDef
from drvs.sim.scenario_model import RobotDef as RobotDef
from drvs.sim.scenario_model import Scenario as Scenario
from drvs.sim.scenario_model import ScenarioError as ScenarioError
from drvs.sim.scenario_model import ScoutDef as ScoutDef
from drvs.sim.scenario_model import along_path as along_path

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
    root.check_keys(["name", "floor_plan", "colors", "cameras", "objects", "robot", "mission", "render", "scouts"])
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
    objects = tuple(_object(_Obj(o, f"objects[{i}]"), colors, box(*bounds)) for i, o in enumerate(objs_raw))

    scouts_raw = root.take("scouts", [])
    if not isinstance(scouts_raw, list):
        raise ScenarioError("scouts: expected a list")
    scouts = tuple(_scout(_Obj(c, f"scouts[{i}]"), bounds, walls) for i, c in enumerate(scouts_raw))
    taken = set(ids)
    for i, scout in enumerate(scouts):
        for what, value in (("id", scout.id), ("camera.id", scout.camera_id)):
            if value in taken:
                raise ScenarioError(f"scouts[{i}].{what}: {value!r} is already a camera's or a scout's id")
            taken.add(value)

    mission = root.take("mission")
    if mission not in MISSIONS:
        raise ScenarioError(f"mission: {mission!r} is not one of {', '.join(MISSIONS)}")

    robot = _robot(_Obj(root.take("robot"), "robot"), colors, bounds, walls, mission)
    if mission == "find_charging_station" and not any(o.kind == "charging_station" for o in objects):
        raise ScenarioError("objects: mission find_charging_station needs an object of kind charging_station")
    _check_docks(objects, robot)

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
        scouts=scouts,
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


def _id(obj: _Obj, default: Any = ...) -> str:
    """`obj.id`: a string that is an id (letters, digits, - _ . :), or ScenarioError naming it."""
    value = obj.take("id", default)
    if not isinstance(value, str):
        raise ScenarioError(f"{obj.path}.id: expected a string")
    try:
        return check_id(value, f"{obj.path}.id")
    except InvalidArgument as exc:
        raise ScenarioError(str(exc)) from None


def _camera(obj: _Obj, floor: Polygon) -> CameraDef:
    obj.check_keys(["id", "position", "yaw_deg", "pitch_deg", "hfov_deg", "resolution", "fps", "max_range_m"])
    p = obj.path
    cid = _id(obj)
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


def _object(obj: _Obj, colors: Mapping[str, ColorDef], floor: Polygon) -> ObjectDef:
    p = obj.path
    obj.check_keys(
        ["kind", "color", "bgr", "polygon", "center", "radius", "aruco", "dictionary", "size", "heading", "path",
         "speed_mps", "loop"]
    )  # fmt: skip
    kind = obj.take("kind")
    if kind not in OBJECT_KINDS:
        raise ScenarioError(f"{p}.kind: {kind!r} is not one of {', '.join(OBJECT_KINDS)}")
    for key in ("path", "speed_mps", "loop"):
        if key in obj.value and kind != "obstacle":
            raise ScenarioError(f"{p}.{key}: only an obstacle moves")
        if key != "path" and key in obj.value and "path" not in obj.value:
            raise ScenarioError(f"{p}.{key}: only with path")
    static = _static_object(obj, colors)
    if "path" not in obj.value:
        return static
    return _moving(obj, static, floor)


def _moving(obj: _Obj, static: ObjectDef, floor: Polygon) -> ObjectDef:
    """An obstacle with a path: its centre starts where its polygon or center puts it, then passes
    through the path's points in order at speed_mps."""
    p = obj.path
    raw = obj.take("path")
    if not isinstance(raw, list) or not raw:
        raise ScenarioError(f"{p}.path: expected a non-empty list of [x, y] points its centre passes through")
    start = (static.shape.centroid.x, static.shape.centroid.y)
    points = (start, *(_point(v, f"{p}.path[{i}]") for i, v in enumerate(raw)))
    if all(math.dist(start, q) < 1e-6 for q in points):
        raise ScenarioError(
            f"{p}.path: every point is where the obstacle starts ({start[0]:g}, {start[1]:g}); it would not move"
        )
    for i, (x, y) in enumerate(points[1:]):
        placed = affinity.translate(static.shape, x - start[0], y - start[1])
        if not floor.contains(placed):
            raise ScenarioError(f"{p}.path[{i}]: at [{x:g}, {y:g}] the obstacle is not inside floor_plan.bounds")
    speed = _number(obj.take("speed_mps"), f"{p}.speed_mps", 0.01, 10)
    loop = obj.take("loop", False)
    if not isinstance(loop, bool):
        raise ScenarioError(f"{p}.loop: expected true (back and forth along the path) or false (stop at its end)")
    return dataclasses.replace(static, path=points, speed_mps=speed, loop=loop)


def _static_object(obj: _Obj, colors: Mapping[str, ColorDef]) -> ObjectDef:
    p = obj.path
    kind = obj.take("kind")
    for key in ("size", "heading"):
        if key in obj.value and not (kind == "marker" and "aruco" in obj.value):
            raise ScenarioError(f"{p}.{key}: only for a marker given by aruco")
    if "dictionary" in obj.value and "aruco" not in obj.value:
        raise ScenarioError(f"{p}.dictionary: only with aruco")
    if kind == "marker" and "aruco" in obj.value:
        for key in ("color", "bgr", "polygon", "radius"):
            if key in obj.value:
                raise ScenarioError(f"{p}.{key}: an ArUco marker is given by aruco, dictionary, center, size, heading")
        marker = _aruco(obj, centered=True)
        return ObjectDef(kind, Polygon(marker.corners()), None, aruco=marker)
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
    bgr: tuple[int, int, int] | None = None
    dock: ArucoDef | None = None
    if kind == "charging_station":
        for key in ("color", "bgr"):
            if key in obj.value:
                raise ScenarioError(f"{p}.{key}: a charging station is found by its markers and has no colour")
        if "aruco" in obj.value:
            dock = _aruco(obj, centered=False)
    else:
        if "aruco" in obj.value:
            raise ScenarioError(f"{p}.aruco: only for a marker or a charging station")
        if kind == "obstacle" and "bgr" in obj.value:
            if "color" in obj.value:
                raise ScenarioError(f"{p}.bgr: give either color (a filter finds it) or bgr (plain paint), not both")
            bgr = _bgr(obj.take("bgr"), f"{p}.bgr")
        else:
            if "bgr" in obj.value:
                raise ScenarioError(f"{p}.bgr: only an obstacle may be plain paint; a marker is found by its color")
            cname = obj.take("color")
            if cname not in colors:
                raise ScenarioError(f"{p}.color: {cname!r} has no definition in colors")
            color = colors[cname]
    return ObjectDef(kind, shape, color, bgr=bgr, aruco=dock)


def _check_docks(objects: Sequence[ObjectDef], robot: RobotDef) -> None:
    """A dock marked by an ArUco id needs that marker on the floor inside it, and no other marker
    (nor the robot) may carry the id, or the robot could drive to the wrong one; nor may a marker
    on the floor carry the robot's id, or the robot would take it for itself."""
    if robot.marker is not None:
        mine = (robot.marker.id, robot.marker.dictionary)
        for j, o in enumerate(objects):
            if o.kind == "marker" and o.aruco is not None and (o.aruco.id, o.aruco.dictionary) == mine:
                raise ScenarioError(f"robot.marker.aruco: {robot.marker.id} is also the id of objects[{j}]")
    for i, obj in enumerate(objects):
        dock = obj.aruco
        if obj.kind != "charging_station" or dock is None:
            continue
        key = (dock.id, dock.dictionary)
        same = [
            (j, o)
            for j, o in enumerate(objects)
            if o.kind == "marker" and o.aruco is not None and (o.aruco.id, o.aruco.dictionary) == key
        ]
        if not same:
            raise ScenarioError(
                f"objects[{i}].aruco: no marker with aruco {dock.id} ({dock.dictionary}) marks this dock"
            )
        if len(same) > 1:
            raise ScenarioError(
                f"objects[{i}].aruco: {len(same)} markers carry aruco {dock.id}; a dock's id must be unique"
            )
        j, marker = same[0]
        if not obj.shape.contains(Point(marker.shape.centroid)):
            raise ScenarioError(f"objects[{i}].aruco: its marker objects[{j}] does not lie inside the charging station")


def _bgr(value: Any, path: str) -> tuple[int, int, int]:
    if not isinstance(value, list) or len(value) != 3:
        raise ScenarioError(f"{path}: expected [b, g, r], three integers 0-255")
    b, g, r = (int(_number(v, f"{path}[{i}]", 0, 255)) for i, v in enumerate(value))
    return b, g, r


def _aruco(obj: _Obj, *, centered: bool) -> ArucoDef:
    """An ArUco marker's id and dictionary, and with `centered` its place on the floor and size."""
    p = obj.path
    dictionary = obj.take("dictionary", "4x4_50")
    if not isinstance(dictionary, str) or dictionary not in DICTIONARIES:
        raise ScenarioError(
            f"{p}.dictionary: {str(dictionary)[:40]!r} is not an OpenCV ArUco dictionary "
            f"(one of {', '.join(DICTIONARIES)})"
        )
    size = DICTIONARY_SIZES[dictionary]
    marker_id = obj.take("aruco")
    if isinstance(marker_id, bool) or not isinstance(marker_id, int) or not 0 <= marker_id < size:
        raise ScenarioError(f"{p}.aruco: {str(marker_id)[:40]} is not a marker id of {dictionary} (0 to {size - 1})")
    if not centered:
        return ArucoDef(marker_id, dictionary, 0.0)
    center = _point(obj.take("center"), f"{p}.center")
    side = _number(obj.take("size"), f"{p}.size", 0.02, 5)
    heading = _number(obj.take("heading", 0.0), f"{p}.heading", -360, 360)
    return ArucoDef(marker_id, dictionary, side, center, heading)


def _robot(
    obj: _Obj,
    colors: Mapping[str, ColorDef],
    bounds: tuple[float, float, float, float],
    walls: Sequence[Polygon],
    mission: str,
) -> RobotDef:
    obj.check_keys(["start", "goal", "radius", "color", "speed_mps", "marker"])
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
    marker: ArucoDef | None = None
    if "marker" in obj.value:
        m = _Obj(obj.take("marker"), "robot.marker")
        m.check_keys(["aruco", "dictionary", "size"])
        m.value = {**m.value, "center": [0.0, 0.0]}
        marker = _aruco(m, centered=True)
        if marker.printed_size * math.sqrt(0.5) > radius:
            raise ScenarioError(
                f"robot.marker.size: {marker.size:g} m does not fit on the robot's top plate: printed with its "
                f"quiet zone it is {marker.printed_size:.3f} m square, wider corner to corner than the robot's "
                f"{2 * radius:g} m"
            )
    return RobotDef(
        start=start,
        goal=goal,
        radius=radius,
        color=colors[cname],
        speed_mps=_number(obj.take("speed_mps", 1.0), "robot.speed_mps", 0.05, 10),
        marker=marker,
    )


def _scout(obj: _Obj, bounds: tuple[float, float, float, float], walls: Sequence[Polygon]) -> ScoutDef:
    obj.check_keys(["id", "camera", "path", "speed_mps", "loop", "radius", "bgr"])
    p = obj.path
    sid = _id(obj)
    radius = _number(obj.take("radius", 0.2), f"{p}.radius", 0.05, 2.0)
    raw = obj.take("path")
    if not isinstance(raw, list) or not raw:
        raise ScenarioError(f"{p}.path: expected a non-empty list of [x, y] points it drives through")
    path = tuple(_point(v, f"{p}.path[{i}]") for i, v in enumerate(raw))
    floor = box(*bounds)
    for i, pt in enumerate(path):
        if not floor.contains(Point(pt).buffer(radius)):
            raise ScenarioError(f"{p}.path[{i}]: {list(pt)} with radius {radius:g} is not inside floor_plan.bounds")
        for j, wall in enumerate(walls):
            if wall.contains(Point(pt)):
                raise ScenarioError(f"{p}.path[{i}]: {list(pt)} is inside a wall (floor_plan.walls[{j}])")
    loop = obj.take("loop", False)
    if not isinstance(loop, bool):
        raise ScenarioError(f"{p}.loop: expected true (back and forth along the path) or false (stop at its end)")
    cam = _Obj(obj.take("camera"), f"{p}.camera")
    cam.check_keys(["id", "height", "pitch_deg", "yaw_deg", "hfov_deg", "resolution", "fps", "max_range_m"])
    c = cam.path
    camera_id = _id(cam, f"{sid}-cam")
    res = _numbers(cam.take("resolution", [640, 480]), f"{c}.resolution", 2)
    w, h = (int(_number(v, f"{c}.resolution[{i}]", 16, 8192)) for i, v in enumerate(res))
    scout = ScoutDef(
        id=sid,
        camera_id=camera_id,
        height=_number(cam.take("height"), f"{c}.height", 0.05, 10),
        pitch_deg=_number(cam.take("pitch_deg"), f"{c}.pitch_deg", -90, 90),
        yaw_deg=_number(cam.take("yaw_deg", 0.0), f"{c}.yaw_deg", -360, 360),
        hfov_deg=_number(cam.take("hfov_deg", 60), f"{c}.hfov_deg", 1, 170),
        resolution=(w, h),
        fps=_number(cam.take("fps", 10), f"{c}.fps", 0.1, 240),
        max_range_m=_number(cam.take("max_range_m", DEFAULT_MAX_RANGE_M), f"{c}.max_range_m", 0.1, 1000),
        path=path,
        speed_mps=_number(obj.take("speed_mps", 0.5), f"{p}.speed_mps", 0.01, 10),
        loop=loop,
        radius=radius,
        bgr=_bgr(obj.take("bgr", [70, 62, 58]), f"{p}.bgr"),
    )
    try:
        FieldOfView.compute(scout.mount.base_homography(scout.resolution), scout.resolution, scout.max_range_m)
    except InvalidArgument as exc:
        raise ScenarioError(f"{c}: sees no floor ({exc})") from None
    return scout

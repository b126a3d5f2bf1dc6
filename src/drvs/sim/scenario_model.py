"""A simulated world as data: the scenario's cameras, objects, robot, scouts and rendering, as
drvs.sim.scenario loads them from YAML (validated once, at load)."""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray
from shapely import affinity
from shapely.geometry import Point, Polygon, box

from drvs.core.errors import InvalidArgument
from drvs.core.geometry import DEFAULT_MAX_RANGE_M, FieldOfView, Homography, homography_from_pose
from drvs.core.mobile import Mount, map_homography
from drvs.core.model import Pose2
from drvs.detectors.aruco import DICTIONARIES

DEFAULT_SCENARIO = Path(__file__).parent / "scenarios" / "office.yaml"
MISSIONS = ("navigate", "find_charging_station")
OBJECT_KINDS = ("obstacle", "marker", "charging_station")
#: White margin around a printed ArUco marker, in marker cells. Two, not OpenCV's minimum of one:
#: the aruco detector's sub-pixel corner window reaches up to 0.8 cell past the black square,
#: and further along the diagonal of a turned marker; past the paper the robot's blue plate pulled
#: its corners by up to 2.6 cm (measured with one cell).
QUIET_ZONE_CELLS = 2


class ScenarioError(InvalidArgument):
    """A scenario file is malformed; the message names the key."""


@dataclass(frozen=True)
class ColorDef:
    name: str
    filter_def: str
    bgr: tuple[int, int, int]


def along_path(path: Sequence[tuple[float, float]], s: float, loop: bool) -> tuple[float, float, float]:
    """Where one is after travelling `s` metres along `path` from its first point, and its heading
    (radians counter-clockwise from +x, the way it is going): it stops at the last point, or with
    `loop` goes back and forth along the path for ever."""
    legs = [math.dist(a, b) for a, b in itertools.pairwise(path)]
    total = sum(legs)
    back = False
    if loop and total > 0:
        s %= 2 * total
        if s > total:
            s, back = 2 * total - s, True
    else:
        s = min(s, total)
    heading = 0.0
    for (a, b), leg in zip(itertools.pairwise(path), legs, strict=True):
        if leg <= 0:
            continue
        heading = math.atan2(b[1] - a[1], b[0] - a[0]) + (math.pi if back else 0.0)
        if s <= leg:
            f = s / leg
            return a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), math.remainder(heading, 2 * math.pi)
        s -= leg
    return path[-1][0], path[-1][1], math.remainder(heading, 2 * math.pi)


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
class ArucoDef:
    """A printed ArUco marker lying flat: `size` is the side of its black square (what OpenCV calls
    the marker's side), printed with a white quiet zone QUIET_ZONE_CELLS cells wide around it. Corner 0 (the
    top-left of OpenCV's marker image) to corner 1 is the marker's x axis, `heading_deg`
    counter-clockwise from the world x axis; on the robot, `center` and `heading_deg` are relative
    to the robot (its x axis points where the robot drives)."""

    id: int
    dictionary: str  # as in filter_defs: "4x4_50", "apriltag_36h11" (drvs.detectors.aruco.DICTIONARIES)
    size: float
    center: tuple[float, float] = (0.0, 0.0)
    heading_deg: float = 0.0

    @property
    def filter_def(self) -> str:
        """The filter_def that finds this one marker."""
        return f"aruco_{self.dictionary}_{self.id}"

    @property
    def cv_dictionary(self) -> cv2.aruco.Dictionary:
        return cv2.aruco.getPredefinedDictionary(DICTIONARIES[self.dictionary])

    @property
    def cells(self) -> int:
        """Cells across the black square: the marker's bits plus its black border."""
        return int(self.cv_dictionary.markerSize) + 2

    @property
    def printed_size(self) -> float:
        """Side of the printed square, quiet zone included."""
        return self.size * (self.cells + 2 * QUIET_ZONE_CELLS) / self.cells

    def corners(
        self, at: tuple[float, float] = (0.0, 0.0), turn_deg: float = 0.0, side: float | None = None
    ) -> NDArray[np.float64]:
        """Floor corners of a square of `side` (default the black square) in OpenCV's corner order
        (top-left, top-right, bottom-right, bottom-left of the marker image), the marker placed at
        `at` turned by `turn_deg` (the robot's pose; the origin and 0 for a marker on the floor)."""
        half = (self.size if side is None else side) / 2
        local = np.array([[-half, half], [half, half], [half, -half], [-half, -half]])  # image v is down
        turn = math.radians(turn_deg)
        c, s = math.cos(turn), math.sin(turn)
        centre = np.array(at) + np.array(
            [c * self.center[0] - s * self.center[1], s * self.center[0] + c * self.center[1]]
        )
        h = math.radians(self.heading_deg + turn_deg)
        rot = np.array([[math.cos(h), -math.sin(h)], [math.sin(h), math.cos(h)]])
        return np.asarray(local @ rot.T + centre, dtype=np.float64)


@dataclass(frozen=True)
class ObjectDef:
    """A flat patch on the floor that is not on the floor plan: only cameras can see it."""

    kind: str
    shape: Polygon
    color: ColorDef | None  # None for a charging station (found by its markers) and plain paint
    #: Paint no filter of the scenario is meant to match (obstacles given by `bgr`).
    bgr: tuple[int, int, int] | None = None
    #: A printed ArUco marker (kind marker), or the marker that marks a charging station's dock.
    aruco: ArucoDef | None = None
    #: A moving obstacle: the points its centre passes through, its start (`shape`'s centroid)
    #: first; empty for one that stands still. It moves at `speed_mps` from world time 0 and stops
    #: at the last point, or with `loop` goes back and forth along the path for ever.
    path: tuple[tuple[float, float], ...] = ()
    speed_mps: float = 0.0
    loop: bool = False

    @property
    def paint(self) -> tuple[int, int, int] | None:
        """The BGR it is painted in; None when it is not a plain patch (markers, stations)."""
        return self.color.bgr if self.color is not None else self.bgr

    @property
    def moving(self) -> bool:
        return len(self.path) > 1

    def offset_at(self, t: float) -> tuple[float, float]:
        """How far it has moved from its start at world time `t` (seconds since the clock started)."""
        if not self.moving:
            return 0.0, 0.0
        x, y, _ = along_path(self.path, self.speed_mps * max(t, 0.0), self.loop)
        return x - self.path[0][0], y - self.path[0][1]

    def shape_at(self, t: float) -> Polygon:
        """Its outline at world time `t`: `shape` itself for one that stands still."""
        if not self.moving:
            return self.shape
        dx, dy = self.offset_at(t)
        moved: Polygon = affinity.translate(self.shape, dx, dy)
        return moved


@dataclass(frozen=True)
class ScoutDef:
    """A robot that drives a path and carries a camera: a mobile camera node in the simulation.

    It drives `path` at `speed_mps` from world time 0 (stopping at the last point, or with `loop`
    going back and forth), heading the way it goes. Its camera sits on its centre at `height`,
    turned `yaw_deg` from its heading and pitched `pitch_deg` below horizontal. Its body (a disc of
    `radius`, painted `bgr`) is drawn in the other cameras' frames; its own camera does not see it.
    Scouts do not touch anything: the world's bumper ignores them.
    """

    id: str
    camera_id: str
    height: float
    pitch_deg: float
    hfov_deg: float
    resolution: tuple[int, int]
    fps: float
    path: tuple[tuple[float, float], ...]
    speed_mps: float
    loop: bool
    yaw_deg: float = 0.0
    max_range_m: float = DEFAULT_MAX_RANGE_M
    radius: float = 0.2
    bgr: tuple[int, int, int] = (70, 62, 58)

    @property
    def mount(self) -> Mount:
        """Where its camera sits on it: what `drvs-camera --mount` and `--hfov` are given."""
        return Mount(0.0, 0.0, self.height, self.yaw_deg, self.pitch_deg, hfov_deg=self.hfov_deg)

    def pose_at(self, t: float) -> Pose2:
        """Its pose at world time `t` (seconds since the clock started; before: its start)."""
        x, y, heading = along_path(self.path, self.speed_mps * max(t, 0.0), self.loop)
        return Pose2(x, y, heading)

    def homography_at(self, t: float) -> Homography:
        """Its camera's image -> floor mapping at world time `t`."""
        return map_homography(self.mount.base_homography(self.resolution), self.pose_at(t))

    def body_at(self, t: float) -> Polygon:
        p = self.pose_at(t)
        body: Polygon = Point(p.x, p.y).buffer(self.radius, quad_segs=16)
        return body


@dataclass(frozen=True)
class RobotDef:
    start: tuple[float, float]
    goal: tuple[float, float] | None
    radius: float
    color: ColorDef
    speed_mps: float = 1.0
    #: An ArUco marker on the robot's top plate, centred, its x axis along the robot's heading.
    marker: ArucoDef | None = None


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
    scouts: tuple[ScoutDef, ...] = ()

    @property
    def floor(self) -> Polygon:
        return box(*self.bounds)

    @property
    def obstacles(self) -> list[ObjectDef]:
        return [o for o in self.objects if o.kind == "obstacle"]

    @property
    def moving_obstacles(self) -> list[ObjectDef]:
        return [o for o in self.objects if o.moving]

    @property
    def charging_stations(self) -> list[ObjectDef]:
        return [o for o in self.objects if o.kind == "charging_station"]

    @property
    def aruco_markers(self) -> list[ArucoDef]:
        """The ArUco markers lying on the floor."""
        return [o.aruco for o in self.objects if o.kind == "marker" and o.aruco is not None]

    def camera(self, camera_id: str) -> CameraDef:
        for cam in self.cameras:
            if cam.id == camera_id:
                return cam
        raise ScenarioError(f"cameras: no camera with id {camera_id!r}")

    def scout(self, scout_id: str) -> ScoutDef:
        for scout in self.scouts:
            if scout.id == scout_id:
                return scout
        raise ScenarioError(f"scouts: no scout with id {scout_id!r}")

    def scout_camera(self, camera_id: str) -> ScoutDef | None:
        """The scout that carries camera `camera_id`, or None (a fixed camera, or none)."""
        return next((s for s in self.scouts if s.camera_id == camera_id), None)

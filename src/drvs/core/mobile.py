"""Mobile cameras: a camera mounted on a robot, its floor mapping as the robot moves. Pure logic.

A ground robot moves in the floor plane, so its camera's image -> floor mapping is the fixed
image -> base-frame homography of the mount (the robot's base frame: x forward, y left, metres,
origin on the floor under the robot's centre), followed by the rigid motion of the robot's pose:

    H_map(pose) = T(pose) @ H_base

Detections found in the base frame move to the map with T(pose), and so does the field of view:
the image polygon below the horizon does not change as the robot drives, only where it lands.
A robot's pose arrives over time (`PoseBuffer`); a frame uses the pose at its capture time,
interpolated between the poses around it, or none when no pose is close enough in time.
"""

from __future__ import annotations

import bisect
import math
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from shapely import affinity
from shapely.geometry import Polygon

from drvs.core.errors import InvalidArgument
from drvs.core.geometry import MAX_COORDINATE_M, Homography, homography_from_pose
from drvs.core.model import Detection, Pose2

#: Poses a PoseBuffer keeps (at 100 Hz, 5 s).
POSE_HISTORY = 500
#: Default for how far from a frame's capture time the poses around it may be, seconds.
DEFAULT_MAX_POSE_GAP_S = 0.25
#: A mobile camera's robot moves at most this fast (m/s) unless its registration declares otherwise
#: (up to MAX_SPEED_MPS), and one pose may jump this far beyond what that speed allows (metres: a
#: localiser's correction); an UpdatePose that implies more is refused.
DEFAULT_MAX_SPEED_MPS = 3.0
MAX_SPEED_MPS = 50.0
POSE_JUMP_M = 1.0
#: A pose feed that drops is reopened after this long, doubling up to the most, seconds.
INITIAL_BACKOFF_S = 0.1
MAX_BACKOFF_S = 5.0

#: Where a pose source hands each pose: push(time the pose held, seconds since the Unix epoch; pose).
Push = Callable[[float, Pose2], None]


@dataclass(frozen=True)
class Mount:
    """Where a camera sits on its robot, in the robot's base frame: position (x forward, y left,
    z up, metres), yaw (degrees counter-clockwise from the robot's forward axis) and pitch (degrees
    below horizontal), and its intrinsics: `hfov_deg` (square pixels, principal point at the image
    centre) or `camera_matrix` (fx, fy, cx, cy in pixels)."""

    x: float
    y: float
    z: float
    yaw_deg: float
    pitch_deg: float
    hfov_deg: float = 0.0
    camera_matrix: tuple[float, float, float, float] | None = None

    def __post_init__(self) -> None:
        for name in ("x", "y", "z", "yaw_deg", "pitch_deg", "hfov_deg"):
            if not math.isfinite(getattr(self, name)):
                raise InvalidArgument(f"mount.{name}: {getattr(self, name)} is not a finite number")
        if self.z <= 0:
            raise InvalidArgument(f"mount.z: the camera's height {self.z:g} m must be above the floor (> 0)")
        if self.camera_matrix is None and not 0 < self.hfov_deg < 180:
            raise InvalidArgument(f"mount.hfov_deg: {self.hfov_deg:g} must be in (0, 180) (or give a camera matrix)")

    @classmethod
    def parse(cls, text: str, hfov_deg: float = 0.0, camera_matrix: str | None = None) -> Mount:
        """From the CLI's `X,Y,Z,YAW,PITCH` (metres, degrees) and `FX,FY,CX,CY` (pixels)."""
        values = _floats(text, 5, "mount", "X,Y,Z,YAW,PITCH")
        matrix = None
        if camera_matrix is not None:
            fx, fy, cx, cy = _floats(camera_matrix, 4, "camera_matrix", "FX,FY,CX,CY")
            matrix = (fx, fy, cx, cy)
        x, y, z, yaw, pitch = values
        return cls(x, y, z, yaw, pitch, hfov_deg=hfov_deg, camera_matrix=matrix)

    def base_homography(self, resolution: tuple[int, int]) -> Homography:
        """Image -> floor in the robot's base frame."""
        return homography_from_pose(
            (self.x, self.y, self.z), self.yaw_deg, self.pitch_deg, self.hfov_deg, resolution, self.camera_matrix
        )


def _floats(text: str, count: int, name: str, form: str) -> list[float]:
    parts = text.split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != count or not all(math.isfinite(v) for v in values):
        raise InvalidArgument(f"{name}: {text!r} is not {form} ({count} finite numbers separated by commas)")
    return values


def pose_matrix(pose: Pose2) -> NDArray[np.float64]:
    """The 3x3 rigid motion base frame -> map frame of a robot at `pose`."""
    c, s = math.cos(pose.yaw), math.sin(pose.yaw)
    return np.array([[c, -s, pose.x], [s, c, pose.y], [0.0, 0.0, 1.0]])


def map_homography(base: Homography, pose: Pose2) -> Homography:
    """Image -> map floor for a camera whose image -> base-frame homography is `base`."""
    return Homography.from_values(pose_matrix(pose) @ base.matrix)


def check_pose_on_floor(pose: Pose2, name: str = "pose") -> Pose2:
    """InvalidArgument naming `name` when the pose is not finite or lies beyond ±MAX_COORDINATE_M."""
    pose.check(name)
    if max(abs(pose.x), abs(pose.y)) > MAX_COORDINATE_M:
        raise InvalidArgument(f"{name}: ({pose.x:g}, {pose.y:g}) is beyond ±{MAX_COORDINATE_M:g} m")
    return pose


def check_speed(camera_id: str, previous: Pose2 | None, pose: Pose2, elapsed_s: float, max_speed_mps: float) -> None:
    """INVALID_ARGUMENT when going from `previous` to `pose` in `elapsed_s` seconds needs more than
    `max_speed_mps` (plus POSE_JUMP_M, for a relocalisation's correction): a robot does not jump."""
    if previous is None:
        return
    distance = math.hypot(pose.x - previous.x, pose.y - previous.y)
    elapsed_s = max(elapsed_s, 0.0)
    if distance > max_speed_mps * elapsed_s + POSE_JUMP_M:
        speed = distance / elapsed_s if elapsed_s > 0 else math.inf
        raise InvalidArgument(
            f"pose: camera {camera_id!r} would have moved {distance:.1f} m in {elapsed_s:.2f} s ({speed:.1f} m/s); "
            f"its robot moves at most {max_speed_mps:g} m/s (and jumps at most {POSE_JUMP_M:g} m)"
        )


def move_polygon(poly: Polygon, pose: Pose2) -> Polygon:
    """A base-frame polygon where the robot at `pose` puts it in the map frame."""
    c, s = math.cos(pose.yaw), math.sin(pose.yaw)
    moved: Polygon = affinity.affine_transform(poly, [c, -s, s, c, pose.x, pose.y])
    return moved


def move_point(xy: Sequence[float], pose: Pose2) -> tuple[float, float]:
    c, s = math.cos(pose.yaw), math.sin(pose.yaw)
    return (pose.x + c * xy[0] - s * xy[1], pose.y + s * xy[0] + c * xy[1])


def move_detection(d: Detection, pose: Pose2) -> Detection:
    """A detection mapped in the base frame, moved to the map frame by the robot's pose."""
    outline = move_polygon(d.outline, pose) if not d.outline.is_empty else d.outline
    if not outline.is_empty:
        x0, y0, x1, y1 = outline.bounds
        bounds = (float(x0), float(y0), float(x1), float(y1))
    else:
        corners = [move_point(p, pose) for p in ((d.bounds[0], d.bounds[1]), (d.bounds[2], d.bounds[3]),
                                                  (d.bounds[0], d.bounds[3]), (d.bounds[2], d.bounds[1]))]  # fmt: skip
        xs, ys = zip(*corners, strict=True)
        bounds = (min(xs), min(ys), max(xs), max(ys))
    heading = d.heading_deg
    if heading is not None:
        heading = (heading + math.degrees(pose.yaw) + 180.0) % 360.0 - 180.0
        if heading == -180.0:
            heading = 180.0
    return replace(
        d,
        outline=outline,
        bounds=bounds,
        centroid_xy=move_point(d.centroid_xy, pose),
        ground_contact_xy=move_point(d.ground_contact_xy, pose),
        heading_deg=heading,
    )


def interpolate(a: tuple[float, Pose2], b: tuple[float, Pose2], t: float) -> Pose2:
    """The pose at time t between two timed poses (linear in position, along the shorter turn)."""
    (ta, pa), (tb, pb) = a, b
    if tb <= ta:
        return pb
    f = (t - ta) / (tb - ta)
    turn = math.remainder(pb.yaw - pa.yaw, 2 * math.pi)
    return Pose2(pa.x + f * (pb.x - pa.x), pa.y + f * (pb.y - pa.y), math.remainder(pa.yaw + f * turn, 2 * math.pi))


class PoseBuffer:
    """Timed poses of one robot (seconds since the Unix epoch), newest last; thread-safe (a robot's
    own code may push from its thread while the camera node reads on its event loop).

    `at(t)` is the pose at time t: interpolated between the poses on either side when both are
    within `max_gap_s` of t, the nearest one when only it is (a frame captured just after the
    newest pose, or before the oldest), else None: no pose close enough, the frame is not used.
    """

    def __init__(self, max_gap_s: float = DEFAULT_MAX_POSE_GAP_S, history: int = POSE_HISTORY) -> None:
        if not (math.isfinite(max_gap_s) and max_gap_s > 0):
            raise InvalidArgument(f"max_pose_gap_s: {max_gap_s} must be > 0 seconds")
        self.max_gap_s = max_gap_s
        self._history = history
        self._times: list[float] = []
        self._poses: list[Pose2] = []
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._times)

    def push(self, t: float, pose: Pose2) -> None:
        """Add a pose that held at time t; one older than the newest is put in its place; a pose at
        a time already held replaces it. InvalidArgument for a pose or time that is not finite."""
        check_pose_on_floor(pose)
        if not math.isfinite(t):
            raise InvalidArgument(f"pose time: {t} is not a finite number")
        with self._lock:
            i = bisect.bisect_left(self._times, t)
            if i < len(self._times) and self._times[i] == t:
                self._poses[i] = pose
            else:
                self._times.insert(i, t)
                self._poses.insert(i, pose)
            if len(self._times) > self._history:
                del self._times[0], self._poses[0]

    def latest(self) -> tuple[float, Pose2] | None:
        """The newest pose and its time, or None before the first."""
        with self._lock:
            return (self._times[-1], self._poses[-1]) if self._times else None

    def at(self, t: float) -> Pose2 | None:
        with self._lock:
            return self._at(t)

    def _at(self, t: float) -> Pose2 | None:
        if not self._times:
            return None
        i = bisect.bisect_left(self._times, t)
        if i < len(self._times) and self._times[i] == t:
            return self._poses[i]
        before = (self._times[i - 1], self._poses[i - 1]) if i > 0 else None
        after = (self._times[i], self._poses[i]) if i < len(self._times) else None
        near_before = before is not None and t - before[0] <= self.max_gap_s
        near_after = after is not None and after[0] - t <= self.max_gap_s
        if near_before and near_after:
            assert before is not None and after is not None
            return interpolate(before, after, t)
        if near_before:
            assert before is not None
            return before[1]
        if near_after:
            assert after is not None
            return after[1]
        return None

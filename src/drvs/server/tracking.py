"""Tracking: stable ids, filtered positions and velocities over a continuous request's periods.

Pure logic (no role, no I/O): the server keeps one `Tracker` per continuous fused request and
feeds it each period's `drvs.server.fusion.fuse` output. docs/fusion.md explains the model; in short:

- Motion model: a constant-velocity Kalman filter per track, state (x, y, vx, vy), in OpenCV's
  `cv2.KalmanFilter`. OpenCV is already a dependency of every role, maintained and released
  several times a year; filterpy (the issue's other suggestion) has had no release since 2018 and
  would add a dependency for the same eight lines of linear algebra; norfair brings its own
  matching and Kalman code, which would hide the gating and id policy this module must state.
  Process noise is white acceleration of `accel_mps2` (1 m/s^2: people and pushed trolleys start,
  stop and turn at about that); measurement noise is each object's own uncertainty_m (the fused
  GSD precision) plus `floor_sigma_m` in quadrature, for what the GSD model does not see: the
  cameras' calibration error and the displacement of a raised object's projection, which changes
  when the set of cameras that see it changes (a hand-over).
- Assignment: global nearest neighbour with `scipy.optimize.linear_sum_assignment` on the squared
  Mahalanobis distance of each object from each track's prediction (innovation covariance
  H P H' + R), gated at the chi-square 99.9 % bound for 2 degrees of freedom (13.8). Only objects
  of the track's type are candidates (same marker id, or same label). A marker with an id is
  assigned by id: the gate does not apply to it (the id already says which track it is).
- Merged blobs (OC-SORT's lesson: keep a track on its own motion through an occlusion and
  re-associate it by that motion, not by the occluder's centroid). Two objects passing within a body
  width are one blob to every camera for a while. An object whose outline holds the predicted
  centroids of two or more tracks of its type, and whose area is at least MERGE_AREA_RATIO times the
  larger one's own (what one alone would not fill), holds those tracks: they coast through it on
  their prediction (seen, with its camera_ids, their uncertainty growing), never corrected by its
  centroid, which is neither's; it opens no track. Where the objects part, each track takes the
  object its motion predicts (the gated Mahalanobis assignment above, over the coasted covariance).
  An object touching one already tracked this period (within FRAGMENT_MARGIN_M, same type) is a
  piece of it (a camera's partial view at its view's edge, left out of the fused object by its
  calibration error): it opens no track either. `merges=False` turns both off (one track per object).
- Life cycle: a track is confirmed at once (no hidden tentative state: the robot sees every object
  the cameras saw). A track with no object in a period is reported predicted to that period's
  time, with camera_ids=() and its last_seen unchanged; one unseen for `drop_after_s` (in the
  periods' own clock) is dropped. Ids are never reused within a Tracker.
- Time: `at` going backwards or repeating does not move the filter (no prediction, no division by
  time): the objects are assimilated at the track's current time.
- Bounds: at most `max_tracks` (default `MAX_TRACKS`) tracks live at once, and at most that many
  objects (the most confident) are considered per period. Objects that would open a track beyond
  it are left untracked (the least confident first), never an error: the robot still gets the others.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np
import shapely
from numpy.typing import NDArray
from shapely import affinity

from drvs.core.errors import InvalidArgument
from drvs.core.model import WorldObject

#: Squared Mahalanobis gate: the chi-square 99.9 % quantile for 2 degrees of freedom.
GATE_CHI2 = 13.816
#: Below this speed (m/s) a track has no heading (its velocity is mostly noise).
MIN_HEADING_SPEED_MPS = 0.05
#: Most tracks alive at once in one Tracker.
MAX_TRACKS = 500
#: Default white-acceleration process noise: people walking and trolleys pushed, m/s^2.
DEFAULT_ACCEL_MPS2 = 1.0
#: Default measurement-noise floor added in quadrature to an object's uncertainty_m, metres.
DEFAULT_FLOOR_SIGMA_M = 0.03
#: Initial speed uncertainty of a new track (1 sigma, m/s): a brisk walk.
INITIAL_SPEED_SIGMA_MPS = 1.5

#: A merged blob: its outline (grown by this margin, m) holds two tracks' predicted centroids, and its
#: area is at least this many times the larger one's own.
MERGE_MARGIN_M = 0.1
MERGE_AREA_RATIO = 1.2
#: An object whose outline is this close to an object tracked in the same period is a piece of it.
FRAGMENT_MARGIN_M = 0.05
#: Weight of the newest area in a track's running mean of its own area.
AREA_WEIGHT = 0.2

_UNMATCHED = 1e9
_H = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]], dtype=np.float64)


def _type_key(o: WorldObject) -> tuple[str, int | str]:
    if o.marker_id is not None:
        return ("marker", o.marker_id)
    return ("label", o.label)


@dataclass
class _Track:
    track_id: int
    kf: cv2.KalmanFilter
    key: tuple[str, int | str]
    last: WorldObject
    #: The tracker time (`at`) of the last period that saw it.
    seen_at: float
    #: The centroid the last seen outline belongs to, to move the outline with the prediction.
    seen_xy: tuple[float, float]
    #: Its floor area when it was an object of its own (a running mean; what a merged blob is weighed against).
    area_m2: float = 0.0

    def state(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        x = np.asarray(self.kf.statePost, dtype=np.float64).reshape(4)
        p = np.asarray(self.kf.errorCovPost, dtype=np.float64)
        return x, p


class Tracker:
    """Constant-velocity Kalman filter per track (cv2.KalmanFilter) and global nearest-neighbour
    assignment with scipy.optimize.linear_sum_assignment, gated by the Mahalanobis distance.

    Tracks are confirmed at once (no hidden tentative state), survive misses up to drop_after_s
    (reported with camera_ids=() meanwhile), and keep their id through a camera hand-over. Markers
    with an id are assigned by id. Tracks coast through a blob that holds two or more of them
    (`merges`, default on). The module docstring says why these choices.
    """

    def __init__(
        self,
        drop_after_s: float = 1.0,
        *,
        accel_mps2: float = DEFAULT_ACCEL_MPS2,
        floor_sigma_m: float = DEFAULT_FLOOR_SIGMA_M,
        max_tracks: int = MAX_TRACKS,
        merges: bool = True,
    ) -> None:
        for name, value in (("drop_after_s", drop_after_s), ("accel_mps2", accel_mps2)):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise InvalidArgument(f"{name}: {value!r} must be a positive finite number")
        if not (isinstance(floor_sigma_m, (int, float)) and math.isfinite(floor_sigma_m) and floor_sigma_m >= 0):
            raise InvalidArgument(f"floor_sigma_m: {floor_sigma_m!r} must be a finite number >= 0")
        if not (isinstance(max_tracks, int) and max_tracks > 0):
            raise InvalidArgument(f"max_tracks: {max_tracks!r} must be a positive integer")
        self.drop_after_s = float(drop_after_s)
        self.accel_mps2 = float(accel_mps2)
        self.floor_sigma_m = float(floor_sigma_m)
        if not isinstance(merges, bool):
            raise InvalidArgument(f"merges: {merges!r} must be True or False")
        self.max_tracks = max_tracks
        self.merges = merges
        self._tracks: list[_Track] = []
        self._next_id = 1
        self._time: float | None = None

    def __len__(self) -> int:
        return len(self._tracks)

    def update(self, objects: Sequence[WorldObject], at: float) -> list[WorldObject]:
        """objects: one period's fuse() output (track_id ignored); at: the period's time (s since
        epoch). Returns the tracks alive at `at` with stable track_id, filtered centroid, velocity,
        heading_deg (None below ~0.05 m/s), uncertainty_m from the covariance.

        InvalidArgument (and nothing changes) when `at` is not finite or an object's centroid or
        uncertainty_m is not finite (or negative)."""
        _check(objects, at)
        if len(objects) > self.max_tracks:
            objects = sorted(objects, key=lambda o: -o.score)[: self.max_tracks]
        dt = 0.0 if self._time is None else max(0.0, at - self._time)
        now = at if self._time is None else max(self._time, at)
        self._time = now
        # What has been unseen for drop_after_s is gone before this period's objects are matched:
        # an object that comes back after that is a new track.
        self._tracks = [t for t in self._tracks if now - t.seen_at < self.drop_after_s - 1e-9]
        for t in self._tracks:
            self._predict(t, dt)
        blobs = self._merged_blobs(objects) if self.merges else {}
        seen: set[int] = set(blobs)
        matched: set[int] = set()
        for ti, oi in self._associate(objects, seen):
            self._observed(self._tracks[ti], objects[oi], now)
            seen.add(oi)
            matched.add(self._tracks[ti].track_id)
        for oi, held in blobs.items():
            # A blob holding tracks that found no object of their own: they coast through it on their
            # motion, seen (its cameras see them) but not corrected by its centroid, which is neither's.
            for ti in held:
                t = self._tracks[ti]
                if t.track_id not in matched:
                    t.seen_at = now
                    t.last = replace(t.last, camera_ids=objects[oi].camera_ids, last_seen=objects[oi].last_seen)
                    matched.add(t.track_id)
        fresh = sorted((i for i in range(len(objects)) if i not in seen), key=lambda i: -objects[i].score)
        if self.merges:
            fresh = [oi for oi in fresh if not _fragment(objects[oi], [objects[i] for i in seen])]
        for oi in fresh:
            if len(self._tracks) >= self.max_tracks:
                break
            track = self._start(objects[oi], now)
            self._tracks.append(track)
            matched.add(track.track_id)
        out = [self._report(t, t.track_id in matched) for t in self._tracks]
        out.sort(key=lambda o: o.track_id)
        return out

    def _observed(self, t: _Track, o: WorldObject, now: float) -> None:
        """An object of its own assigned to the track: correct the filter, remember it."""
        self._correct(t, o)
        t.last, t.seen_at, t.seen_xy = o, now, o.centroid_xy
        if o.area_m2 > 0:
            t.area_m2 = o.area_m2 if t.area_m2 <= 0 else (1 - AREA_WEIGHT) * t.area_m2 + AREA_WEIGHT * o.area_m2

    def _merged_blobs(self, objects: Sequence[WorldObject]) -> dict[int, list[int]]:
        """Objects that are two or more tracked objects merged into one blob: {object index: the
        indices of the tracks it holds}. A blob's outline holds the predicted centroids of two or more
        tracks of its type (within MERGE_MARGIN_M), and its area is at least MERGE_AREA_RATIO times
        the largest of theirs: what one of them alone would not fill. Markers with an id are never
        merged (the id says which one it is)."""
        if len(self._tracks) < 2:
            return {}
        xy = np.array([t.state()[0][:2] for t in self._tracks])
        blobs: dict[int, list[int]] = {}
        for oi, o in enumerate(objects):
            key = _type_key(o)
            if key[0] == "marker" or o.outline.is_empty or o.area_m2 <= 0:
                continue
            x0, y0, x1, y1 = o.outline.bounds
            m = MERGE_MARGIN_M
            inside = np.flatnonzero(
                (xy[:, 0] >= x0 - m) & (xy[:, 0] <= x1 + m) & (xy[:, 1] >= y0 - m) & (xy[:, 1] <= y1 + m)
            )
            if len(inside) < 2:  # the bounds first: the outline's test is the costly one
                continue
            near = o.outline.buffer(m)
            held = [int(ti) for ti in inside if self._tracks[ti].key == key and near.contains(shapely.Point(xy[ti]))]
            if len(held) >= 2 and o.area_m2 >= MERGE_AREA_RATIO * max(self._tracks[ti].area_m2 for ti in held):
                blobs[oi] = held
        return blobs

    # -- filter -------------------------------------------------------------------------------

    def _measurement_var(self, o: WorldObject) -> float:
        return float(o.uncertainty_m**2 + self.floor_sigma_m**2) or 1e-6

    def _start(self, o: WorldObject, now: float) -> _Track:
        # Double precision: map coordinates may be large (a site grid in the 1e5 m range), where float32
        # would round positions to centimetres.
        kf = cv2.KalmanFilter(4, 2, 0, cv2.CV_64F)
        kf.measurementMatrix = _H.copy()
        kf.statePost = np.array([[o.centroid_xy[0]], [o.centroid_xy[1]], [0.0], [0.0]], dtype=np.float64)
        r = self._measurement_var(o)
        v = INITIAL_SPEED_SIGMA_MPS**2
        kf.errorCovPost = np.diag([r, r, v, v]).astype(np.float64)
        track = _Track(self._next_id, kf, _type_key(o), o, now, o.centroid_xy, area_m2=o.area_m2)
        self._next_id += 1
        return track

    def _predict(self, t: _Track, dt: float) -> None:
        if dt <= 0:
            return
        f = np.eye(4, dtype=np.float64)
        f[0, 2] = f[1, 3] = dt
        q = self.accel_mps2**2
        # Discrete white-noise acceleration: G q G' with G = (dt^2/2, dt) per axis.
        a, b, c = dt**4 / 4 * q, dt**3 / 2 * q, dt**2 * q
        qm = np.array([[a, 0, b, 0], [0, a, 0, b], [b, 0, c, 0], [0, b, 0, c]], dtype=np.float64)
        t.kf.transitionMatrix = f
        t.kf.processNoiseCov = qm
        t.kf.predict()
        # predict() leaves statePost/errorCovPost as they were; a track that is not corrected this
        # period must carry the prediction forward.
        t.kf.statePost = t.kf.statePre.copy()
        t.kf.errorCovPost = t.kf.errorCovPre.copy()

    def _correct(self, t: _Track, o: WorldObject) -> None:
        r = self._measurement_var(o)
        t.kf.measurementNoiseCov = np.diag([r, r]).astype(np.float64)
        # correct() starts from statePre/errorCovPre: the prediction (or the state when dt was 0).
        t.kf.statePre = t.kf.statePost.copy()
        t.kf.errorCovPre = t.kf.errorCovPost.copy()
        t.kf.correct(np.array([[o.centroid_xy[0]], [o.centroid_xy[1]]], dtype=np.float64))

    def _associate(self, objects: Sequence[WorldObject], skip: Collection[int] = ()) -> list[tuple[int, int]]:
        """(track index, object index) pairs: the assignment minimising the summed squared
        Mahalanobis distance, over the pairs of one type within the gate (markers: any distance);
        objects in `skip` take no part."""
        if not self._tracks or not objects:
            return []
        xy = np.array([o.centroid_xy for o in objects], dtype=np.float64)
        r = np.array([self._measurement_var(o) for o in objects], dtype=np.float64)
        codes: dict[tuple[str, int | str], int] = {}
        kinds = np.array([codes.setdefault(_type_key(o), len(codes)) for o in objects])
        cost = np.full((len(self._tracks), len(objects)), _UNMATCHED)
        for ti, t in enumerate(self._tracks):
            if t.key not in codes:
                continue
            same = kinds == codes[t.key]
            x, p = t.state()
            # Innovation covariance S = P_xy + r I per object; d^2 = v' S^-1 v in closed form (2 x 2).
            a, b, d = p[0, 0] + r, p[0, 1], p[1, 1] + r
            det = a * d - b * b
            dx, dy = xy[:, 0] - x[0], xy[:, 1] - x[1]
            d2 = (d * dx * dx - 2 * b * dx * dy + a * dy * dy) / det
            if t.key[0] == "marker":
                # By id: the gate does not apply; among same-id objects the nearest wins.
                ok = same
                d2 = np.minimum(d2, _UNMATCHED / 2)
            else:
                ok = same & (d2 <= GATE_CHI2)
            cost[ti] = np.where(ok, d2, _UNMATCHED)
        if skip:
            cost[:, sorted(skip)] = _UNMATCHED
        from scipy.optimize import linear_sum_assignment  # on first use: see drvs.server.fusion

        rows, cols = linear_sum_assignment(cost)
        return [(r_, c) for r_, c in zip(rows.tolist(), cols.tolist(), strict=True) if cost[r_, c] < _UNMATCHED]

    def _report(self, t: _Track, seen_now: bool) -> WorldObject:
        x, p = t.state()
        cx, cy, vx, vy = (float(v) for v in x)
        # The largest eigenvalue of the 2 x 2 position covariance, in closed form.
        a, b, d = float(p[0, 0]), float(p[0, 1]), float(p[1, 1])
        sigma = math.sqrt(max(0.0, (a + d) / 2 + math.hypot((a - d) / 2, b)))
        speed = math.hypot(vx, vy)
        heading = math.degrees(math.atan2(vy, vx)) if speed >= MIN_HEADING_SPEED_MPS else None
        last = t.last
        dx, dy = cx - t.seen_xy[0], cy - t.seen_xy[1]
        outline = last.outline if last.outline.is_empty else affinity.translate(last.outline, dx, dy)
        x0, y0, x1, y1 = last.bounds
        return replace(
            last,
            track_id=t.track_id,
            outline=outline,
            bounds=(x0 + dx, y0 + dy, x1 + dx, y1 + dy),
            centroid_xy=(cx, cy),
            velocity_xy=(vx, vy),
            course_deg=heading,
            uncertainty_m=sigma,
            camera_ids=last.camera_ids if seen_now else (),
        )


def _fragment(o: WorldObject, tracked: Sequence[WorldObject]) -> bool:
    """Is `o` a piece of an object already tracked this period: of its type, its outline touching
    (within FRAGMENT_MARGIN_M) that object's? A camera that sees part of an object at its view's
    edge, placed a little off by its calibration, can leave that part out of the fused object: it
    is not a new object. Markers with an id never are."""
    key = _type_key(o)
    if key[0] == "marker" or o.outline.is_empty:
        return False
    x0, y0, x1, y1 = o.outline.bounds
    m = FRAGMENT_MARGIN_M
    for t in tracked:
        if _type_key(t) != key or t.outline.is_empty:
            continue
        a0, b0, a1, b1 = t.outline.bounds
        if a0 <= x1 + m and x0 <= a1 + m and b0 <= y1 + m and y0 <= b1 + m and o.outline.distance(t.outline) <= m:
            return True
    return False


def _check(objects: Sequence[WorldObject], at: float) -> None:
    if not (isinstance(at, (int, float)) and math.isfinite(at)):
        raise InvalidArgument(f"at: {at!r} must be a finite time in seconds")
    for i, o in enumerate(objects):
        if not all(math.isfinite(v) for v in o.centroid_xy):
            raise InvalidArgument(f"objects[{i}].centroid_xy: {o.centroid_xy} must be finite")
        if not (math.isfinite(o.uncertainty_m) and o.uncertainty_m >= 0):
            raise InvalidArgument(f"objects[{i}].uncertainty_m: {o.uncertainty_m} must be a finite number >= 0")

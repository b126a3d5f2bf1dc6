"""Where moving obstacles will be: the simulated robot's prediction from fused tracks. Pure logic.

A tracked obstacle (`drvs.core.model.WorldObject`: outline, centroid, velocity, uncertainty, when it was
last seen) is assumed to keep its velocity. For each instant of the robot's planning horizon the
robot's disc is checked against the obstacle's footprint swept along its predicted path over that
instant's time step, grown by the robot's clearance, by the track's uncertainty, and by a margin
that grows with how far ahead the prediction reaches (a trolley can be stopped or turned).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import shapely
from shapely import affinity
from shapely.geometry import LineString, Polygon

from drvs.core.model import WorldObject

#: The planning horizon: the robot looks this far ahead, seconds, at this time step.
HORIZON_S = 3.0
STEP_S = 0.1
#: Sigmas of a track's centroid uncertainty added to the clearance.
UNCERTAINTY_SIGMAS = 2.0
#: The predicted footprint grows by this fraction of the distance the obstacle is predicted to go:
#: the further ahead, the less sure (it may slow down, stop or turn).
DRIFT_FRACTION = 0.25


@dataclass(frozen=True)
class MovingObstacle:
    """A tracked obstacle as the robot predicts it: its outline when last seen, moved on at its velocity."""

    key: str
    outline: Polygon
    velocity_xy: tuple[float, float]
    uncertainty_m: float
    seen: float  # Unix time of the outline and velocity

    @classmethod
    def from_track(cls, key: str, obj: WorldObject, predict: bool = True) -> MovingObstacle:
        """`predict=False`: the robot ignores the velocity (the obstacle stays where it was seen)."""
        outline = obj.outline if not obj.outline.is_empty else shapely.box(*obj.bounds)
        velocity = obj.velocity_xy if predict else (0.0, 0.0)
        return cls(key, outline, velocity, obj.uncertainty_m, obj.last_seen)

    @property
    def speed_mps(self) -> float:
        return math.hypot(*self.velocity_xy)

    def at(self, t: float) -> Polygon:
        """The outline moved on to Unix time `t`."""
        dt = t - self.seen
        moved: Polygon = affinity.translate(self.outline, self.velocity_xy[0] * dt, self.velocity_xy[1] * dt)
        return moved

    def swept(self, t0: float, t1: float, clearance: float) -> Polygon:
        """The floor it covers between Unix times t0 and t1 (t0 <= t1), grown by `clearance`, its
        uncertainty and the drift margin of the later time."""
        grow = clearance + UNCERTAINTY_SIGMAS * self.uncertainty_m
        grow += DRIFT_FRACTION * self.speed_mps * max(0.0, t1 - self.seen)
        if self.speed_mps == 0.0:
            return self.outline.buffer(grow, quad_segs=4)
        hull = shapely.union(self.at(t0), self.at(t1)).convex_hull
        return hull.buffer(grow, quad_segs=4)


def positions_along(
    path: Sequence[tuple[float, float]], speed_mps: float, horizon_s: float = HORIZON_S, step_s: float = STEP_S
) -> list[tuple[float, float]]:
    """Where a robot driving `path` (its first point is where it is now) at `speed_mps` is after
    0, step_s, 2 step_s ... horizon_s seconds; it stays at the path's end once there."""
    count = round(horizon_s / step_s) + 1
    if len(path) < 2 or speed_mps <= 0:
        return [(path[0][0], path[0][1])] * count
    line = LineString(path)
    return [(p.x, p.y) for p in (line.interpolate(min(i * step_s * speed_mps, line.length)) for i in range(count))]


def first_conflict(
    positions: Sequence[tuple[float, float]],
    obstacles: Sequence[MovingObstacle],
    now: float,
    clearance: float,
    step_s: float = STEP_S,
) -> float | None:
    """The first time (seconds from `now`) at which the robot, at `positions[i]` at now + i * step_s,
    would be within `clearance` of an obstacle's predicted footprint swept over that step (what
    `MovingObstacle.swept` draws); None when the way is clear over the whole horizon.

    Computed in each obstacle's own frame, all instants at once: the robot's position less the
    obstacle's motion over the step is a short segment, and the robot meets the swept footprint
    when that segment comes within the grown clearance of the outline as last seen."""
    if not obstacles or not positions:
        return None
    where = np.asarray(positions, dtype=np.float64)
    times = now + np.arange(len(where)) * step_s
    start, stop = np.maximum(times - step_s, now), times + step_s
    first: int | None = None
    for obstacle in obstacles:
        v = np.asarray(obstacle.velocity_xy, dtype=np.float64)
        a = where - np.outer(start - obstacle.seen, v)
        b = where - np.outer(stop - obstacle.seen, v) + 1e-9  # never a zero-length segment
        distance = shapely.distance(obstacle.outline, shapely.linestrings(np.stack([a, b], axis=1)))
        grow = clearance + UNCERTAINTY_SIGMAS * obstacle.uncertainty_m
        grow = grow + DRIFT_FRACTION * obstacle.speed_mps * np.maximum(0.0, stop - obstacle.seen)
        hits = np.flatnonzero(distance <= grow)
        if len(hits) and (first is None or int(hits[0]) < first):
            first = int(hits[0])
    return None if first is None else first * step_s


def decide(
    path: Sequence[tuple[float, float]],
    step_m: float,
    speed_mps: float,
    obstacles: Sequence[MovingObstacle],
    now: float,
    clearance: float,
) -> bool:
    """Drive on (True) or wait where it is (False) for one step of `step_m` along `path`.

    Drive when the way ahead is clear over the horizon, or when the next step ends somewhere the
    robot can wait safely (it closes up to a crossing obstacle, then lets it pass); else wait when
    waiting here is safe; else do whichever meets an obstacle later."""
    ahead = positions_along(path, speed_mps)
    conflict = first_conflict(ahead, obstacles, now, clearance)
    if conflict is None:
        return True
    step_s = step_m / speed_mps if speed_mps > 0 else 0.0
    after = positions_along(path, speed_mps, horizon_s=step_s, step_s=max(step_s, 1e-6))[-1]
    hold_after = first_conflict([after] * len(ahead), obstacles, now + step_s, clearance)
    if hold_after is None:
        return True
    hold_here = first_conflict([(path[0][0], path[0][1])] * len(ahead), obstacles, now, clearance)
    if hold_here is None:
        return False
    return conflict > hold_here


#: A track is a standing obstacle once it has been followed this long and over the last
#: STILL_WINDOW_S has neither moved more than STILL_M nor reported more than STILL_MPS.
STATIC_AFTER_S = 0.6
STILL_WINDOW_S = 1.0
STILL_M = 0.08
STILL_MPS = 0.1


class TrackRecord:
    """What the robot knows of one track of one of its fused requests: for deciding whether it
    stands still (a map obstacle) or moves (predicted), and for result.json's `tracks`."""

    def __init__(self, key: str, filter_def: str, obj: WorldObject, at: float) -> None:
        self.key = key
        self.filter_def = filter_def
        self.track_id = obj.track_id
        self.first_seen = at
        self.first_xy = obj.centroid_xy
        self.snapshots = 0
        self.max_speed = 0.0
        self.velocity_sum = (0.0, 0.0)
        self.static = False
        self.moving = False
        self.history: list[tuple[float, float, float]] = []
        #: The moving track of an earlier request this one continues (a re-plan's new request).
        self.handed_over: TrackRecord | None = None
        self.last = obj
        self.last_seen = at
        self.update(obj, at)

    def update(self, obj: WorldObject, at: float) -> None:
        self.last = obj
        self.last_seen = at
        self.snapshots += 1
        self.max_speed = max(self.max_speed, obj.speed_mps)
        self.velocity_sum = (self.velocity_sum[0] + obj.velocity_xy[0], self.velocity_sum[1] + obj.velocity_xy[1])
        self.history.append((at, *obj.centroid_xy))
        self.history = [h for h in self.history if h[0] >= at - STILL_WINDOW_S]
        if obj.speed_mps >= STILL_MPS or self._spread() >= STILL_M:
            self.moving = True

    def _spread(self) -> float:
        x0, y0 = self.history[0][1:]
        return max(math.hypot(x - x0, y - y0) for _, x, y in self.history)

    def stands_still(self) -> bool:
        """Followed long enough, and neither moved nor reported a speed over the last window."""
        return (
            self.last_seen - self.first_seen >= STATIC_AFTER_S
            and self._spread() < STILL_M
            and self.last.speed_mps < STILL_MPS
        )

    def summary(self, epoch: float) -> dict[str, object]:
        """Small: ids, when (seconds since `epoch`, the mission's start), where first and last,
        the mean velocity and the top speed, and what the robot made of it."""
        n = max(self.snapshots, 1)
        return {
            "track_id": self.track_id,
            "filter_def": self.filter_def,
            "first_seen_s": round(self.first_seen - epoch, 2),
            "last_seen_s": round(self.last_seen - epoch, 2),
            "snapshots": self.snapshots,
            "first": [round(v, 3) for v in self.first_xy],
            "last": [round(v, 3) for v in self.last.centroid_xy],
            "mean_velocity": [round(self.velocity_sum[0] / n, 3), round(self.velocity_sum[1] / n, 3)],
            "max_speed_mps": round(self.max_speed, 3),
            "used_as": ("moving, then standing" if self.static else "moving")
            if self.moving
            else ("standing" if self.static else "unsure"),
        }

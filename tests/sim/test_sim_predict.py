"""The simulated robot's prediction (drvs.sim.predict), on model types alone: it waits for an
obstacle about to cross its way, does not wait for one that has already crossed, and a robot that
ignored velocity would drive into the first; tracks are told apart as standing or moving."""

from __future__ import annotations

import pytest
from shapely.geometry import box

from drvs.core.model import WorldObject
from drvs.sim.predict import MovingObstacle, TrackRecord, decide, first_conflict, positions_along

NOW = 1_000_000.0
CLEARANCE = 0.3  # the robot's radius and margin
#: The robot drives east along y = 2 at 1 m/s from x = 0.
PATH = [(0.0, 2.0), (8.0, 2.0)]


def trolley(x: float, y: float, vy: float, seen: float = NOW, sigma: float = 0.02) -> WorldObject:
    """A 0.6 m square trolley centred at (x, y), moving north at vy m/s."""
    outline = box(x - 0.3, y - 0.3, x + 0.3, y + 0.3)
    return WorldObject(1, outline, outline.bounds, (x, y), (0.0, vy), 90.0 if vy else None, sigma, ("c",), seen)


def test_positions_along_the_path_at_the_robots_speed() -> None:
    pos = positions_along(PATH, 1.0, horizon_s=1.0, step_s=0.5)
    assert pos == [(0.0, 2.0), (0.5, 2.0), (1.0, 2.0)]
    assert positions_along([(7.5, 2.0), (8.0, 2.0)], 1.0, 2.0, 1.0)[-1] == (8.0, 2.0)  # stays at the end
    assert positions_along([(1.0, 1.0)], 1.0, 1.0, 0.5) == [(1.0, 1.0)] * 3


def test_it_waits_for_a_trolley_about_to_cross_and_one_ignoring_velocity_would_not() -> None:
    # The trolley is 1.4 m south of the robot's line at x = 1.5, coming north at 0.8 m/s: it is on
    # the line from about 1.1 s to 2.6 s, just when the robot (at x = 1.5 after 1.5 s) gets there.
    coming = trolley(1.5, 0.6, 0.8)
    predicted = MovingObstacle.from_track("t", coming)
    conflict = first_conflict(positions_along(PATH, 1.0), [predicted], NOW, CLEARANCE)
    assert conflict is not None and 0.5 < conflict < 1.6
    assert decide(PATH, 0.1, 1.0, [predicted], NOW, CLEARANCE) is True  # it may close up for now ...
    close = [(0.8, 2.0), (8.0, 2.0)]
    assert decide(close, 0.1, 1.0, [predicted], NOW, CLEARANCE) is False  # ... and waits at its edge
    # Ignoring its velocity, the way looks clear: the robot would drive on into it.
    blind = MovingObstacle.from_track("t", coming, predict=False)
    assert first_conflict(positions_along(PATH, 1.0), [blind], NOW, CLEARANCE) is None
    assert decide(close, 0.1, 1.0, [blind], NOW, CLEARANCE) is True


def test_it_closes_up_to_a_crossing_obstacle_then_lets_it_pass() -> None:
    # At x = 2.5 the trolley comes north, reaching the line as the robot would: the robot may
    # drive on for a while ...
    crossing = MovingObstacle.from_track("t", trolley(2.5, 1.2, 0.4))
    assert first_conflict(positions_along(PATH, 1.0), [crossing], NOW, CLEARANCE) is not None
    assert decide(PATH, 0.1, 1.0, [crossing], NOW, CLEARANCE) is True
    # ... but close to its way it waits.
    near = [(1.7, 2.0), (8.0, 2.0)]
    assert decide(near, 0.1, 1.0, [crossing], NOW, CLEARANCE) is False


def test_an_obstacle_that_has_already_crossed_is_no_reason_to_wait() -> None:
    # Just north of the line and going away north at 0.6 m/s: it was on the line half a second ago.
    gone = MovingObstacle.from_track("t", trolley(1.2, 2.7, 0.6))
    assert first_conflict(positions_along(PATH, 1.0), [gone], NOW, CLEARANCE) is None
    assert decide(PATH, 0.1, 1.0, [gone], NOW, CLEARANCE) is True
    # The same place standing still blocks the line (it is within the clearance of it).
    standing = MovingObstacle.from_track("t", trolley(1.2, 2.5, 0.0))
    assert first_conflict(positions_along(PATH, 1.0), [standing], NOW, CLEARANCE) is not None


def test_the_prediction_is_grown_by_uncertainty_and_by_how_far_ahead_it_reaches() -> None:
    o = MovingObstacle.from_track("t", trolley(0.0, 0.0, 1.0, sigma=0.05))
    now_area = o.swept(NOW, NOW, 0.0).area
    assert now_area == pytest.approx((0.6 + 0.2) ** 2, rel=0.05)  # 2 sigmas on each side
    later = o.swept(NOW + 2.0, NOW + 2.0, 0.0)
    assert later.centroid.y == pytest.approx(2.0, abs=0.01) and later.area > now_area * 1.5  # drift margin
    assert o.swept(NOW, NOW + 1.0, 0.0).bounds[3] > 1.3  # swept over the second


def test_tracks_are_told_apart_as_standing_or_moving() -> None:
    box_ = trolley(3.0, 3.0, 0.0)
    record = TrackRecord("a/1", "hsv_x", box_, NOW)
    for i in range(1, 5):
        record.update(trolley(3.0 + 0.002 * (i % 2), 3.0, 0.01), NOW + 0.1 * i)
    assert not record.stands_still()  # 0.4 s: too soon to say
    for i in range(5, 10):
        record.update(trolley(3.0, 3.0, 0.01), NOW + 0.1 * i)
    assert record.stands_still() and not record.moving
    mover = TrackRecord("a/2", "hsv_x", trolley(1.0, 1.0, 0.5), NOW)
    for i in range(1, 10):
        mover.update(trolley(1.0, 1.0 + 0.05 * i, 0.5), NOW + 0.1 * i)
    assert mover.moving and not mover.stands_still()
    for i in range(10, 25):  # it stops: parked
        mover.update(trolley(1.0, 1.45, 0.0), NOW + 0.1 * i)
    assert mover.stands_still()
    mover.static = True
    summary = mover.summary(NOW)
    assert summary["used_as"] == "moving, then standing" and summary["max_speed_mps"] == 0.5
    assert summary["first"] == [1.0, 1.0] and summary["last"] == [1.0, 1.45] and summary["snapshots"] == 25


def test_a_replans_new_track_of_a_moving_obstacle_keeps_its_motion() -> None:
    """A re-plan sends a new track request, whose tracks are numbered anew and have no velocity
    until their second look. A new track where a moving track of the earlier request was just seen
    is that obstacle: it is predicted at that track's velocity, not taken to stand still (the
    default office's robot was once run into by the trolley that way; CI, 6e30bf9)."""
    from drvs.core.model import Snapshot
    from drvs.sim.robot import SimRobot
    from drvs.sim.scenario import load_scenario

    robot = SimRobot(load_scenario(), None, None)
    for i in range(4):  # the trolley heads south at 0.4 m/s, followed by the first request
        t = NOW + 0.5 * i
        robot.use_snapshot("hsv_x", "r1", Snapshot(t, (trolley(16.8, 7.7 - 0.2 * i, -0.4, seen=t),)))
    assert robot.moving["r1/1"].velocity_xy == (0.0, -0.4)
    t = NOW + 2.0  # re-planned: the new request's first look, no velocity yet
    robot.use_snapshot("hsv_x", "r2", Snapshot(t, (trolley(16.8, 6.95, 0.0, seen=t),)))
    assert robot.moving["r2/1"].velocity_xy == (0.0, -0.4)
    far = NOW + 2.0 + 0.1  # something new elsewhere takes over nothing
    robot.use_snapshot("hsv_x", "r3", Snapshot(far, (trolley(3.0, 3.0, 0.0, seen=far),)))
    assert robot.moving["r3/1"].velocity_xy == (0.0, 0.0)

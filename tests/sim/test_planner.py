"""A* planning on an occupancy grid: conservative rasterising, blocked and unreachable goals, corners, clearance."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import shapely
from shapely.geometry import LineString, Point, Polygon, box
from shapely.ops import unary_union

from drvs.sim.planner import NoPath, OccupancyGrid, plan_path

RES = 0.1
#: One cell diagonal: the slack the brief allows between the driven path and the inflated obstacle.
CELL_DIAGONAL = RES * math.sqrt(2.0)
#: What the rasteriser actually guarantees: the inflation minus the buffer's chord error (well under 1 mm).
CHORD_SLACK = 1e-3

Path = list[tuple[float, float]]


def samples(path: Path, step: float = 0.01) -> np.ndarray:
    """Points every `step` metres along the path, both ends included."""
    line = LineString(path)
    n = max(1, math.ceil(line.length / step))
    return np.asarray(shapely.line_interpolate_point(line, np.linspace(0.0, line.length, n + 1)))


def clearance(path: Path, obstacle: Polygon) -> float:
    """Smallest distance from any point sampled along the path to the obstacle."""
    return float(np.min(shapely.distance(samples(path), obstacle)))


def all_segments_free(grid: OccupancyGrid, path: Path) -> bool:
    return all(grid.segment_is_free(a, b) for a, b in itertools.pairwise(path))


def crossing_y(path: Path, x: float) -> list[float]:
    """Where the path crosses the vertical line at x."""
    hit = LineString(path).intersection(LineString([(x, -1e3), (x, 1e3)]))
    return sorted(p.y for p in shapely.get_parts(hit))


def cell_boxes(grid: OccupancyGrid) -> np.ndarray:
    """Each cell's square as a shapely box, [row, col]."""
    x_min, y_min, _, _ = grid.bounds
    rows, cols = np.mgrid[0 : grid.shape[0], 0 : grid.shape[1]]
    r = grid.resolution_m
    return np.asarray(shapely.box(x_min + cols * r, y_min + rows * r, x_min + (cols + 1) * r, y_min + (rows + 1) * r))


# --- the grid ---------------------------------------------------------------------------------------------------


def test_grid_shape_cells_and_centres() -> None:
    grid = OccupancyGrid((0.0, 0.0, 30.0, 20.0), RES)
    assert grid.shape == (200, 300)
    assert grid.occupied.shape == (200, 300) and not grid.occupied.any()
    assert grid.bounds == (0.0, 0.0, 30.0, 20.0) and grid.resolution_m == RES
    assert grid.cell_of(0.05, 0.05) == (0, 0)
    assert grid.cell_of(29.95, 0.05) == (0, 299)  # column is x, row is y
    assert grid.cell_of(0.05, 19.95) == (199, 0)
    assert grid.centre_of(199, 0) == pytest.approx((0.05, 19.95))
    assert grid.cell_of(*grid.centre_of(123, 45)) == (123, 45)
    assert grid.cell_of(-0.05, 0.05) == (0, -1)  # outside: returned as is


def test_grid_with_offset_bounds_and_partial_last_cell() -> None:
    grid = OccupancyGrid((-2.0, 1.0, 1.05, 2.0), 0.5)
    assert grid.shape == (2, 7)
    assert grid.centre_of(0, 0) == pytest.approx((-1.75, 1.25))
    assert grid.is_free(1.05, 2.0)
    assert not grid.is_free(1.06, 1.5)  # still inside the last cell's square, but outside the bounds
    assert plan_path(grid, (-2.0, 1.0), (1.05, 2.0)) == [(-2.0, 1.0), (1.05, 2.0)]  # corner to corner


@pytest.mark.parametrize(
    ("bounds", "resolution"),
    [
        ((0.0, 0.0, 0.0, 1.0), 0.1),
        ((0.0, 2.0, 1.0, 1.0), 0.1),
        ((0.0, 0.0, math.inf, 1.0), 0.1),
        ((0.0, 0.0, 1.0, math.nan), 0.1),
        ((0.0, 0.0, 1.0, 1.0), 0.0),
        ((0.0, 0.0, 1.0, 1.0), -0.1),
        ((0.0, 0.0, 1.0, 1.0), math.nan),
    ],
)
def test_bad_bounds_or_resolution_raise(bounds: tuple[float, float, float, float], resolution: float) -> None:
    with pytest.raises(ValueError):
        OccupancyGrid(bounds, resolution)


def test_negative_inflation_raises() -> None:
    with pytest.raises(ValueError, match="inflate_m"):
        OccupancyGrid((0.0, 0.0, 1.0, 1.0)).add_polygon(box(0.2, 0.2, 0.4, 0.4), -0.1)


def test_outside_bounds_is_not_free() -> None:
    grid = OccupancyGrid((0.0, 0.0, 2.0, 2.0), RES)
    assert grid.is_free(1.0, 1.0)
    assert not grid.is_free(-0.01, 1.0)
    assert not grid.is_free(1.0, 2.01)
    assert not grid.is_free(math.nan, 1.0)
    assert not grid.segment_is_free((1.0, 1.0), (2.5, 1.0))
    assert grid.segment_is_free((0.0, 0.0), (2.0, 2.0))  # the bounds themselves are inside


def test_occupied_is_a_read_only_view() -> None:
    grid = OccupancyGrid((0.0, 0.0, 1.0, 1.0), RES)
    with pytest.raises(ValueError):
        grid.occupied[0, 0] = True
    grid.add_polygon(box(0.0, 0.0, 0.05, 0.05))
    assert grid.occupied[0, 0]


def test_add_polygon_reports_whether_anything_changed() -> None:
    grid = OccupancyGrid((0.0, 0.0, 5.0, 5.0), RES)
    desk = box(1.0, 1.0, 2.0, 1.8)
    assert grid.add_polygon(desk, 0.2) is True
    after_first = grid.occupied.copy()
    assert grid.add_polygon(desk, 0.2) is False
    assert grid.add_polygon(box(1.2, 1.2, 1.6, 1.6)) is False  # wholly within what is already occupied
    assert grid.add_polygon(box(10.0, 10.0, 11.0, 11.0), 0.5) is False  # wholly outside the grid
    assert grid.add_polygon(Polygon()) is False
    assert np.array_equal(grid.occupied, after_first)
    assert grid.add_polygon(desk, 0.3) is True  # more inflation reaches new cells


def test_copy_is_independent() -> None:
    plan = OccupancyGrid((0.0, 0.0, 5.0, 5.0), RES)
    plan.add_polygon(box(1.0, 1.0, 2.0, 2.0), 0.2)
    run = plan.copy()
    assert np.array_equal(run.occupied, plan.occupied)
    assert run.add_polygon(box(3.0, 3.0, 4.0, 4.0), 0.2) is True
    assert not plan.occupied[35, 35] and run.occupied[35, 35]
    assert run.bounds == plan.bounds and run.resolution_m == plan.resolution_m


def test_inflated_box_occupies_to_its_inflation_and_no_further() -> None:
    grid = OccupancyGrid((0.0, 0.0, 4.0, 4.0), RES)
    grid.add_polygon(box(1.5, 1.5, 2.5, 2.5), 0.2)
    s = 1 / math.sqrt(2.0)
    for d in (0.0, 0.1, 0.19, 0.2):
        assert not grid.is_free(2.5 + d, 2.0), d
        assert not grid.is_free(2.0, 1.5 - d), d
        assert not grid.is_free(2.5 + d * s, 2.5 + d * s), d  # round the corner
    for d in (0.35, 0.5):
        assert grid.is_free(2.5 + d, 2.0), d
        assert grid.is_free(2.0, 1.5 - d), d
        assert grid.is_free(2.5 + d * s, 2.5 + d * s), d


@pytest.mark.parametrize(
    ("polygon", "inflate"),
    [
        (box(1.5, 1.5, 2.5, 2.5), 0.2),
        (shapely.affinity.rotate(box(1.03, 1.21, 2.87, 1.64), 27.0), 0.17),
        (Polygon([(0.52, 0.61), (3.3, 1.07), (1.71, 3.45), (1.9, 1.6)]), 0.0),
        (box(0.5, 0.5, 3.5, 3.5).difference(box(1.13, 1.07, 2.91, 2.88)), 0.05),
        (box(-1.0, 1.04, 6.0, 1.06), 0.0),  # thinner than a cell, off the grid on both ends
    ],
)
def test_occupied_cells_are_exactly_those_meeting_the_inflated_polygon(polygon: Polygon, inflate: float) -> None:
    grid = OccupancyGrid((0.0, 0.0, 4.0, 4.0), RES)
    grid.add_polygon(polygon, inflate)
    distance = shapely.distance(cell_boxes(grid), polygon.buffer(inflate, quad_segs=64) if inflate else polygon)
    assert grid.occupied[distance <= 1e-9].all()  # every cell the shape meets (or touches)
    assert not grid.occupied[distance > CHORD_SLACK].any()  # and none clear of it


def test_sliver_between_cell_centres_still_blocks() -> None:
    grid = OccupancyGrid((0.0, 0.0, 5.0, 5.0), RES)
    assert grid.add_polygon(box(2.01, 0.0, 2.011, 5.0)) is True  # 1 mm thick, no cell centre inside
    assert grid.occupied[:, 20].all() and grid.occupied.sum() == 50
    with pytest.raises(NoPath, match="walled off"):
        plan_path(grid, (1.0, 2.5), (4.0, 2.5))


# --- planning -------------------------------------------------------------------------------------------------------


def test_empty_room_gives_the_straight_line() -> None:
    grid = OccupancyGrid((0.0, 0.0, 10.0, 5.0), RES)
    assert plan_path(grid, (1.0, 1.0), (9.0, 1.0)) == [(1.0, 1.0), (9.0, 1.0)]


def test_start_equal_to_goal_is_a_single_point() -> None:
    grid = OccupancyGrid((0.0, 0.0, 10.0, 5.0), RES)
    assert plan_path(grid, (3.0, 3.0), (3.0, 3.0)) == [(3.0, 3.0)]


def test_path_goes_through_the_gap_in_a_wall_with_clearance() -> None:
    inflate = 0.3
    grid = OccupancyGrid((0.0, 0.0, 10.0, 6.0), RES)
    wall = unary_union([box(4.9, 0.0, 5.1, 2.5), box(4.9, 3.5, 5.1, 6.0)])  # gap for y in 2.5..3.5
    grid.add_polygon(wall, inflate)
    path = plan_path(grid, (1.0, 1.0), (9.0, 1.0))
    assert path[0] == (1.0, 1.0) and path[-1] == (9.0, 1.0)
    (y,) = crossing_y(path, 5.0)
    assert 2.5 + inflate <= y <= 3.5 - inflate
    assert clearance(path, wall) >= inflate - CELL_DIAGONAL
    assert clearance(path, wall) >= inflate - CHORD_SLACK  # the conservative grid does better than the brief asks
    assert all_segments_free(grid, path)
    assert len(path) == 4  # smoothing leaves one corner at each side of the gap


def test_blocked_goal_ends_at_the_nearest_free_cell() -> None:
    grid = OccupancyGrid((0.0, 0.0, 10.0, 10.0), RES)
    grid.add_polygon(box(4.0, 4.0, 6.0, 6.0))
    # Row 39 (y 3.9..4.0) touches the box's lower edge, so the nearest free cell is row 38, centre y 3.85.
    path = plan_path(grid, (1.0, 1.0), (5.02, 4.55))
    assert path == [(1.0, 1.0), pytest.approx((5.05, 3.85))]


def test_blocked_goal_ends_at_the_nearest_free_cell_that_can_be_reached() -> None:
    grid = OccupancyGrid((0.0, 0.0, 10.0, 10.0), RES)
    room = box(4.0, 4.0, 7.0, 7.0).difference(box(4.5, 4.5, 6.5, 6.5))  # closed room, walls 0.5 m thick
    grid.add_polygon(room)
    path = plan_path(grid, (1.0, 5.0), (4.4, 5.02))  # in the wall, nearer the sealed inside than the outside
    assert path[-1] == pytest.approx((3.85, 5.05))


def test_start_pressed_against_an_obstacle_leaves_by_the_nearest_free_cell() -> None:
    grid = OccupancyGrid((0.0, 0.0, 10.0, 10.0), RES)
    grid.add_polygon(box(4.0, 4.0, 6.0, 6.0))
    path = plan_path(grid, (4.02, 5.02), (1.0, 5.02))
    assert path == [(4.02, 5.02), pytest.approx((3.85, 5.05)), (1.0, 5.02)]


def test_enclosed_goal_region_raises_no_path() -> None:
    grid = OccupancyGrid((0.0, 0.0, 10.0, 10.0), RES)
    grid.add_polygon(box(6.0, 6.0, 9.0, 9.0).difference(box(6.2, 6.2, 8.8, 8.8)), 0.1)
    assert grid.is_free(7.5, 7.5)
    with pytest.raises(NoPath, match=r"no path from start \(1\.0, 1\.0\) to goal \(7\.5, 7\.5\): .*walled off"):
        plan_path(grid, (1.0, 1.0), (7.5, 7.5))
    with pytest.raises(NoPath, match="walled off"):
        plan_path(grid, (7.5, 7.5), (1.0, 1.0))  # and out of it


def test_start_outside_bounds_raises_no_path_naming_start() -> None:
    grid = OccupancyGrid((0.0, 0.0, 10.0, 10.0), RES)
    with pytest.raises(NoPath, match=r"start \(-1\.0, 5\.0\) is outside the grid bounds"):
        plan_path(grid, (-1.0, 5.0), (5.0, 5.0))
    with pytest.raises(NoPath, match=r"goal \(5\.0, 10\.5\) is outside the grid bounds"):
        plan_path(grid, (5.0, 5.0), (5.0, 10.5))


def test_fully_occupied_grid_raises_no_path() -> None:
    grid = OccupancyGrid((0.0, 0.0, 1.0, 1.0), RES)
    grid.add_polygon(box(0.0, 0.0, 1.0, 1.0))
    with pytest.raises(NoPath, match="every cell"):
        plan_path(grid, (0.5, 0.5), (0.7, 0.7))


def test_no_corner_cutting_between_two_diagonal_occupied_cells() -> None:
    grid = OccupancyGrid((0.0, 0.0, 1.0, 1.0), RES)
    for i in range(10):  # a staircase wall of cells (i, i), neighbours only at their corners
        grid.add_polygon(box(i * RES + 0.03, i * RES + 0.03, i * RES + 0.07, i * RES + 0.07))
    assert grid.occupied.sum() == 10 and np.array_equal(grid.occupied, np.eye(10, dtype=bool))
    with pytest.raises(NoPath, match="walled off"):
        plan_path(grid, (0.85, 0.15), (0.15, 0.85))


def test_path_detours_round_a_diagonal_pair_instead_of_through_their_corner() -> None:
    grid = OccupancyGrid((0.0, 0.0, 1.0, 1.0), RES)
    grid.add_polygon(box(0.43, 0.53, 0.47, 0.57))  # cell (5, 4)
    grid.add_polygon(box(0.53, 0.43, 0.57, 0.47))  # cell (4, 5): the two meet only at (0.5, 0.5)
    start, goal = grid.centre_of(4, 4), grid.centre_of(5, 5)
    assert not grid.segment_is_free(start, goal)  # the straight line passes through the shared corner
    path = plan_path(grid, start, goal)
    assert path[0] == start and path[-1] == goal and len(path) > 2
    assert LineString(path).distance(Point(0.5, 0.5)) > 0.04
    assert all_segments_free(grid, path)


def test_path_around_a_u_shaped_obstacle_never_crosses_it() -> None:
    inflate = 0.25
    grid = OccupancyGrid((0.0, 0.0, 12.0, 10.0), RES)
    u_shape = unary_union([box(6.0, 3.0, 6.2, 7.0), box(3.0, 3.0, 6.2, 3.2), box(3.0, 6.8, 6.2, 7.0)])  # open to -x
    assert grid.add_polygon(u_shape, inflate) is True
    path = plan_path(grid, (4.5, 5.0), (9.0, 5.0))  # from inside the U to behind its base
    assert path[0] == (4.5, 5.0) and path[-1] == (9.0, 5.0)
    assert all_segments_free(grid, path)
    assert not LineString(path).intersects(u_shape)
    assert clearance(path, u_shape) >= inflate - CHORD_SLACK
    assert min(x for x, _ in path) < 3.0 - inflate  # it left through the mouth


def test_replanning_after_learning_an_obstacle() -> None:
    grid = OccupancyGrid((0.0, 0.0, 10.0, 5.0), RES)
    before = plan_path(grid, (1.0, 2.5), (9.0, 2.5))
    crate = box(4.5, 2.0, 5.5, 3.0)
    assert grid.add_polygon(crate, 0.3) is True
    assert not all_segments_free(grid, before)
    after = plan_path(grid, (1.0, 2.5), (9.0, 2.5))
    assert all_segments_free(grid, after) and clearance(after, crate) >= 0.3 - CHORD_SLACK


def test_whole_office_floor_goes_through_the_doors() -> None:
    inflate = 0.3
    grid = OccupancyGrid((0.0, 0.0, 30.0, 20.0), RES)
    walls = unary_union(
        [
            box(0.0, 0.0, 30.0, 0.1),
            box(0.0, 19.9, 30.0, 20.0),
            box(0.0, 0.0, 0.1, 20.0),
            box(29.9, 0.0, 30.0, 20.0),
            box(9.9, 0.0, 10.1, 17.0),  # door at y 17..19
            box(9.9, 19.0, 10.1, 20.0),
            box(19.9, 3.0, 20.1, 20.0),  # door at y 1..3
            box(19.9, 0.0, 20.1, 1.0),
        ]
    )
    desks = [box(3.0, 8.0, 5.0, 9.0), box(13.0, 4.0, 15.0, 15.0), box(24.0, 14.0, 26.0, 18.5)]
    grid.add_polygon(walls, inflate)
    for desk in desks:
        grid.add_polygon(desk, inflate)
    start, goal = (1.0, 1.0), (29.0, 19.0)
    path = plan_path(grid, start, goal)
    assert path[0] == start and path[-1] == goal
    (y_door1,) = crossing_y(path, 10.0)
    assert 17.0 + inflate <= y_door1 <= 19.0 - inflate
    (y_door2,) = crossing_y(path, 20.0)
    assert 1.0 + inflate <= y_door2 <= 3.0 - inflate
    assert all_segments_free(grid, path)
    for obstacle in (walls, *desks):
        assert clearance(path, obstacle) >= inflate - CHORD_SLACK
    # No path through both doors is shorter than straight legs via their nearest usable points (about 54.9 m).
    # The desk between the doors costs a detour and line-of-sight smoothing of a grid path is not quite
    # taut (about 61.9 m here), but nothing like a wander round the rooms.
    door1, door2 = (10.0, 17.0 + inflate), (20.0, 3.0 - inflate)
    bound = math.dist(start, door1) + math.dist(door1, door2) + math.dist(door2, goal)
    assert bound <= LineString(path).length <= 1.15 * bound

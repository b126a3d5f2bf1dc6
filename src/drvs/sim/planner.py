"""Path planning for the simulated robot: A* on an occupancy grid. Pure logic, no gRPC.

The grid is the robot's configuration space: obstacles are added inflated by the robot's radius, so the
robot's centre may stand in any free cell. Rasterising is conservative (a cell is occupied as soon as its
closed square meets the inflated shape), so every point of a free cell keeps at least the inflation
distance from every obstacle added (less shapely's chord error on round corners, well under 1 mm), and a
path whose segments cross only free cells keeps it too. plan_path returns such paths, except for the first
leg when the robot starts inside an occupied cell.

Cell (row, col) covers x in [x_min + col*res, x_min + (col+1)*res) and y likewise with row; row 0 is
at y_min, so the occupied array reads [y index, x index] and is upside down when shown as an image.
"""

from __future__ import annotations

import heapq
import math

import cv2
import numpy as np
import shapely
from numpy.typing import NDArray
from shapely.geometry import MultiPolygon, Polygon
from shapely.geometry.base import BaseGeometry

Point2 = tuple[float, float]

#: Slack, in cells, with which a point counts as touching a cell's edge. It makes a segment through the
#: shared corner of two diagonal cells touch all four cells, so smoothing cannot slip between two
#: occupied cells that meet only at a corner, whatever the floating-point rounding.
_EDGE_EPS = 1e-6
#: Sub-pixel bits for cv2.fillPoly: vertices keep 1/256 of a cell of precision instead of being rounded.
_SHIFT = 8
#: Step costs in integer units (1e6 per cell): exact ties on f, so among equal-cost paths A* follows the
#: heuristic straight to the goal instead of wandering over float rounding noise.
_ORTHO = 1_000_000
_DIAG = 1_414_214


class NoPath(Exception):
    """No path exists; the message names start, goal and the reason, for the robot's log."""


class OccupancyGrid:
    """Free/occupied cells over a rectangle of floor; everything outside the rectangle counts as occupied."""

    def __init__(self, bounds: tuple[float, float, float, float], resolution_m: float = 0.1) -> None:
        x_min, y_min, x_max, y_max = (float(v) for v in bounds)
        res = float(resolution_m)
        if not all(math.isfinite(v) for v in (x_min, y_min, x_max, y_max)):
            raise ValueError(f"grid bounds {bounds} must be finite")
        if not (x_min < x_max and y_min < y_max):
            raise ValueError(f"grid bounds {bounds} must be (x_min, y_min, x_max, y_max) with min < max")
        if not (math.isfinite(res) and res > 0):
            raise ValueError(f"grid resolution {resolution_m} m must be a positive number")
        # The small slack keeps e.g. 30 m / 0.1 m (= 299.99999999999994) at 300 columns, not 301.
        cols = math.ceil((x_max - x_min) / res - 1e-9)
        rows = math.ceil((y_max - y_min) / res - 1e-9)
        if rows * cols > 50_000_000:
            raise ValueError(f"grid of {rows} x {cols} cells is too large; use a coarser resolution")
        self._bounds = (x_min, y_min, x_max, y_max)
        self._res = res
        self._occupied = np.zeros((rows, cols), dtype=bool)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) in metres."""
        return self._bounds

    @property
    def resolution_m(self) -> float:
        """Side of one square cell, metres."""
        return self._res

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols): rows along y, columns along x."""
        rows, cols = self._occupied.shape
        return rows, cols

    @property
    def occupied(self) -> NDArray[np.bool_]:
        """Read-only view, [row = y index, col = x index]. Read-only so that every change goes through
        add_polygon, whose return value is what tells callers to re-plan."""
        view = self._occupied.view()
        view.flags.writeable = False
        return view

    def add_polygon(self, polygon: Polygon | MultiPolygon, inflate_m: float = 0.0) -> bool:
        """Mark every cell whose square meets polygon.buffer(inflate_m) as occupied.

        Returns True iff at least one cell went from free to occupied, so callers re-plan only then.
        The interior is filled with cv2.fillPoly (cell centres inside) and the outline is traced exactly
        (every cell it passes through or touches): an 8-connected cv2.polylines would miss cells that an
        edge clips at a corner, and thin shapes would slip through between cell centres.
        """
        inflate = float(inflate_m)
        if not (math.isfinite(inflate) and inflate >= 0):
            raise ValueError(f"inflate_m {inflate_m} must be a finite distance >= 0")
        geom = polygon.buffer(inflate, quad_segs=16) if inflate > 0 else polygon
        if geom.is_empty:
            return False
        x_min, y_min, x_max, y_max = self._bounds
        margin = 2 * self._res
        gx0, gy0, gx1, gy1 = geom.bounds
        if gx1 < x_min - margin or gx0 > x_max + margin or gy1 < y_min - margin or gy0 > y_max + margin:
            return False
        if gx0 < x_min - margin or gx1 > x_max + margin or gy0 < y_min - margin or gy1 > y_max + margin:
            # Keeps cell coordinates small enough for cv2's fixed-point integers; the cut edges lie outside.
            geom = shapely.clip_by_rect(geom, x_min - margin, y_min - margin, x_max + margin, y_max + margin)

        fill_rings: list[NDArray[np.float64]] = []
        outlines: list[NDArray[np.float64]] = []
        for part in _flat_parts(geom):
            if isinstance(part, Polygon):
                for ring in (part.exterior, *part.interiors):
                    coords = self._to_cells(np.asarray(ring.coords, dtype=np.float64))
                    fill_rings.append(coords)
                    outlines.append(coords)
            else:  # LineString or Point left over from clipping: no interior, outline only.
                outlines.append(self._to_cells(np.asarray(part.coords, dtype=np.float64)))

        outline = np.zeros(self._occupied.shape, dtype=np.uint8)
        starts = [c[:-1] if len(c) > 1 else c for c in outlines if len(c)]
        ends = [c[1:] if len(c) > 1 else c for c in outlines if len(c)]
        if starts:
            rows, cols = _touched_cells(np.concatenate(starts), np.concatenate(ends))
            keep = (rows >= 0) & (rows < outline.shape[0]) & (cols >= 0) & (cols < outline.shape[1])
            outline[rows[keep], cols[keep]] = 1
        mask = np.zeros_like(outline)
        if fill_rings:
            # cv2 pixel i has its centre at integer i; cell i has its centre at i + 0.5 in cell units.
            pts = [np.round((c - 0.5) * (1 << _SHIFT)).astype(np.int32).reshape(-1, 1, 2) for c in fill_rings]
            cv2.fillPoly(mask, pts, 1, lineType=cv2.LINE_8, shift=_SHIFT)
            # fillPoly also takes some pixels whose centres lie up to about a pixel outside the edge. Any cell
            # the outline misses is wholly inside or wholly outside, so re-test the centres of filled cells
            # next to the outline exactly; deeper cells are left to fillPoly.
            near = cv2.dilate(outline, np.ones((5, 5), np.uint8)).view(bool) & mask.view(bool) & ~outline.view(bool)
            rows, cols = np.nonzero(near)
            if len(rows):
                x_min, y_min, _, _ = self._bounds
                xs = x_min + (cols + 0.5) * self._res
                ys = y_min + (rows + 0.5) * self._res
                mask[rows, cols] = shapely.contains_xy(geom, xs, ys)
        mask |= outline
        marked = mask.view(bool)
        changed = bool(np.any(marked & ~self._occupied))
        if changed:
            self._occupied |= marked
        return changed

    def is_free(self, x: float, y: float) -> bool:
        """True iff (x, y) lies within bounds (edges included) in a free cell."""
        return self._in_bounds(x, y) and not self._occupied[self._cell_within(x, y)]

    def cell_of(self, x: float, y: float) -> tuple[int, int]:
        """(row, col) of the cell holding (x, y); indices outside the grid are returned as they are."""
        x_min, y_min, _, _ = self._bounds
        return math.floor((y - y_min) / self._res), math.floor((x - x_min) / self._res)

    def centre_of(self, row: int, col: int) -> tuple[float, float]:
        """World (x, y) of a cell's centre."""
        x_min, y_min, _, _ = self._bounds
        return x_min + (col + 0.5) * self._res, y_min + (row + 0.5) * self._res

    def copy(self) -> OccupancyGrid:
        """An independent grid, e.g. the static floor plan to which one run adds what it learns."""
        other = OccupancyGrid(self._bounds, self._res)
        other._occupied = self._occupied.copy()
        return other

    def segment_is_free(self, a: tuple[float, float], b: tuple[float, float]) -> bool:
        """True iff both ends are within bounds and every cell the segment passes through or touches is free."""
        if not (self._in_bounds(*a) and self._in_bounds(*b)):
            return False
        ends = self._to_cells(np.array([a, b], dtype=np.float64))
        (ua, va), (ub, vb) = ends.tolist()
        # Ends lie within bounds, so any index outside is a touch of the outer edge: clip it back in.
        n_rows, n_cols = self._occupied.shape
        c0 = max(math.floor(min(ua, ub) - _EDGE_EPS), 0)
        c1 = min(math.floor(max(ua, ub) + _EDGE_EPS), n_cols - 1)
        r0 = max(math.floor(min(va, vb) - _EDGE_EPS), 0)
        r1 = min(math.floor(max(va, vb) + _EDGE_EPS), n_rows - 1)
        if not self._occupied[r0 : r1 + 1, c0 : c1 + 1].any():
            return True  # nothing occupied anywhere in the box of cells around the segment
        rows, cols = _touched_cells(ends[:1], ends[1:])
        return not bool(self._occupied[np.clip(rows, 0, n_rows - 1), np.clip(cols, 0, n_cols - 1)].any())

    def _cell_within(self, x: float, y: float) -> tuple[int, int]:
        """cell_of for a point within bounds; a point on the upper edges belongs to the last cell."""
        row, col = self.cell_of(x, y)
        rows, cols = self._occupied.shape
        return min(max(row, 0), rows - 1), min(max(col, 0), cols - 1)

    def _in_bounds(self, x: float, y: float) -> bool:
        x_min, y_min, x_max, y_max = self._bounds
        return math.isfinite(x) and math.isfinite(y) and x_min <= x <= x_max and y_min <= y <= y_max

    def _to_cells(self, xy: NDArray[np.float64]) -> NDArray[np.float64]:
        """World (x, y) rows to cell units (u along columns, v along rows)."""
        x_min, y_min, _, _ = self._bounds
        return np.asarray((xy[:, :2] - np.array([x_min, y_min])) / self._res, dtype=np.float64)


def _flat_parts(geom: BaseGeometry) -> list[BaseGeometry]:
    """Polygons, lines and points of a possibly nested collection."""
    parts = list(shapely.get_parts(geom))
    if any(p.geom_type in ("MultiPolygon", "MultiLineString", "MultiPoint", "GeometryCollection") for p in parts):
        return [q for p in parts for q in _flat_parts(p)]
    return [p for p in parts if not p.is_empty]


def _touched_cells(p0: NDArray[np.float64], p1: NDArray[np.float64]) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """(rows, cols), with repeats, of every cell whose closed square meets one of the segments p0[i]-p1[i].

    Points are in cell units (u, v). A segment enters and leaves every cell it meets through a point where it
    crosses a grid line, or else ends inside the cell; so the cells on both sides of each crossing, plus the
    cells of the two ends, each point widened by _EDGE_EPS, are exactly the cells it meets. All in numpy.
    """
    n = len(p0)
    d = p1 - p0
    rows: list[NDArray[np.intp]] = []
    cols: list[NDArray[np.intp]] = []
    for p in (p0, p1):
        lo = np.floor(p - _EDGE_EPS).astype(np.intp)
        hi = np.floor(p + _EDGE_EPS).astype(np.intp)
        cols += [lo[:, 0], hi[:, 0], lo[:, 0], hi[:, 0]]
        rows += [lo[:, 1], lo[:, 1], hi[:, 1], hi[:, 1]]
    for axis in (0, 1):  # crossings of the lines u = k (axis 0), then v = k (axis 1)
        first = np.ceil(np.minimum(p0[:, axis], p1[:, axis]))
        last = np.floor(np.maximum(p0[:, axis], p1[:, axis]))
        counts = np.where(d[:, axis] != 0, np.maximum(last - first + 1, 0), 0).astype(np.intp)
        total = int(counts.sum())
        if not total:
            continue
        edge = np.repeat(np.arange(n), counts)
        line = first[edge] + (np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts))
        other = p0[edge, 1 - axis] + (line - p0[edge, axis]) / d[edge, axis] * d[edge, 1 - axis]
        across = [line.astype(np.intp) - 1, line.astype(np.intp)] * 2
        along = [np.floor(other - _EDGE_EPS).astype(np.intp)] * 2 + [np.floor(other + _EDGE_EPS).astype(np.intp)] * 2
        (cols if axis == 0 else rows).extend(across)
        (rows if axis == 0 else cols).extend(along)
    return np.concatenate(rows), np.concatenate(cols)


def _nearest_cell(grid: OccupancyGrid, candidates: NDArray[np.bool_], point: Point2) -> tuple[int, int] | None:
    """The candidate cell whose centre is nearest (Euclidean) to point, or None if there is none."""
    rows, cols = np.nonzero(candidates)
    if len(rows) == 0:
        return None
    x_min, y_min, _, _ = grid.bounds
    res = grid.resolution_m
    dist2 = (x_min + (cols + 0.5) * res - point[0]) ** 2 + (y_min + (rows + 0.5) * res - point[1]) ** 2
    i = int(np.argmin(dist2))
    return int(rows[i]), int(cols[i])


def plan_path(grid: OccupancyGrid, start: Point2, goal: Point2) -> list[Point2]:
    """A shortest 8-connected grid path from start to goal, shortened by line of sight, as world points.

    The path begins at start. If start lies in an occupied cell (the robot pressed against an inflated
    obstacle) it first heads for the nearest free cell. It ends at goal if goal's cell is free; otherwise
    at the nearest free cell to goal that can be reached, so a goal on a desk still brings the robot close.
    Raises NoPath if start or goal is outside the grid, the grid has no free cell, or goal is walled off.
    """
    start = (float(start[0]), float(start[1]))
    goal = (float(goal[0]), float(goal[1]))
    why = f"no path from start {start} to goal {goal}"
    occupied = grid.occupied
    for name, p in (("start", start), ("goal", goal)):
        if not grid._in_bounds(*p):
            raise NoPath(f"{why}: {name} {p} is outside the grid bounds {grid.bounds}")

    free = ~occupied
    start_cell = grid._cell_within(*start)
    if occupied[start_cell]:
        nearest = _nearest_cell(grid, free, start)
        if nearest is None:
            raise NoPath(f"{why}: every cell of the grid is occupied")
        start_cell = nearest
    # A diagonal step needs both orthogonal neighbours free, so reachability is exactly 4-connectivity:
    # one labelling answers "reachable?" before any search, which would otherwise flood the whole region.
    _, labels = cv2.connectedComponents(free.astype(np.uint8), connectivity=4)
    reachable = labels == labels[start_cell]
    goal_cell = grid._cell_within(*goal)
    goal_free = bool(free[goal_cell])
    if goal_free:
        if not reachable[goal_cell]:
            raise NoPath(f"{why}: goal's free region is walled off from start's")
    else:
        nearest = _nearest_cell(grid, reachable, goal)
        assert nearest is not None  # start_cell itself is reachable
        goal_cell = nearest

    cells = _astar(occupied, start_cell, goal_cell)
    # A last row or column may stick out past the bounds; its centre is moved in, staying in the cell.
    _, _, x_max, y_max = grid.bounds
    centres = (grid.centre_of(r, c) for r, c in cells)
    points = [start, *((min(x, x_max), min(y, y_max)) for x, y in centres)]
    if goal_free:
        points.append(goal)
    return _dedupe(_smooth(grid, points))


def _astar(occupied: NDArray[np.bool_], start: tuple[int, int], goal: tuple[int, int]) -> list[tuple[int, int]]:
    """Cells of a shortest path (octile costs), start and goal included; goal must be reachable.

    Flat indices into a grid padded with one ring of occupied cells, so neighbours need no bounds checks.
    """
    width = occupied.shape[1] + 2
    # state: 0 free, 1 occupied, 2 closed (expanded).
    state = bytearray(np.pad(occupied, 1, constant_values=True).astype(np.uint8).tobytes())
    size = len(state)
    rr, cc = np.divmod(np.arange(size), width)
    dr = np.abs(rr - (goal[0] + 1))
    dc = np.abs(cc - (goal[1] + 1))
    # Octile distance with the same integer costs: consistent, so the first time a cell is expanded is optimal.
    h: list[int] = (_ORTHO * np.maximum(dr, dc) + (_DIAG - _ORTHO) * np.minimum(dr, dc)).tolist()
    w = width
    # (offset, cost, orthogonal offset 1, orthogonal offset 2); 0, 0 for orthogonal steps.
    steps = (
        (1, _ORTHO, 0, 0),
        (-1, _ORTHO, 0, 0),
        (w, _ORTHO, 0, 0),
        (-w, _ORTHO, 0, 0),
        (w + 1, _DIAG, w, 1),
        (w - 1, _DIAG, w, -1),
        (-w + 1, _DIAG, -w, 1),
        (-w - 1, _DIAG, -w, -1),
    )
    src = (start[0] + 1) * w + start[1] + 1
    dst = (goal[0] + 1) * w + goal[1] + 1
    unseen = 1 << 62
    g = [unseen] * size
    parent = [-1] * size
    g[src] = 0
    heap: list[tuple[int, int, int]] = [(h[src], h[src], src)]
    pop, push = heapq.heappop, heapq.heappush
    while heap:
        _, _, cur = pop(heap)
        if cur == dst:
            break
        if state[cur] == 2:
            continue
        state[cur] = 2
        g_cur = g[cur]
        for off, cost, o1, o2 in steps:
            nxt = cur + off
            if state[nxt]:
                continue
            if o1 and (state[cur + o1] == 1 or state[cur + o2] == 1):
                continue  # a diagonal step would cut (or graze) an occupied cell's corner
            g_new = g_cur + cost
            if g_new < g[nxt]:
                g[nxt] = g_new
                parent[nxt] = cur
                h_nxt = h[nxt]
                # Ties on f go to the node nearer the goal: far fewer expansions on open floor.
                push(heap, (g_new + h_nxt, h_nxt, nxt))
    else:
        raise AssertionError("A* exhausted a region the labelling called connected")
    path = [dst]
    while path[-1] != src:
        path.append(parent[path[-1]])
    path.reverse()
    return [(i // w - 1, i % w - 1) for i in path]


def _dedupe(points: list[Point2]) -> list[Point2]:
    out = [points[0]]
    for p in points[1:]:
        if p != out[-1]:
            out.append(p)
    return out


def _smooth(grid: OccupancyGrid, points: list[Point2]) -> list[Point2]:
    """Drop every waypoint the previous kept one can see past: a waypoint is kept only when the straight
    segment from the last kept one to the waypoint after it crosses a non-free cell."""
    if len(points) <= 2:
        return points
    kept = [points[0]]
    for k in range(1, len(points) - 1):
        if not grid.segment_is_free(kept[-1], points[k + 1]):
            kept.append(points[k])
    kept.append(points[-1])
    return kept

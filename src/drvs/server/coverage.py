"""What part of a request's region no camera asked sees (`DetectionReply.uncovered`): every
answer carries it, so that a robot never reads unseen floor as "nothing there"."""

from __future__ import annotations

from collections.abc import Sequence

import shapely
from shapely.geometry import Polygon

#: Uncovered parts smaller than this (m²) are slivers along field-of-view edges, not reported.
MIN_UNCOVERED_M2 = 0.01


def uncovered(region: Polygon, fields_of_view: Sequence[Polygon]) -> list[Polygon]:
    """The parts of `region` that none of `fields_of_view` sees, each a polygon without holes (the
    wire's polygons have none: a part with a hole some camera sees is cut in pieces around it)."""
    if not fields_of_view:
        unseen = region
    elif any(fov.covers(region) for fov in fields_of_view):
        return []  # the common case: one camera sees it all
    else:
        unseen = shapely.difference(region, _union(tuple(fields_of_view)))
    parts: list[Polygon] = []
    for part in shapely.get_parts(unseen):
        if isinstance(part, Polygon) and part.area >= MIN_UNCOVERED_M2:
            parts.extend(p for p in _without_holes(part) if p.area >= MIN_UNCOVERED_M2)
    return parts


#: The union of the fields of view of a set of cameras, kept by their ids (the polygons held, so
#: that the ids stay theirs): requests to the same cameras come again and again.
_unions: dict[tuple[int, ...], tuple[tuple[Polygon, ...], Polygon]] = {}
UNION_CACHE_SIZE = 256


def _union(fields_of_view: tuple[Polygon, ...]) -> Polygon:
    key = tuple(map(id, fields_of_view))
    hit = _unions.get(key)
    if hit is not None and all(a is b for a, b in zip(hit[0], fields_of_view, strict=True)):
        return hit[1]
    union = shapely.union_all(list(fields_of_view))
    shapely.prepare(union)
    if len(_unions) >= UNION_CACHE_SIZE:
        del _unions[next(iter(_unions))]
    _unions[key] = (fields_of_view, union)
    return union


def _without_holes(polygon: Polygon) -> list[Polygon]:
    """`polygon` as pieces without holes, the same area: cut across its first hole, again until none."""
    if not polygon.interiors:
        return [polygon]
    x0, y0, x1, y1 = polygon.bounds
    hx0, _, hx1, _ = polygon.interiors[0].bounds
    cut = (hx0 + hx1) / 2  # inside the hole's x-range: each side keeps it as a notch, not a hole
    pieces: list[Polygon] = []
    for side in (shapely.clip_by_rect(polygon, x0, y0, cut, y1), shapely.clip_by_rect(polygon, cut, y0, x1, y1)):
        for part in shapely.get_parts(side):
            if isinstance(part, Polygon) and not part.is_empty:
                pieces.extend(_without_holes(part))
    return pieces

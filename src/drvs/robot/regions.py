"""Floor regions as robot code gives them (a shapely Polygon, a box, a list of points), validated,
and the client's cache of the ones it built and encoded."""

from __future__ import annotations

import collections
from collections.abc import Iterable, Sequence
from typing import Any, TypeAlias

from shapely.geometry import Polygon

from drvs.core.errors import InvalidArgument
from drvs.core.geometry import box_region, polygon_region
from drvs.v1 import geometry_pb2
from drvs.wire.convert import region_to_pb

#: Regions a client keeps built and encoded, by the value robot code passed.
REGION_CACHE_SIZE = 256

#: A floor region in metres: a shapely Polygon, a box (x0, y0, x1, y1), or a list of [x, y] points.
RegionLike: TypeAlias = "Polygon | Sequence[float] | Sequence[Sequence[float]]"


REGION_EXPECTED = "region: expected a shapely Polygon, a box (x0, y0, x1, y1) or a list of [x, y] points"


def as_region(region: RegionLike) -> Polygon:
    """A shapely polygon, a box (x0, y0, x1, y1), or a list of [x, y] points (metres) as a validated Polygon."""
    if isinstance(region, Polygon):
        return polygon_region(list(region.exterior.coords), "region")
    if isinstance(region, (str, bytes)) or not isinstance(region, Iterable):
        raise InvalidArgument(f"{REGION_EXPECTED}, got {type(region).__name__}")
    items: list[Any] = list(region)
    if len(items) == 4 and all(isinstance(v, (int, float)) for v in items):
        return box_region(*items)
    if items and all(isinstance(p, Sequence) for p in items):
        return polygon_region(items, "region")
    raise InvalidArgument(REGION_EXPECTED)


class _Regions:
    """Robot code asks about the same few regions again and again: each is built, validated and
    encoded once. Building the polygon and its wire form was a tenth of a request's CPU at 30 Hz.
    Keyed by the values robot code passed (a shapely Polygon by identity: it is immutable)."""

    def __init__(self, size: int = REGION_CACHE_SIZE) -> None:
        self._size = size
        self._cache: collections.OrderedDict[Any, tuple[Any, Polygon, geometry_pb2.Region]] = collections.OrderedDict()

    @staticmethod
    def _key(region: RegionLike) -> Any:
        if isinstance(region, Polygon):
            return ("polygon", id(region))
        try:
            key = tuple(tuple(p) if isinstance(p, Sequence) else p for p in region)
            hash(key)
        except TypeError:
            return None
        return key

    def get(self, region: RegionLike) -> tuple[Polygon, geometry_pb2.Region]:
        key = self._key(region)
        hit = self._cache.get(key) if key is not None else None
        if hit is not None and (not isinstance(region, Polygon) or hit[0] is region):
            self._cache.move_to_end(key)
            return hit[1], hit[2]
        polygon = as_region(region)  # a bad region raises here, every time, and is not kept
        encoded = region_to_pb(polygon)
        if key is not None:
            self._cache[key] = (region, polygon, encoded)
            if len(self._cache) > self._size:
                self._cache.popitem(last=False)
        return polygon, encoded

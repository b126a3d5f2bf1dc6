"""The server's camera registry: fields of view in a spatial index, held by leases. Pure logic."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import shapely
from shapely import STRtree
from shapely.geometry import Polygon

from drvs.errors import InvalidArgument, NotFound
from drvs.geometry import FieldOfView, Homography
from drvs.model import check_id
from drvs.net import parse_address

DEFAULT_LEASE_TTL_S = 10.0
#: Regions whose overlapping cameras are remembered until the registry's next change, by count and
#: by the regions' points (the cache holds the regions alive: a byte budget, not only a count).
ROUTE_CACHE_SIZE = 1024
ROUTE_CACHE_POINTS = 64 * 1024


@dataclass(frozen=True)
class CameraEntry:
    camera_id: str
    address: str
    field_of_view: Polygon
    detector_kinds: frozenset[str]
    homography: Homography
    image_size: tuple[int, int]


class Registry:
    """Cameras by id, with an STRtree over their fields of view rebuilt lazily after changes.

    Lookups are O(log n + k) in the number of cameras. Registrations are rare next to lookups, so
    the (immutable) STRtree is rebuilt on the first lookup after one; leases live apart from the
    index, so heartbeats never touch it. Robots ask about the same regions again and again, and
    `drvs.convert.region_from_pb` hands out one polygon object per distinct region, so the cameras
    a region object overlaps are also remembered, until the next registration change.
    """

    def __init__(self, lease_ttl_s: float = DEFAULT_LEASE_TTL_S, clock: Callable[[], float] = time.monotonic) -> None:
        if not lease_ttl_s > 0:
            raise ValueError(f"lease_ttl_s must be > 0, got {lease_ttl_s}")
        self.lease_ttl_s = lease_ttl_s
        self._clock = clock
        self._entries: dict[str, CameraEntry] = {}
        self._expires: dict[str, float] = {}
        self._tree: STRtree | None = None
        self._tree_entries: list[CameraEntry] = []
        self._fovs: np.ndarray = np.array([], dtype=object)
        # id(region) -> (region, the cameras it overlaps by camera id); the region is held, so
        # its id is not reused while the entry lives.
        self._routes: dict[int, tuple[Polygon, list[CameraEntry], int]] = {}
        self._route_points = 0

    def __len__(self) -> int:
        return len(self._entries)

    def __contains__(self, camera_id: object) -> bool:
        return camera_id in self._entries

    def get(self, camera_id: str) -> CameraEntry:
        try:
            return self._entries[camera_id]
        except KeyError:
            raise NotFound(f"camera_id: {camera_id!r} is not registered") from None

    def register(
        self,
        camera_id: str,
        address: str,
        homography: Homography,
        image_size: tuple[int, int],
        detector_kinds: frozenset[str] | set[str],
        max_range_m: float,
    ) -> CameraEntry:
        """Validate everything first, then add or replace the entry (replacing renews the lease)."""
        check_id(camera_id, "camera_id")
        parse_address(address, "address")
        if not detector_kinds:
            raise InvalidArgument("detector_kinds: empty; a camera must run at least one detector")
        for kind in detector_kinds:
            check_id(kind, "detector_kinds")
        fov = FieldOfView.compute(homography, image_size, max_range_m)
        entry = CameraEntry(
            camera_id=camera_id,
            address=address,
            field_of_view=fov.floor,
            detector_kinds=frozenset(detector_kinds),
            homography=homography,
            image_size=image_size,
        )
        self._entries[camera_id] = entry
        self._expires[camera_id] = self._clock() + self.lease_ttl_s
        self._tree = None
        return entry

    def renew(self, camera_id: str) -> CameraEntry:
        entry = self.get(camera_id)
        now = self._clock()
        if self._expires[camera_id] <= now:
            self.remove(camera_id)
            raise NotFound(f"camera_id: {camera_id!r}'s lease expired; register again")
        self._expires[camera_id] = now + self.lease_ttl_s
        return entry

    def remove(self, camera_id: str) -> CameraEntry:
        entry = self._entries.pop(camera_id, None)
        if entry is None:
            raise NotFound(f"camera_id: {camera_id!r} is not registered")
        del self._expires[camera_id]
        self._tree = None
        return entry

    def expire(self) -> list[CameraEntry]:
        """Drop every entry whose lease has run out; returns them."""
        now = self._clock()
        gone = [self._entries[cid] for cid, t in self._expires.items() if t <= now]
        for entry in gone:
            del self._entries[entry.camera_id]
            del self._expires[entry.camera_id]
        if gone:
            self._tree = None
        return gone

    def is_live(self, camera_id: str) -> bool:
        return self._expires.get(camera_id, 0.0) > self._clock()

    def cameras(self) -> list[CameraEntry]:
        return sorted((e for e in self._entries.values() if self.is_live(e.camera_id)), key=lambda e: e.camera_id)

    def cameras_seeing(self, region: Polygon, kind: str | None = None) -> list[CameraEntry]:
        """Live cameras whose field of view meets `region` with positive area (and run `kind`)."""
        now = self._clock()
        return [
            e
            for e in self._overlapping(region)
            if self._expires.get(e.camera_id, 0.0) > now and (kind is None or kind in e.detector_kinds)
        ]

    def _overlapping(self, region: Polygon) -> list[CameraEntry]:
        if self._tree is None:
            self._tree_entries = list(self._entries.values())
            self._fovs = np.array([e.field_of_view for e in self._tree_entries], dtype=object)
            self._tree = STRtree(self._fovs)
            self._routes.clear()
            self._route_points = 0
        known = self._routes.get(id(region))
        if known is not None and known[0] is region:
            return known[1]
        found: list[CameraEntry] = []
        if self._tree_entries:
            candidates = np.sort(self._tree.query(region, predicate="intersects"))
            if len(candidates):
                # Positive-area overlap of two polygons is exactly "their interiors meet" (DE-9IM
                # T********): a relate test, cheaper than building each intersection to measure it.
                overlaps = shapely.relate_pattern(self._fovs[candidates], region, "T********")
                hits = (self._tree_entries[i] for i, hit in zip(candidates, overlaps, strict=True) if hit)
                found = sorted(hits, key=lambda e: e.camera_id)
        points = int(shapely.get_num_coordinates(region))
        while self._routes and (
            len(self._routes) >= ROUTE_CACHE_SIZE or self._route_points + points > ROUTE_CACHE_POINTS
        ):
            self._route_points -= self._routes.pop(next(iter(self._routes)))[2]  # the oldest
        if points <= ROUTE_CACHE_POINTS:
            self._routes[id(region)] = (region, found, points)
            self._route_points += points
        return found

    def remaining_s(self, camera_id: str) -> float:
        return max(0.0, self._expires.get(camera_id, 0.0) - self._clock())

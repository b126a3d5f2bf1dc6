"""The server's camera registry: fields of view in a spatial index, held by leases. Pure logic."""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import shapely
from shapely.geometry import Polygon

from drvs.core.errors import FailedPrecondition, InvalidArgument, NotFound, ResourceExhausted
from drvs.core.geometry import FieldOfView, Homography
from drvs.core.mobile import DEFAULT_MAX_SPEED_MPS, MAX_SPEED_MPS, check_pose_on_floor, check_speed, move_polygon
from drvs.core.model import DEFAULT_FRAME, Pose2, check_frame, check_id
from drvs.core.net import parse_address

# Claims (who holds a camera id) live in drvs.server.claims; their names stay importable from here.
from drvs.server.claims import DEFAULT_GRACE_S as DEFAULT_GRACE_S
from drvs.server.claims import DEFAULT_MAX_CAMERAS_PER_IDENTITY as DEFAULT_MAX_CAMERAS_PER_IDENTITY
from drvs.server.claims import Claim as Claim
from drvs.server.claims import Claims as Claims

DEFAULT_LEASE_TTL_S = 10.0
#: The largest field of view a registration may claim: sized for a building, so one registration
#: cannot claim a whole site and receive every robot's requests.
DEFAULT_MAX_FOV_RANGE_M = 100.0
DEFAULT_MAX_FOV_AREA_M2 = 5000.0
#: Detector kinds one camera may register (DRVS has five).
MAX_DETECTOR_KINDS = 16
#: Regions whose overlapping cameras are remembered until the registry's next change, by count and
#: by the regions' points (the cache holds the regions alive: a byte budget, not only a count).
ROUTE_CACHE_SIZE = 1024
ROUTE_CACHE_POINTS = 64 * 1024
#: Side of the grid cells that index mobile cameras' fields of view, metres (about a camera's range).
MOBILE_CELL_M = 8.0
#: Side of the finest cells of the fixed cameras' grid, metres; cells double in size level by level,
#: and a camera sits in one cell of the finest level whose cells are at least as wide as its view.
STATIC_CELL_M = 8.0
#: A lookup probes the grid's cells while they number at most one per this many fixed cameras (and
#: at least SCAN_MIN_CELLS); a larger region is cheaper to test against every camera's bounds at once.
SCAN_CAMERAS_PER_CELL = 16
SCAN_MIN_CELLS = 64
#: Up to this many candidates go straight to the relate test (GEOS rejects a polygon whose bounds
#: miss the region at once); more are first filtered by their bounds, vectorised.
PREFILTER_CANDIDATES = 32
#: A mobile camera's field of view is routed this long after a pose update, seconds (default and
#: cap), and pose updates closer together than MIN_POSE_INTERVAL_S are refused.
DEFAULT_POSE_LEASE_S = 1.0
MAX_POSE_LEASE_S = 10.0
DEFAULT_MIN_POSE_INTERVAL_S = 0.1
_EMPTY = Polygon()


@dataclass(frozen=True)
class CameraEntry:
    camera_id: str
    address: str
    field_of_view: Polygon
    detector_kinds: frozenset[str]
    homography: Homography
    image_size: tuple[int, int]
    #: A camera on a robot: `homography` maps to the robot's base frame and `field_of_view` is
    #: where its last pose puts it (empty before the first pose, or when it sees no floor).
    mobile: bool = False
    #: The floor plan its field of view is in; requests are routed to it only in this frame.
    frame: str = DEFAULT_FRAME


@dataclass
class MobileState:
    """A mobile camera's moving part, kept apart from the static index."""

    #: The field of view in the robot's base frame; None when the mount sees no floor.
    base_fov: Polygon | None
    #: Why it is never routed ("" when it can be): its mount sees no floor.
    no_floor: str
    pose_lease_s: float
    #: The fastest its robot moves (m/s): a pose update that implies more is refused.
    max_speed_mps: float = DEFAULT_MAX_SPEED_MPS
    pose: Pose2 | None = None
    pose_time_unix: float = 0.0
    #: Registry clock: when the last pose arrived (-inf: never), and until when it routes.
    received: float = -math.inf
    routed_until: float = -math.inf
    #: The routed field of view's bounds (map frame), for the lookup's vectorised prefilter.
    bounds: tuple[float, float, float, float] = (math.nan, math.nan, math.nan, math.nan)


class StaticIndex:
    """Fixed cameras' fields of view in a grid per frame, changed in place by each registration.

    An STRtree is immutable: with leases lapsing and cameras re-registering somewhere on a campus
    every second, rebuilding it whole (70 ms at 100 000 cameras) would land on nearly every lookup.
    Here a change costs a few dict and list operations and a lookup never rebuilds anything, so
    every lookup is correct at once and none pays for another's change. Each camera sits in exactly
    one cell: the one holding its bounds' lower corner, at the finest level whose cells are at least
    as wide as its bounds (STATIC_CELL_M, doubling per level), so it reaches at most one cell further
    up and right, and a lookup probes the region's cells plus one row and column below and left. The
    bounds and fields of view sit in numpy arrays by slot, so candidates are filtered vectorised.
    """

    def __init__(self) -> None:
        #: frame -> level -> cell key -> slots.
        self._grids: dict[str, dict[int, dict[int, list[int]]]] = {}
        self._slot_of: dict[str, int] = {}
        self._entries: list[CameraEntry | None] = []
        self._free: list[int] = []
        self._bounds: np.ndarray = np.full((0, 4), np.nan)
        self._fovs: np.ndarray = np.empty(0, dtype=object)
        #: Changes so far (adds and discards): the index is never rebuilt, only changed.
        self.changes = 0

    def __len__(self) -> int:
        return len(self._slot_of)

    def add(self, entry: CameraEntry) -> None:
        """Index a fixed camera (replacing any entry under its id)."""
        self.discard(entry.camera_id)
        if self._free:
            slot = self._free.pop()
            self._entries[slot] = entry
        else:
            slot = len(self._entries)
            self._entries.append(entry)
            if slot >= len(self._fovs):  # doubling: a copy now and then, amortised per change
                grown = max(64, 2 * len(self._fovs))
                self._bounds = np.concatenate([self._bounds, np.full((grown - len(self._fovs), 4), np.nan)])
                self._fovs = np.concatenate([self._fovs, np.empty(grown - len(self._fovs), dtype=object)])
        self._slot_of[entry.camera_id] = slot
        self._fovs[slot] = entry.field_of_view
        self.changes += 1
        if entry.field_of_view.is_empty:  # no bounds (nan): never a candidate, as in an STRtree
            return
        bounds = entry.field_of_view.bounds
        self._bounds[slot] = bounds
        level, key = _static_cell(bounds)
        self._grids.setdefault(entry.frame, {}).setdefault(level, {}).setdefault(key, []).append(slot)

    def discard(self, camera_id: str) -> None:
        slot = self._slot_of.pop(camera_id, None)
        if slot is None:
            return
        entry = self._entries[slot]
        assert entry is not None
        bounds = self._bounds[slot]
        if not math.isnan(bounds[0]):
            level, key = _static_cell(tuple(float(b) for b in bounds))  # type: ignore[arg-type]
            grid = self._grids[entry.frame]
            cells = grid[level]
            held = cells[key]
            held.remove(slot)
            if not held:
                del cells[key]
                if not cells:
                    del grid[level]
                    if not grid:
                        del self._grids[entry.frame]
        self._bounds[slot] = np.nan
        self._fovs[slot] = None
        self._entries[slot] = None
        self._free.append(slot)
        self.changes += 1

    def overlapping(self, region: Polygon, frame: str | None) -> list[CameraEntry]:
        """Cameras of `frame` (None: every frame) whose field of view meets `region` with positive
        area, by camera id."""
        if not self._slot_of:
            return []
        x0, y0, x1, y1 = shapely.bounds(region).tolist()
        if math.isnan(x0):  # an empty region
            return []
        grids = [g for g in (self._grids.get(frame),) if g] if frame is not None else list(self._grids.values())
        spans = []
        probes = 0
        for grid in grids:
            for level, cells in grid.items():
                size = math.ldexp(STATIC_CELL_M, level)
                i0, j0 = math.floor(x0 / size) - 1, math.floor(y0 / size) - 1
                i1, j1 = math.floor(x1 / size), math.floor(y1 / size)
                spans.append((cells, i0, j0, i1, j1))
                probes += min((i1 - i0 + 1) * (j1 - j0 + 1), len(cells))
        if probes > max(SCAN_MIN_CELLS, len(self._slot_of) // SCAN_CAMERAS_PER_CELL):
            b = self._bounds
            candidates = np.flatnonzero((b[:, 0] <= x1) & (b[:, 2] >= x0) & (b[:, 1] <= y1) & (b[:, 3] >= y0))
        else:
            slots: list[int] = []
            for cells, i0, j0, i1, j1 in spans:
                if (i1 - i0 + 1) * (j1 - j0 + 1) > len(cells):  # fewer cells held than under the region
                    for key, ids in cells.items():
                        i, j = divmod(key + _HALF, _KEY)
                        j -= _HALF
                        if i0 <= i <= i1 and j0 <= j <= j1:
                            slots += ids
                else:
                    for i in range(i0, i1 + 1):
                        base = i * _KEY
                        for j in range(j0, j1 + 1):
                            here = cells.get(base + j)
                            if here:
                                slots += here
            if not slots:
                return []
            candidates = np.array(slots, dtype=np.intp)
            if len(candidates) > PREFILTER_CANDIDATES:
                b = self._bounds[candidates]
                candidates = candidates[(b[:, 0] <= x1) & (b[:, 2] >= x0) & (b[:, 1] <= y1) & (b[:, 3] >= y0)]
        if not len(candidates):
            return []
        # Positive-area overlap of two polygons is exactly "their interiors meet" (DE-9IM T********):
        # a relate test, cheaper than building each intersection to measure it.
        hits = candidates[shapely.relate_pattern(self._fovs[candidates], region, "T********")]
        entries = self._entries
        found = [e for e in (entries[s] for s in hits) if e is not None and (frame is None or e.frame == frame)]
        return sorted(found, key=lambda e: e.camera_id)


class Registry:
    """Cameras by id, fixed ones in a grid index of their fields of view changed per registration.

    Each registration change updates the index in place (StaticIndex: no rebuild, so a lookup costs
    the same however often cameras come and go); leases live apart from the index, so heartbeats
    never touch it. Robots ask about the same regions again and again, and
    `drvs.wire.convert.region_from_pb` hands out one polygon object per distinct region, so the cameras
    a region object overlaps are also remembered, until the next registration change.
    """

    def __init__(
        self,
        lease_ttl_s: float = DEFAULT_LEASE_TTL_S,
        clock: Callable[[], float] = time.monotonic,
        *,
        max_fov_range_m: float = DEFAULT_MAX_FOV_RANGE_M,
        max_fov_area_m2: float = DEFAULT_MAX_FOV_AREA_M2,
        pose_lease_s: float = DEFAULT_POSE_LEASE_S,
        max_pose_lease_s: float = MAX_POSE_LEASE_S,
        min_pose_interval_s: float = DEFAULT_MIN_POSE_INTERVAL_S,
    ) -> None:
        if not (0 < pose_lease_s <= max_pose_lease_s and min_pose_interval_s >= 0):
            raise ValueError("pose_lease_s must be in (0, max_pose_lease_s] and min_pose_interval_s >= 0")
        self.pose_lease_s = pose_lease_s
        self.max_pose_lease_s = max_pose_lease_s
        self.min_pose_interval_s = min_pose_interval_s
        #: Mobile cameras by id: never in the STRtree, checked one by one at each lookup.
        self._mobile: dict[str, MobileState] = {}
        # Mobile cameras by the MOBILE_CELL_M grid cells their routed field of view's bounds cover:
        # a pose update moves one camera between a few cells, and a lookup reads the cells under
        # the region, so neither costs more with more cameras elsewhere.
        self._mobile_cells: dict[tuple[int, int], set[str]] = {}
        if not lease_ttl_s > 0:
            raise ValueError(f"lease_ttl_s must be > 0, got {lease_ttl_s}")
        if not (max_fov_range_m > 0 and max_fov_area_m2 > 0):
            raise ValueError("max_fov_range_m and max_fov_area_m2 must be > 0")
        self.lease_ttl_s = lease_ttl_s
        self.max_fov_range_m = max_fov_range_m
        self.max_fov_area_m2 = max_fov_area_m2
        self._clock = clock
        self._entries: dict[str, CameraEntry] = {}
        self._expires: dict[str, float] = {}
        #: The fixed cameras' index (named as the STRtree it replaced, which tests and the mobile
        #: benchmark check pose updates never touch).
        self._tree = StaticIndex()
        # (id(region), frame) -> (region, the cameras of that frame it overlaps by camera id, its
        # points); the region is held, so its id is not reused while the entry lives.
        self._routes: dict[tuple[int, str | None], tuple[Polygon, list[CameraEntry], int]] = {}
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
        *,
        mobile: bool = False,
        pose_lease_s: float = 0.0,
        frame: str = DEFAULT_FRAME,
        max_speed_mps: float = 0.0,
    ) -> CameraEntry:
        """Validate everything first, then add or replace the entry (replacing renews the lease).

        A mobile camera's `homography` maps to its robot's base frame: its field of view there is
        computed once, with the same limits; one that sees no floor stays registered but is never
        routed (`unroutable` says why). It is routed only while a pose update is fresh."""
        return self.store(
            *self.check(
                camera_id, address, homography, image_size, detector_kinds, max_range_m,
                mobile=mobile, pose_lease_s=pose_lease_s, frame=frame, max_speed_mps=max_speed_mps,
            )
        )  # fmt: skip

    def check(
        self,
        camera_id: str,
        address: str,
        homography: Homography,
        image_size: tuple[int, int],
        detector_kinds: frozenset[str] | set[str],
        max_range_m: float,
        *,
        mobile: bool = False,
        pose_lease_s: float = 0.0,
        frame: str = DEFAULT_FRAME,
        max_speed_mps: float = 0.0,
    ) -> tuple[CameraEntry, MobileState | None]:
        """Every check of a registration, and the entry (and a mobile camera's state) it would
        make, with nothing stored (InvalidArgument naming the field)."""
        check_id(camera_id, "camera_id")
        frame = check_frame(frame)
        parse_address(address, "address")
        if not detector_kinds:
            raise InvalidArgument("detector_kinds: empty; a camera must run at least one detector")
        if len(detector_kinds) > MAX_DETECTOR_KINDS:
            raise InvalidArgument(f"detector_kinds: {len(detector_kinds)} kinds; at most {MAX_DETECTOR_KINDS}")
        for kind in detector_kinds:
            check_id(kind, "detector_kinds")
        if max_range_m > self.max_fov_range_m:
            raise InvalidArgument(
                f"max_range_m: {max_range_m:g} m is beyond this server's limit of {self.max_fov_range_m:g} m"
            )
        state: MobileState | None = None
        if mobile:
            if not (math.isfinite(pose_lease_s) and pose_lease_s >= 0):
                raise InvalidArgument(f"pose_lease_s: {pose_lease_s} must be >= 0 seconds (0: the server's default)")
            lease = min(pose_lease_s or self.pose_lease_s, self.max_pose_lease_s)
            if not (math.isfinite(max_speed_mps) and 0 <= max_speed_mps <= MAX_SPEED_MPS):
                raise InvalidArgument(f"max_speed_mps: {max_speed_mps} must be 0 (the default) to {MAX_SPEED_MPS:g}")
            try:
                base: Polygon | None = self.field_of_view(homography, image_size, max_range_m).floor
                no_floor = ""
            except InvalidArgument as exc:
                if "sees no floor" not in str(exc):
                    raise
                base, no_floor = None, str(exc)
            state = MobileState(base_fov=base, no_floor=no_floor, pose_lease_s=lease)
            state.max_speed_mps = max_speed_mps or DEFAULT_MAX_SPEED_MPS
            fov_floor = _EMPTY
        else:
            fov_floor = self.field_of_view(homography, image_size, max_range_m).floor
        entry = CameraEntry(
            camera_id=camera_id,
            address=address,
            field_of_view=fov_floor,
            detector_kinds=frozenset(detector_kinds),
            homography=homography,
            image_size=image_size,
            mobile=mobile,
            frame=frame,
        )
        return entry, state

    def store(self, entry: CameraEntry, state: MobileState | None = None) -> CameraEntry:
        """Add or replace a checked entry (`check`); its lease starts now."""
        camera_id = entry.camera_id
        was_static = camera_id in self._entries and camera_id not in self._mobile
        self._entries[camera_id] = entry
        self._expires[camera_id] = self._clock() + self.lease_ttl_s
        old = self._mobile.pop(camera_id, None)
        if old is not None:
            self._uncell(camera_id, old)
        if state is not None:
            self._mobile[camera_id] = state
        # A mobile camera alone never touches the static index.
        if state is None:
            self._tree.add(entry)
            self._static_changed()
        elif was_static:
            self._tree.discard(camera_id)
            self._static_changed()
        return entry

    def _static_changed(self) -> None:
        """Regions routed before a change to the fixed cameras are routed afresh."""
        self._routes.clear()
        self._route_points = 0

    def mobile_state(self, camera_id: str) -> MobileState | None:
        """A mobile camera's pose and routing state; None for a fixed (or unknown) camera."""
        return self._mobile.get(camera_id)

    def unroutable(self, camera_id: str) -> str:
        """Why the registry does not route to this camera now ("" when it does, or it is fixed)."""
        state = self._mobile.get(camera_id)
        if state is None:
            return ""
        if state.no_floor:
            return state.no_floor
        if state.pose is None:
            return "no pose yet"
        if state.routed_until <= self._clock():
            return (
                f"pose stale: the last came {self._clock() - state.received:.1f} s ago (lease {state.pose_lease_s:g} s)"
            )
        return ""

    def pose_age_s(self, camera_id: str) -> float:
        """Seconds since a mobile camera's last pose update arrived (inf before the first)."""
        state = self._mobile.get(camera_id)
        return math.inf if state is None or state.pose is None else self._clock() - state.received

    def update_pose(
        self, camera_id: str, pose: Pose2, pose_time_unix: float = 0.0, *, check_rate: bool = True
    ) -> CameraEntry:
        """A mobile camera's robot is at `pose` (map frame): its field of view moves there and is
        routed for its pose lease. Checks (all before any change): NOT_FOUND unknown or expired,
        FAILED_PRECONDITION a fixed camera, INVALID_ARGUMENT a pose that is not finite or off any
        floor, RESOURCE_EXHAUSTED sooner than min_pose_interval_s after the previous update.
        Never touches the static index."""
        entry = self.get(camera_id)
        if not self.is_live(camera_id):
            raise NotFound(f"camera_id: {camera_id!r}'s lease expired; register again")
        state = self._mobile.get(camera_id)
        if state is None:
            raise FailedPrecondition(f"camera_id: {camera_id!r} registered as a fixed camera; it has no pose")
        check_pose_on_floor(pose, "pose")
        if not math.isfinite(pose_time_unix):
            raise InvalidArgument(f"pose_time_unix: {pose_time_unix} is not a finite number")
        now = self._clock()
        if check_rate and now - state.received < self.min_pose_interval_s:
            raise ResourceExhausted(
                f"pose: camera {camera_id!r} updated {now - state.received:.3f} s ago; at most one update "
                f"every {self.min_pose_interval_s:g} s"
            )
        if check_rate:  # (a pose another server took was checked there)
            check_speed(camera_id, state.pose, pose, now - state.received, state.max_speed_mps)
        state.pose, state.pose_time_unix, state.received = pose, pose_time_unix, now
        state.routed_until = now + state.pose_lease_s
        fov = move_polygon(state.base_fov, pose) if state.base_fov is not None else _EMPTY
        self._uncell(camera_id, state)
        if not fov.is_empty:
            x0, y0, x1, y1 = fov.bounds
            state.bounds = (float(x0), float(y0), float(x1), float(y1))
            for cell in _cells(state.bounds):
                self._mobile_cells.setdefault(cell, set()).add(camera_id)
        entry = dataclasses.replace(entry, field_of_view=fov)
        self._entries[camera_id] = entry
        return entry

    def _uncell(self, camera_id: str, state: MobileState) -> None:
        if math.isnan(state.bounds[0]):
            return
        for cell in _cells(state.bounds):
            held = self._mobile_cells.get(cell)
            if held is not None:
                held.discard(camera_id)
                if not held:
                    del self._mobile_cells[cell]

    def _mobile_near(self, region: Polygon, now: float) -> list[CameraEntry]:
        """Live mobile cameras with a fresh pose whose field of view's bounds meet the region's.
        (Every lookup pays this: the region's bounds are read once, and a region over cells that
        hold no mobile camera costs a dict probe per cell.)"""
        x0, y0, x1, y1 = region.bounds
        cells = self._mobile_cells
        i0, j0 = math.floor(x0 / MOBILE_CELL_M), math.floor(y0 / MOBILE_CELL_M)
        i1, j1 = math.floor(x1 / MOBILE_CELL_M), math.floor(y1 / MOBILE_CELL_M)
        near: set[str] = set()
        if (i1 - i0 + 1) * (j1 - j0 + 1) > len(cells):  # a large region: read the cells that hold cameras
            for (i, j), ids in cells.items():
                if i0 <= i <= i1 and j0 <= j <= j1:
                    near |= ids
        else:
            for i in range(i0, i1 + 1):
                for j in range(j0, j1 + 1):
                    held = cells.get((i, j))
                    if held:
                        near |= held
        if not near:
            return []
        found = []
        for cid in near:
            state = self._mobile[cid]
            b = state.bounds
            fresh = state.routed_until > now and self._expires.get(cid, 0.0) > now
            if fresh and b[0] <= x1 and b[2] >= x0 and b[1] <= y1 and b[3] >= y0:
                found.append(self._entries[cid])
        return found

    def field_of_view(self, homography: Homography, image_size: tuple[int, int], max_range_m: float) -> FieldOfView:
        """The field of view a registration would get; INVALID_ARGUMENT when larger than allowed."""
        fov = FieldOfView.compute(homography, image_size, max_range_m)
        if fov.floor.area > self.max_fov_area_m2:
            raise InvalidArgument(
                f"field_of_view: {fov.floor.area:.0f} m² of floor is more than this server's limit of "
                f"{self.max_fov_area_m2:g} m² for one camera"
            )
        return fov

    def expires_at(self, camera_id: str) -> float:
        return self._expires.get(camera_id, 0.0)

    def renew(self, camera_id: str) -> CameraEntry:
        entry = self.get(camera_id)
        now = self._clock()
        if self._expires[camera_id] <= now:
            self.remove(camera_id)
            raise NotFound(f"camera_id: {camera_id!r}'s lease expired; register again")
        self._expires[camera_id] = now + self.lease_ttl_s
        return entry

    def hold(self, camera_id: str) -> None:
        """Keep `camera_id` until it is removed: its lease is kept elsewhere (a registry shared in
        etcd, whose lease expiry removes it on every server)."""
        self.get(camera_id)
        self._expires[camera_id] = math.inf

    def remove(self, camera_id: str) -> CameraEntry:
        entry = self._entries.pop(camera_id, None)
        if entry is None:
            raise NotFound(f"camera_id: {camera_id!r} is not registered")
        del self._expires[camera_id]
        state = self._mobile.pop(camera_id, None)
        if state is None:
            self._tree.discard(camera_id)
            self._static_changed()
        else:
            self._uncell(camera_id, state)
        return entry

    def expire(self) -> list[CameraEntry]:
        """Drop every entry whose lease has run out; returns them."""
        now = self._clock()
        gone = [self._entries[cid] for cid, t in self._expires.items() if t <= now]
        static_gone = False
        for entry in gone:
            del self._entries[entry.camera_id]
            del self._expires[entry.camera_id]
            state = self._mobile.pop(entry.camera_id, None)
            if state is None:
                self._tree.discard(entry.camera_id)
                static_gone = True
            else:
                self._uncell(entry.camera_id, state)
        if static_gone:
            self._static_changed()
        return gone

    def is_live(self, camera_id: str) -> bool:
        return self._expires.get(camera_id, 0.0) > self._clock()

    def cameras(self) -> list[CameraEntry]:
        return sorted((e for e in self._entries.values() if self.is_live(e.camera_id)), key=lambda e: e.camera_id)

    def kinds_served(self) -> set[str]:
        """Every object type (routing kind) some live camera serves."""
        now = self._clock()
        live = (e for e in self._entries.values() if self._expires.get(e.camera_id, 0.0) > now)
        return {kind for e in live for kind in e.detector_kinds}

    def cameras_seeing(
        self, region: Polygon, kind: str | None = None, frame: str | None = DEFAULT_FRAME
    ) -> list[CameraEntry]:
        """Live cameras of `frame` (None: of every frame) whose field of view meets `region` with
        positive area (and run `kind`)."""
        now = self._clock()
        found = [
            e
            for e in self._overlapping(region, frame)
            if self._expires.get(e.camera_id, 0.0) > now and (kind is None or kind in e.detector_kinds)
        ]
        if self._mobile:
            moving = [
                e
                for e in self._mobile_near(region, now)
                if (kind is None or kind in e.detector_kinds) and (frame is None or e.frame == frame)
            ]
            if moving:
                fovs = np.array([e.field_of_view for e in moving], dtype=object)
                hits = shapely.relate_pattern(fovs, region, "T********")
                found += [e for e, hit in zip(moving, hits, strict=True) if hit]
                found.sort(key=lambda e: e.camera_id)
        return found

    def _overlapping(self, region: Polygon, frame: str | None) -> list[CameraEntry]:
        key = (id(region), frame)
        known = self._routes.get(key)
        if known is not None and known[0] is region:
            return known[1]
        found = self._tree.overlapping(region, frame)
        points = int(shapely.get_num_coordinates(region))
        while self._routes and (
            len(self._routes) >= ROUTE_CACHE_SIZE or self._route_points + points > ROUTE_CACHE_POINTS
        ):
            self._route_points -= self._routes.pop(next(iter(self._routes)))[2]  # the oldest
        if points <= ROUTE_CACHE_POINTS:
            self._routes[key] = (region, found, points)
            self._route_points += points
        return found

    def remaining_s(self, camera_id: str) -> float:
        return max(0.0, self._expires.get(camera_id, 0.0) - self._clock())


def _cell_span(bounds: tuple[float, float, float, float]) -> tuple[int, int, int, int]:
    x0, y0, x1, y1 = (math.floor(v / MOBILE_CELL_M) for v in bounds)
    return x0, y0, x1, y1


def _cells(bounds: tuple[float, float, float, float]) -> list[tuple[int, int]]:
    """The MOBILE_CELL_M grid cells a box covers."""
    x0, y0, x1, y1 = _cell_span(bounds)
    return [(i, j) for i in range(x0, x1 + 1) for j in range(y0, y1 + 1)]


#: Cell keys: i * _KEY + j, one int (smaller than a tuple); exact while |j| < 2**31 cells (far
#: beyond the floor coordinates a homography can map to).
_KEY = 1 << 32
_HALF = 1 << 31


def _static_cell(bounds: tuple[float, float, float, float]) -> tuple[int, int]:
    """A fixed camera's level and cell key (see StaticIndex)."""
    x0, y0, x1, y1 = bounds
    width = max(x1 - x0, y1 - y0)
    level, size = 0, STATIC_CELL_M
    while size < width:
        level, size = level + 1, size * 2
    return level, math.floor(x0 / size) * _KEY + math.floor(y0 / size)

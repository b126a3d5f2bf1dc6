"""Routing: which cameras a request goes to, which are missing, and what floor nobody looks at.

The server's routing state lives here: cameras skipped after a failed forward (until they
heartbeat), cameras that left without deregistering (named missing for a while), and the cache of
uncovered parts of regions robots ask about again and again."""

from __future__ import annotations

import time
from collections import OrderedDict
from dataclasses import dataclass

import shapely
from shapely.geometry import Polygon

from drvs.core.errors import FailedPrecondition
from drvs.core.model import DetectionRequest
from drvs.server.coverage import uncovered
from drvs.server.registry import CameraEntry, Registry
from drvs.v1 import geometry_pb2
from drvs.wire.convert import polygon_to_pb

#: A camera whose lease ran out without it deregistering is remembered this long (at most MAX_LOST
#: of them): requests whose region it sees name it as missing until it registers again.
LOST_MEMORY_S = 3600.0
MAX_LOST = 1024
UNCOVERED_CACHE_SIZE = 256


@dataclass(frozen=True)
class MissingCamera:
    """A camera that sees a request's region and runs its detector, but is not asked."""

    camera_id: str
    code: str
    message: str
    field_of_view: Polygon


class Routing:
    """Plans requests over `registry`'s cameras, minus those skipped or lost; `warm_up_s`: how long
    after a start cameras registered with a previous run may not be back yet."""

    def __init__(self, registry: Registry, warm_up_s: float) -> None:
        self.registry = registry
        # Cameras whose last forward failed: skipped until their next heartbeat proves them alive.
        self.unreachable: set[str] = set()
        self.unreachable_why: dict[str, str] = {}
        # Cameras whose lease ran out without deregistering: id -> (entry, when, why).
        self.lost: OrderedDict[str, tuple[CameraEntry, float, str]] = OrderedDict()
        # ids of (region, fields of view asked and missing) -> (region, fields of view, unseen parts)
        self._uncovered_cache: dict[
            tuple[int, ...], tuple[Polygon, tuple[Polygon, ...], list[geometry_pb2.Polygon]]
        ] = {}
        self.warm_up_s = warm_up_s
        self.started_at = time.monotonic()

    def route(self, request: DetectionRequest) -> list[CameraEntry]:
        """The live cameras that see the request's region, run its detector and are reachable."""
        return self.plan(request)[0]

    def plan(self, request: DetectionRequest) -> tuple[list[CameraEntry], list[MissingCamera]]:
        """The cameras to ask, and those that see the region and run the detector but will not be
        asked: skipped after a failed forward, or gone without deregistering."""
        seeing = self.registry.cameras_seeing(request.region, request.kind, request.frame)
        if not self.unreachable and not self.lost:
            return seeing, []  # the common case costs nothing more
        cameras = [c for c in seeing if c.camera_id not in self.unreachable]
        missing = [
            MissingCamera(
                c.camera_id,
                "UNAVAILABLE",
                f"skipped until it heartbeats: {self.unreachable_why.get(c.camera_id, 'its last forward failed')}",
                c.field_of_view,
            )
            for c in seeing
            if c.camera_id in self.unreachable
        ]
        now = time.monotonic()
        x0, y0, x1, y1 = request.region.bounds
        for camera_id, (entry, since, why) in list(self.lost.items()):
            if camera_id in self.registry or now - since > LOST_MEMORY_S:
                del self.lost[camera_id]  # back (routed or refused as itself), or forgotten
                continue
            fx0, fy0, fx1, fy1 = entry.field_of_view.bounds  # cheap test first: most are far away
            if fx0 >= x1 or fx1 <= x0 or fy0 >= y1 or fy1 <= y0 or request.kind not in entry.detector_kinds:
                continue
            if entry.frame != request.frame:
                continue
            if shapely.relate_pattern(entry.field_of_view, request.region, "T********"):
                message = f"{why} {now - since:.0f} s ago"
                missing.append(MissingCamera(camera_id, "UNAVAILABLE", message, entry.field_of_view))
        return cameras, missing

    def refuse_unserved(self, request: DetectionRequest) -> None:
        """FailedPrecondition when cameras are up but none serves the request's object type: the
        robot hears that nobody can answer it, not an empty answer it may read as "nothing there".
        (With no camera up at all the answer stays empty, as the paper's protocol has it.)"""
        served = self.registry.kinds_served()
        if served and request.kind not in served:
            raise FailedPrecondition(
                f"filter_def: no camera serves {request.kind!r} (asked for {request.filter_def[:64]!r}); "
                f"the cameras serve {', '.join(sorted(served))}"
            )

    def uncovered(self, region: Polygon, cameras: list[CameraEntry]) -> list[geometry_pb2.Polygon]:
        """`coverage.uncovered`, encoded, kept per region object and cameras: robots ask about the
        same regions again and again (a stream sends a repeated region once)."""
        fovs = tuple(c.field_of_view for c in cameras)
        key = (id(region), *map(id, fovs))
        hit = self._uncovered_cache.get(key)
        if hit is not None and hit[0] is region and all(a is b for a, b in zip(hit[1], fovs, strict=True)):
            return hit[2]
        parts = [polygon_to_pb(part) for part in uncovered(region, [c.field_of_view for c in cameras])]
        if len(self._uncovered_cache) >= UNCOVERED_CACHE_SIZE:
            del self._uncovered_cache[next(iter(self._uncovered_cache))]
        self._uncovered_cache[key] = (region, fovs, parts)  # held: their ids stay theirs
        return parts

    def coverage_uncertain_s(self) -> float:
        """How much longer cameras registered with a previous run of the server may still be on
        their way back (0 once a lease has passed since the start)."""
        return max(0.0, self.started_at + self.warm_up_s - time.monotonic())

    def unreachable_now(self, camera_id: str, why: str) -> None:
        """A forward to it failed: skipped until it heartbeats."""
        self.unreachable.add(camera_id)
        self.unreachable_why[camera_id] = why

    def remember_lost(self, entry: CameraEntry, why: str) -> None:
        """It did not deregister: requests whose region it saw say it is missing (`plan`)."""
        self.lost[entry.camera_id] = (entry, time.monotonic(), why)
        while len(self.lost) > MAX_LOST:
            self.lost.popitem(last=False)

    def forget(self, camera_id: str) -> None:
        """It left routing: neither skipped nor lost any more."""
        self.unreachable.discard(camera_id)
        self.unreachable_why.pop(camera_id, None)
        self.lost.pop(camera_id, None)

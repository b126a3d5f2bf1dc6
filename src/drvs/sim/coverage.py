"""The simulated robot's coverage: where nobody looks, the way is not known to be clear.

A camera that stops answering (failed, skipped, gone, silent) leaves the floor only it saw unseen,
as does floor the answers say no camera sees; the robot slows down there (drvs.sim.robot). A mixin
of SimRobot, which owns the state it keeps (declared here for the type checker).
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Sequence
from typing import Any

import shapely
from shapely.geometry import Polygon

from drvs.robot import DetectionResult, DrvsClient, Subscription

log = logging.getLogger("drvs.sim.robot")

#: A camera of a continuous request that has sent nothing for this long has stopped looking.
SILENT_AFTER_S = 3.0


class CoverageWatch:
    """Which cameras stopped looking, and the floor left unseen (SimRobot's coverage part)."""

    drvs: DrvsClient | None
    fields_of_view: dict[str, Polygon]
    blind: dict[str, Polygon]
    unseen: dict[str, Polygon]
    _blind_area: Polygon | None
    _watching: list[tuple[Subscription, float]]
    coverage_events: list[dict[str, Any]]
    path_driven: list[tuple[float, float]]
    _started: float

    async def learn_cameras(self) -> None:
        """Every camera's field of view, so that when one stops the robot knows where."""
        assert self.drvs is not None
        self.fields_of_view = {c.camera_id: c.field_of_view for c in await self.drvs.cameras()}

    def check_coverage(self, result: DetectionResult, *, running: bool = False) -> None:
        """A camera that did not answer (failed, skipped, gone) leaves its floor unseen. `running`:
        the request is still under way, so only the cameras the server could not ask count."""
        unseen = shapely.union_all(result.uncovered) if result.uncovered else None
        errors = result.skipped if running else result.camera_errors
        for camera_id, error in sorted(errors.items()):
            self.lose(camera_id, f"{error.code} {error.message}", unseen)
        for camera_id in result.finished_cameras - set(result.camera_errors):
            self.regain(camera_id)

    def lose(self, camera_id: str, why: str, area: Polygon | None = None) -> None:
        if camera_id in self.blind:
            return
        area = self.fields_of_view.get(camera_id, area)
        if area is None or area.is_empty:
            return
        self.blind[camera_id] = area
        self._blind_area = None
        log.warning("camera %s stopped looking (%s): slowing down where only it looked", camera_id, why)
        self.coverage_events.append(self._event(camera_id, "lost", why))

    def regain(self, camera_id: str) -> None:
        if self.blind.pop(camera_id, None) is not None:
            self._blind_area = None
            log.info("camera %s looks again", camera_id)
            self.coverage_events.append(self._event(camera_id, "regained", ""))

    def _event(self, camera_id: str, what: str, why: str) -> dict[str, Any]:
        return {
            "t": round(time.monotonic() - self._started, 2),
            "step": len(self.path_driven) - 1,
            "camera_id": camera_id,
            "event": what,
            "why": why,
        }

    def set_unseen(self, source: str, parts: Sequence[Polygon]) -> None:
        """The floor the latest answers of `source` ("look": the single shots along the plan;
        "watch": the requests watching it while the robot drives) said no camera sees: unknown,
        not clear, as a blind camera's floor is."""
        area = shapely.union_all(list(parts)) if parts else None
        if area is None or area.is_empty:
            if self.unseen.pop(source, None) is not None:
                self._blind_area = None
            return
        self.unseen[source] = area
        self._blind_area = None

    def blind_area(self) -> Polygon | None:
        """Floor that a camera which stopped looking saw and no camera still looking sees, and
        floor the answers said no camera sees."""
        if not self.blind and not self.unseen:
            return None
        if self._blind_area is None:
            area = shapely.union_all(list(self.blind.values())) if self.blind else Polygon()
            seen = [fov for cid, fov in self.fields_of_view.items() if cid not in self.blind]
            if seen and self.blind:
                area = area.difference(shapely.union_all(seen))
            if self.unseen:
                area = shapely.union_all([area, *self.unseen.values()])
            shapely.prepare(area)
            self._blind_area = area
        return self._blind_area

    def check_silence(self) -> None:
        """Cameras of the running continuous requests whose report stream broke, or that fell silent."""
        now = asyncio.get_running_loop().time()
        for sub, since in self._watching:
            for camera_id in sub.interrupted:
                self.lose(camera_id, "its report stream ended")
            done = sub.result.finished_cameras  # a camera that sent its final report is not silent
            for camera_id in sub.camera_ids:
                if camera_id in done:
                    continue
                last = sub.last_report_at.get(camera_id, since)
                if now - last > SILENT_AFTER_S:
                    self.lose(camera_id, f"no report for {now - last:.1f} s")

"""What the robot client hands back: DetectionResult (the reports of one per-camera request) and
CameraInfo (a camera the server routes to)."""

from __future__ import annotations

from dataclasses import dataclass, field

from shapely.geometry import Polygon

from drvs.core.model import DEFAULT_FRAME, CameraError, Detection, DetectionReport, Pose2
from drvs.v1 import registry_pb2
from drvs.wire.convert import polygon_from_pb, pose_from_pb


@dataclass(frozen=True)
class CameraInfo:
    """A camera the server routes to: its id, the address it serves on, its field of view on the
    floor (a shapely Polygon, metres), the detector kinds it serves (hsv, aruco ...), and the
    seconds left on its registration lease.

    A camera on a robot (`mobile`): `field_of_view` is where its robot's last pose puts it (empty
    before the first pose, or when it sees no floor), `pose` that pose (map frame; None before the
    first), `pose_age_s` the seconds since the server received it, and `unroutable` why the server
    does not route to it now ("" when it does: a stale pose, no pose yet, a mount that sees no floor).
    """

    camera_id: str
    address: str
    field_of_view: Polygon
    detector_kinds: tuple[str, ...]
    lease_remaining_s: float
    mobile: bool = False
    pose: Pose2 | None = None
    pose_age_s: float = 0.0
    unroutable: str = ""
    #: The floor plan it registered in ("map" unless it gave one).
    frame: str = DEFAULT_FRAME


def camera_info_from_pb(c: registry_pb2.CameraInfo) -> CameraInfo:
    """One camera of the server's ListCameras answer."""
    return CameraInfo(
        camera_id=c.camera_id,
        address=c.address,
        field_of_view=polygon_from_pb(c.field_of_view, "field_of_view") if c.HasField("field_of_view") else Polygon(),
        detector_kinds=tuple(c.detector_kinds),
        lease_remaining_s=c.lease_remaining_s,
        mobile=c.mobile,
        pose=pose_from_pb(c.pose) if c.HasField("pose") else None,
        pose_age_s=c.pose_age_s,
        unroutable=c.unroutable,
        frame=c.frame or DEFAULT_FRAME,
    )


@dataclass
class DetectionResult:
    """Everything one request brought back.

    Absence of detections means "nothing there" only where a camera looked: `complete` is False
    when any camera that sees the region did not answer (`missing_cameras`, each with its
    `camera_errors` entry, a CameraError), and `uncovered` holds the parts of the region (shapely
    Polygons, metres) that no camera the server asked sees: no camera at all, or only missing
    ones. `all_seen` is True only when both say nothing: the whole region was looked at. A region
    (or frame) no camera sees is complete, and all of it uncovered. `coverage_uncertain_s` > 0: the server
    restarted that many seconds ago or less and may not know every camera yet, so parts of the
    region no dispatched camera sees are not known to be clear. `dropped`: reports this request's
    subscription dropped unread (continuous requests keep only the newest; see
    DrvsClient.subscribe). `raise_for_errors()` turns the first camera failure into an exception.
    """

    request_id: str
    camera_ids: tuple[str, ...]
    reports: list[DetectionReport] = field(default_factory=list)
    #: Cameras the server named in its reply as seeing the region but not asked.
    skipped: dict[str, CameraError] = field(default_factory=dict)
    #: Dispatched cameras whose report stream ended before their final report.
    interrupted: set[str] = field(default_factory=set)
    uncovered: list[Polygon] = field(default_factory=list)
    coverage_uncertain_s: float = 0.0
    dropped: int = 0

    @property
    def detections(self) -> list[Detection]:
        """Every detection of every report, in the order the reports arrived."""
        return [d for r in self.reports for d in r.detections]

    @property
    def finished_cameras(self) -> set[str]:
        """Dispatched cameras that have sent their final report."""
        return {r.camera_id for r in self.reports if r.final}

    @property
    def unfinished_cameras(self) -> set[str]:
        """Dispatched cameras that have sent no final report (yet)."""
        return set(self.camera_ids) - self.finished_cameras

    @property
    def camera_errors(self) -> dict[str, CameraError]:
        """Every camera whose answer is missing, and why (camera id -> CameraError)."""
        errors = dict(self.skipped)
        for camera_id in self.unfinished_cameras:
            if camera_id in self.interrupted:
                errors[camera_id] = CameraError(
                    "UNAVAILABLE", f"camera {camera_id}: its report stream ended before its final report", camera_id
                )
            else:
                errors[camera_id] = CameraError(
                    "DEADLINE_EXCEEDED", f"camera {camera_id}: no final report in time", camera_id
                )
        for r in self.reports:
            error = r.camera_error
            if r.final and error is not None:
                errors[r.camera_id] = error
        return errors

    @property
    def missing_cameras(self) -> set[str]:
        """Cameras that see the region but did not answer: not asked (skipped, gone), failed, or
        sent no final report before the timeout."""
        return set(self.camera_errors)

    @property
    def complete(self) -> bool:
        """True when every camera that sees the region answered."""
        return not self.missing_cameras

    @property
    def all_seen(self) -> bool:
        """True when the whole region was looked at: every camera answered and no part of the
        region is uncovered. Only then do no detections mean nothing there."""
        return self.complete and not self.uncovered

    @property
    def errors(self) -> list[str]:
        """The error text of every report that carried one (see camera_errors for typed values)."""
        return [r.error for r in self.reports if r.error]

    def raise_for_errors(self) -> DetectionResult:
        """Raise the drvs.core.errors exception of the first missing camera (by id; its `.code` the
        status name, its `.camera_id` the camera), or return this result when it is complete."""
        errors = self.camera_errors
        if errors:
            raise errors[min(errors)].exception()
        return self

"""Mobile cameras: a camera on a robot moves with its poses, and joins the continuous fused
requests in flight whose region it comes to see."""

from __future__ import annotations

import logging

import shapely

from drvs.core.errors import DrvsError
from drvs.core.model import Pose2, check_id
from drvs.server.forwarding import Forwarder
from drvs.server.fusion_session import Continuous, FusionSessions
from drvs.server.registration import POSE_APPLIED, RegistryBackend
from drvs.server.registry import CameraEntry, Registry
from drvs.server.routing import Routing
from drvs.v1 import detection_pb2
from drvs.wire import logs, metrics
from drvs.wire.report_auth import report_key

log = logging.getLogger("drvs.server")


class MobileCameras:
    """Takes mobile cameras' poses (`update_pose`) and has a camera that moved pick up the fused
    requests it can now serve (`pick_up`, also for poses another server took)."""

    def __init__(
        self,
        registry: Registry,
        routing: Routing,
        fusion: FusionSessions,
        forwarder: Forwarder,
        registrations: RegistryBackend,
    ) -> None:
        self.registry = registry
        self.routing = routing
        self.fusion = fusion
        self.forwarder = forwarder
        self.registrations = registrations

    def update_pose(
        self, camera_id: str, who: str, registration_secret: str, pose: Pose2, pose_time_unix: float = 0.0
    ) -> CameraEntry:
        """A mobile camera's new pose, from the id's holder with its registration's secret: its field
        of view moves there and is routed for its pose lease (see Registry.update_pose).

        A camera routable now (a fresh pose that puts its field of view on the floor, and not
        skipped after a failed forward) joins every continuous fused request in flight whose region
        its new field of view meets and whose object type it serves, for what remains of the
        request (`pick_up`). Fused single shots are not extended (they answer once, soon), nor are
        continuous requests without fusion: their cameras report straight to the robot's callback,
        and the robot asked the cameras the dispatch named."""
        check_id(camera_id, "camera_id")
        self.registrations.check_holder(camera_id, who, registration_secret, "UpdatePose")
        try:
            self.registrations.admit_pose(camera_id)
            entry = self.registry.update_pose(camera_id, pose, pose_time_unix)
        except DrvsError as exc:
            metrics.POSE_UPDATES.labels(outcome=exc.code.lower()).inc()
            raise
        metrics.POSE_UPDATES.labels(outcome="ok").inc()
        log.debug(POSE_APPLIED, camera_id, pose.x, pose.y, pose.yaw, "")
        self.registrations.share_pose(camera_id, pose, pose_time_unix)
        self.pick_up(entry)
        return entry

    def pick_up(self, camera: CameraEntry) -> None:
        """Ask a mobile camera that just moved to join the continuous fused requests in flight that
        it was not asked for and now can serve: routable as `Routing.plan` would route it, serving the
        request's object type, its field of view meeting the region with positive area (as
        Registry.cameras_seeing tests), and at least one period of the request left."""
        fov = camera.field_of_view
        for left in self.fusion.leave(camera.camera_id, fov):
            log.info("fused request %s: mobile camera %s left its region", left.request_id, camera.camera_id)
        if fov.is_empty or camera.camera_id in self.routing.unreachable or self.registry.unroutable(camera.camera_id):
            return
        fx0, fy0, fx1, fy1 = fov.bounds
        for session in self.fusion.continuous():
            away = camera.camera_id in session.away
            if session.ended or (camera.camera_id in session.keys and not away):
                continue
            region = session.request.region
            x0, y0, x1, y1 = region.bounds  # cheap test first: most requests are elsewhere
            if fx0 >= x1 or fx1 <= x0 or fy0 >= y1 or fy1 <= y0:
                continue
            if session.request.kind not in camera.detector_kinds:
                continue
            if not shapely.relate_pattern(fov, region, "T********"):
                continue
            if not away:
                self.join(session, camera)
            elif session.rejoin(camera.camera_id):
                log.info("fused request %s: mobile camera %s is back over its region", session.request_id,
                         camera.camera_id)  # fmt: skip

    def join(self, session: Continuous, camera: CameraEntry) -> None:
        """Forward `session`'s request to `camera` for the rest of its duration, the same way as at
        its dispatch (its own key, the camera's link, load shedding, failures named in the
        snapshots), and add the camera to the session; nothing when less than a period is left."""
        remaining = session.remaining_s()
        if session.forwarded is None or remaining < session.period:
            return
        message = detection_pb2.DetectionRequest()
        message.CopyFrom(session.forwarded)
        message.continuous.duration_s = remaining
        session.add_camera(camera.camera_id, report_key(session.secret, camera.camera_id))
        token = logs.request_id.set(session.request_id)
        try:
            log.info(
                "fused request %s: mobile camera %s entered its region; asked for the remaining %.1f s",
                session.request_id,
                camera.camera_id,
                remaining,
            )
            metrics.MOBILE_PICKUPS.inc()
            metrics.FORWARDED_BYTES.inc(message.ByteSize())
            self.forwarder.forward(camera, session.request, message, session.secret, session=session)
        finally:
            logs.request_id.reset(token)

"""Dispatch: a robot's validated request counted against its limits, admitted at the door,
forwarded to the cameras routing chose, and answered at once (or, fused, gathered by a session)."""

from __future__ import annotations

import dataclasses
import functools
import itertools
import logging
import time
from collections.abc import Callable

from drvs.core.geometry import Homography
from drvs.core.model import CameraError, DetectionRequest
from drvs.server.admission import Door
from drvs.server.forwarding import Forwarder, Outcome
from drvs.server.fusion_session import Continuous, Delivery, FusionSession, FusionSessions, SingleShot
from drvs.server.policy import CallbackPolicy, IPAddress, RequestLimits
from drvs.server.registry import CameraEntry, Registry
from drvs.server.routing import MissingCamera, Routing
from drvs.v1 import detection_pb2
from drvs.wire import metrics
from drvs.wire.report_auth import new_secret, report_key

log = logging.getLogger("drvs.server")


class Slots:
    """The continuous requests one robot runs on one DetectStream, by request id: freed at once when
    the robot cancels one, or when no camera took it, instead of when its duration runs out."""

    __slots__ = ("_held", "limits", "robot")

    def __init__(self, limits: RequestLimits, robot: str) -> None:
        self.limits = limits
        self.robot = robot
        self._held: dict[str, float] = {}

    def hold(self, request_id: str, slot: float) -> None:
        now = time.monotonic()
        if len(self._held) >= 64:  # forget the ones whose time ran out (RequestLimits did already)
            self._held = {k: end for k, end in self._held.items() if end > now}
        self._held[request_id] = slot

    def release(self, request_id: str) -> None:
        """Free `request_id`'s slot, once; an unknown or already freed id changes nothing."""
        slot = self._held.pop(request_id, None)
        if slot is not None:
            self.limits.release(self.robot, slot)


class Dispatcher:
    """Limits, admission and dispatch: `submit` a request, `submit_fused` a fused one."""

    def __init__(
        self,
        *,
        registry: Registry,
        routing: Routing,
        forwarder: Forwarder,
        limits: RequestLimits,
        door: Door,
        callback_policy: CallbackPolicy,
        fusion: FusionSessions,
        report_address: Callable[[], str],
    ) -> None:
        self.registry = registry
        self.routing = routing
        self.forwarder = forwarder
        self.limits = limits
        self.door = door
        self.callback_policy = callback_policy
        self.fusion = fusion
        self._report_address = report_address
        self._fused_ids = itertools.count(1)

    def dispatch(
        self,
        request: DetectionRequest,
        message: detection_pb2.DetectionRequest,
        secret: bytes = b"",
        plan: tuple[list[CameraEntry], list[MissingCamera]] | None = None,
        on_none_accepted: Callable[[], None] | None = None,
        session: FusionSession | None = None,
    ) -> detection_pb2.DetectionReply:
        """Forward to every camera planned (`plan`, by default the one `Routing.plan` makes) and answer the
        robot: whom it asked, whom it could not, and what part of the region nobody looks at.
        `secret`: the robot's report secret (a fused request's: the server's own for it). `on_none_accepted`
        is called once if every camera refused or failed the request (so it holds no resources
        anywhere). `session`: a fused request's, told of cameras that do not take it."""
        cameras, missing = self.routing.plan(request) if plan is None else plan
        outcome = Outcome(len(cameras), on_none_accepted)
        for camera in cameras:
            self.forwarder.forward(camera, request, message, secret, outcome, session)
        log.debug(
            "request %s from robot %r (%s): dispatched to %s",
            request.request_id,
            request.robot_id,
            request.filter_def,
            ", ".join(c.camera_id for c in cameras) or "no camera",
        )
        reply = detection_pb2.DetectionReply(request_id=request.request_id, camera_ids=[c.camera_id for c in cameras])
        for m in missing:
            reply.missing_cameras.add(camera_id=m.camera_id, code=m.code, message=m.message)
        # Coverage is part of every answer: what no camera asked sees, whoever is missing.
        reply.uncovered.extend(self.routing.uncovered(request.region, cameras))
        uncertain = self.routing.coverage_uncertain_s()
        if uncertain:
            reply.coverage_uncertain_s = uncertain
        return reply

    async def submit(
        self,
        request: DetectionRequest,
        message: detection_pb2.DetectionRequest,
        secret: bytes,
        robot: str,
        peer: IPAddress | None,
        checked_callbacks: dict[str, str],
        slots: Slots | None = None,
    ) -> detection_pb2.DetectionReply:
        """A robot's validated request (`request`, and `message` as it is to be forwarded): refused
        if no camera serves its type; counted against `robot`'s limits; its callback checked against
        the robot's address `peer` (once per address per call: `checked_callbacks`); forwarded to the
        cameras that see its region. `secret`: the robot's report secret. `slots`: the continuous
        requests of the robot's request stream, freed when cancelled. The reply, at once."""
        plan = self.routing.plan(request)
        cameras = plan[0]
        if not cameras and not plan[1]:
            self.routing.refuse_unserved(request)
        # What this request costs the cameras, counted against the robot's budget (not what it
        # cost the robot to send: on a stream a repeated region is left out). The robot's own
        # budget first: one over it hears so, not that the server is busy.
        limits = self.limits
        size = message.ByteSize()
        slot = limits.admit(robot, request.continuous.duration_s, size * len(cameras))
        try:
            self.admit(cameras, caller=robot)
            verified = checked_callbacks.get(request.callback_address)
            if verified is None:
                verified = await self.callback_policy.check(request.callback_address, peer)
                checked_callbacks[request.callback_address] = verified
        except BaseException:
            limits.release(robot, slot)
            raise
        if verified != request.callback_address:
            # Cameras dial the address that was checked, not a name that may resolve anew.
            request = dataclasses.replace(request, callback_address=verified)
            message.callback_address = verified
        on_none_accepted: Callable[[], None] | None = None
        if slot is not None and not cameras:
            limits.release(robot, slot)  # nothing runs: the slot is free again at once
        elif slot is not None and slots is not None:
            slots.hold(request.request_id, slot)  # until it ends, is cancelled, or no camera takes it
            on_none_accepted = functools.partial(slots.release, request.request_id)
        elif slot is not None:
            on_none_accepted = functools.partial(limits.release, robot, slot)
        reply = self.dispatch(request, message, secret, plan, on_none_accepted)
        metrics.FORWARDED_BYTES.inc(size * len(reply.camera_ids))
        return reply

    def submit_fused(
        self,
        request: DetectionRequest,
        message: detection_pb2.DetectionRequest,
        robot: str,
        delivery: Delivery,
        slots: Slots | None = None,
        on_end: Callable[[FusionSession], None] | None = None,
    ) -> tuple[detection_pb2.DetectionReply, FusionSession]:
        """A robot's validated fused request: counted against `robot`'s limits as any request,
        forwarded to the cameras that see its region with `report_to_server` and a key per camera
        from a secret made for it, and gathered by a FusionSession whose replies go to `delivery`.
        Returns the reply to the request as dispatched (a single shot's session answers with it
        later, its snapshot added) and the session. `on_end`: called when the session ends."""
        self.fusion.check_room()
        plan = self.routing.plan(request)
        cameras, missing = plan
        if not cameras and not missing:
            self.routing.refuse_unserved(request)
        limits = self.limits
        # The cameras report to the server, with outlines (fusion matches by them); no callback.
        message.ClearField("fusion")
        message.callback_address = ""
        message.report_to_server = True
        message.report_address = self._report_address()
        message.omit_outlines = False
        # The cameras know it by an id unique in this server (robots choose theirs, and two may
        # choose the same): a cancel one robot's request sends a camera stops no other's.
        forward_id = f"{request.request_id[:100]}:{next(self._fused_ids):x}"
        message.request_id = forward_id
        size = message.ByteSize()
        slot = limits.admit(robot, request.continuous.duration_s, size * len(cameras))
        single_shot = request.continuous.single_shot
        try:
            self.admit(cameras, fused=single_shot, caller=robot)
        except BaseException:
            limits.release(robot, slot)
            raise
        started, waiting = time.perf_counter(), self.fusion.count
        if slot is not None and slots is not None:
            slots.hold(request.request_id, slot)
        secret = new_secret()
        keys = {c.camera_id: report_key(secret, c.camera_id) for c in cameras}

        def ended(session: FusionSession) -> None:
            if single_shot and cameras:  # how long the answer took: fused delivery's queue
                self.door.fused.observe(time.perf_counter() - started, waiting)
            self.fusion.remove(session)
            if slots is not None:
                slots.release(request.request_id)
            elif slot is not None:
                limits.release(robot, slot)
            if on_end is not None:
                on_end(session)

        kind: type[FusionSession] = SingleShot if single_shot else Continuous
        session = kind(
            request,
            [c.camera_id for c in cameras],
            keys,
            self._homography_of,
            delivery,
            ended,
            [CameraError(m.code, m.message, m.camera_id) for m in missing],
            forward_id,
            secret,
            # A continuous one keeps what it forwards: a mobile camera may join it later (mobile.py).
            None if single_shot else message,
        )
        self.fusion.add(session)
        reply = self.dispatch(request, message, secret, plan, session=session)
        session.start(reply)
        metrics.FORWARDED_BYTES.inc(size * len(cameras))
        return reply, session

    def admit(self, cameras: list[CameraEntry], fused: bool = False, caller: str = "") -> None:
        """The door, once a request is routed: ResourceExhausted, before anything is forwarded, if a
        camera it needs has as many forwards waiting as it may, or its link is shedding this one
        (`caller`'s fair part of what it admits: see admission.FairShares)."""
        links = [(c.camera_id, self.forwarder.link(c)) for c in cameras]
        most = self.forwarder.max_queued_forwards
        for camera_id, link in links:
            waiting = link.requests.in_flight
            if waiting >= most:
                link.delay.shedder.congested()
            self.door.check_queue(camera_id, waiting, most, caller)
        self.door.check_cameras(((camera_id, link.delay.shedder) for camera_id, link in links), fused, caller)

    def _homography_of(self, camera_id: str) -> Homography | None:
        if camera_id not in self.registry:
            return None
        return self.registry.get(camera_id).homography

"""Forwarding: the server's links to its cameras, what it sends on them, and what it tells a
robot (or a fused request's session) when a camera does not take a request."""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable, Coroutine
from typing import Any

from drvs.core.errors import DeadlineExceeded, DrvsError, ResourceExhausted, Unavailable
from drvs.core.model import CameraError, DetectionReport, DetectionRequest
from drvs.server.admission import Door, LinkDelay
from drvs.server.fusion_session import FusionSession
from drvs.server.registry import CameraEntry
from drvs.server.routing import Routing
from drvs.server.routing_errors import KEPT, RoutingErrors
from drvs.v1 import detection_pb2, detection_pb2_grpc
from drvs.wire import logs, metrics
from drvs.wire.callback import CallbackSender
from drvs.wire.report_auth import report_key
from drvs.wire.request_stream import BatchSender
from drvs.wire.security import Security

log = logging.getLogger("drvs.server")


class Outcome:
    """Counts a request's forwards that failed; calls `on_none_accepted` once when all have."""

    __slots__ = ("on_none_accepted", "pending")

    def __init__(self, forwards: int, on_none_accepted: Callable[[], None] | None) -> None:
        self.pending = forwards
        self.on_none_accepted = on_none_accepted

    def failed(self) -> None:
        self.pending -= 1
        if self.pending == 0 and self.on_none_accepted is not None:
            callback, self.on_none_accepted = self.on_none_accepted, None
            callback()


class CameraLink:
    """One reused channel per camera, replaced when the camera registers a new address."""

    def __init__(self, address: str, security: Security, token: str, timeout_s: float, delay: LinkDelay) -> None:
        self.address = address
        self.token = token
        #: Its forwards' round trips beyond the fastest: the camera's queue, for the server's door.
        self.delay = delay
        self.channel = security.channel(address)
        # The server proves itself to a camera with the camera's own registration token.
        self.requests = BatchSender(
            detection_pb2_grpc.DetectObjectBoundaryStub(self.channel),
            f"camera at {address}",
            timeout_s=timeout_s,
            metadata=security.metadata(token),
        )

    async def close(self) -> None:
        await self.requests.close()
        await self.channel.close()


class Forwarder:
    """The links to the cameras (one each, presenting what the camera's registration asked for),
    the forwards on them, and the robot told when one fails; a camera that cannot be reached is
    marked in `routing`."""

    def __init__(
        self, security: Security, forward_timeout_s: float, max_queued_forwards: int, door: Door, routing: Routing
    ) -> None:
        self.security = security
        self.forward_timeout_s = forward_timeout_s
        self.max_queued_forwards = max_queued_forwards
        self.door = door
        self.routing = routing
        self.links: dict[str, CameraLink] = {}
        # camera id -> the secret its current registration handed over (or the token it carried),
        # presented back when forwarding to it; replaced, never inherited, at every registration.
        self.camera_tokens: dict[str, str] = {}
        self.routing_errors = RoutingErrors()
        self.callbacks = CallbackSender(security=security)
        self.tasks: set[asyncio.Task[None]] = set()
        #: The server is stopping: failures are its own closing of the links, told to nobody.
        self.stopped = False

    def spawn(self, coro: Coroutine[Any, Any, None]) -> None:
        task = asyncio.get_running_loop().create_task(coro)
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)

    def link(self, camera: CameraEntry) -> CameraLink:
        link = self.links.get(camera.camera_id)
        token = self.camera_tokens.get(camera.camera_id, "")
        if link is None or link.address != camera.address or link.token != token:
            if link is not None:
                self.spawn(link.close())
            link = CameraLink(camera.address, self.security, token, self.forward_timeout_s, self.door.link())
            self.links[camera.camera_id] = link
        return link

    def forward(
        self,
        camera: CameraEntry,
        request: DetectionRequest,
        message: detection_pb2.DetectionRequest,
        secret: bytes = b"",
        outcome: Outcome | None = None,
        session: FusionSession | None = None,
    ) -> None:
        key = report_key(secret, camera.camera_id)
        link = self.link(camera)
        if link.requests.in_flight >= self.max_queued_forwards:
            # Shed load at once rather than queue until the forward timeout: the robot hears
            # now that this camera is busy, and the camera stays in routing.
            self.not_accepted(
                camera,
                request,
                ResourceExhausted(
                    f"busy: {link.requests.in_flight} requests already waiting for it "
                    f"(limit {self.max_queued_forwards}); try again later"
                ),
                key,
                session=session,
            )
            if outcome is not None:
                outcome.failed()
            return
        started = time.perf_counter()
        waiting = link.requests.in_flight

        def done(result: detection_pb2.DetectionReply | DrvsError) -> None:
            if isinstance(result, DeadlineExceeded) or (isinstance(result, ResourceExhausted) and result.retry_after_s):
                # The camera had no room (a refusal with a hint; a cap on one robot's requests has
                # none), or no time: its queue stands.
                link.delay.shedder.congested()
            if isinstance(result, DrvsError):
                # A link the camera has replaced since (it registered again, at another address)
                # says nothing of the camera now: closing it fails what was still in flight on it.
                current = self.links.get(camera.camera_id) is link
                self.not_accepted(camera, request, result, key, mark_unreachable=current, session=session)
                if outcome is not None:
                    outcome.failed()
            else:
                metrics.ROUTED_OK.inc()
                took = time.perf_counter() - started
                link.delay.observe(took, waiting)
                metrics.STAGE_FORWARD.observe(took)

        if key:
            # Each camera gets its own key, and only its own: a copy of the request per camera.
            forwarded = detection_pb2.DetectionRequest()
            forwarded.CopyFrom(message)
            forwarded.report_key = key
            message = forwarded
        link.requests.submit(message, done)

    def not_accepted(
        self,
        camera: CameraEntry,
        request: DetectionRequest,
        exc: DrvsError,
        key: bytes = b"",
        *,
        mark_unreachable: bool = True,
        session: FusionSession | None = None,
    ) -> None:
        """The camera will not report on this request: tell the robot in the camera's name, so it
        need not wait for it (a fused request: tell its `session`, which names it missing). A
        camera that could not be reached is skipped until it heartbeats (unless `mark_unreachable`
        is False: the failure was on a link it has since replaced)."""
        if self.stopped:
            return  # the server's own shutdown closed the links: nobody is waiting to hear
        metrics.ROUTED_FAILED.inc()
        token = logs.request_id.set(request.request_id)
        try:
            # What failed on the hop itself stays in the log (routing_errors): the robot hears UNAVAILABLE.
            code, said = self.routing_errors.for_robot(camera.camera_id, exc, request.request_id)
            reason = f"camera {camera.camera_id} did not accept the request: {code} {said}"
            if code in KEPT:
                log.warning("request %s: %s", request.request_id, reason)
            if mark_unreachable and isinstance(exc, (Unavailable, DeadlineExceeded)):
                self.routing.unreachable_now(camera.camera_id, f"{code} {said}")
            if session is not None:
                session.failed(camera.camera_id, CameraError(code, reason, camera.camera_id))
                return
            report = DetectionReport(
                request_id=request.request_id,
                camera_id=camera.camera_id,
                capture_time=time.time(),
                sequence=0,
                final=True,
                error=reason,
                error_code=code,
            )
            self.spawn(self.tell_robot(request, report, key))
        finally:
            logs.request_id.reset(token)

    async def tell_robot(self, request: DetectionRequest, report: DetectionReport, key: bytes = b"") -> None:
        try:
            await self.callbacks.send(request.callback_address, report, key=key)
        except Exception as exc:
            log.warning("request %s: could not tell the robot: %s", request.request_id, exc)

    def forget(self, camera_id: str) -> None:
        """It left: its link closed, what it presented and its routing errors forgotten."""
        self.routing_errors.forget(camera_id)
        self.camera_tokens.pop(camera_id, None)
        link = self.links.pop(camera_id, None)
        if link is not None:
            self.spawn(link.close())

    async def close(self) -> None:
        """At the server's stop: what it was still doing cancelled, every link closed."""
        for task in list(self.tasks):
            task.cancel()
        await asyncio.gather(*self.tasks, return_exceptions=True)
        await asyncio.gather(*(link.close() for link in self.links.values()), return_exceptions=True)
        self.links.clear()
        await self.callbacks.close()

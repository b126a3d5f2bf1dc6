"""The server's three gRPC services: each converts protobuf and call context to the server's
own terms and delegates to the rooms that do the work (dispatch, registration, mobile cameras,
fusion sessions), then converts the answer back."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import time
import uuid
from collections.abc import AsyncIterator
from typing import TYPE_CHECKING, Any, Protocol

import grpc
from grpc import aio
from shapely.geometry import Polygon

from drvs.core.errors import DrvsError, InvalidArgument, ResourceExhausted, Unavailable
from drvs.core.model import DetectionRequest, Pose2, check_id
from drvs.server.admission import Door
from drvs.server.dispatch import Dispatcher, Slots
from drvs.server.fusion_session import FusionSession, FusionSessions, ReportIntake, SingleShot
from drvs.server.listing import camera_info, list_cameras
from drvs.server.mobile import MobileCameras
from drvs.server.policy import IPAddress, RequestLimits, peer_ip
from drvs.server.registration import CameraRegistration, RegistryBackend
from drvs.server.registry import Registry
from drvs.v1 import detection_pb2, detection_pb2_grpc, registry_pb2, registry_pb2_grpc
from drvs.wire import _grpc, logs, metrics
from drvs.wire.convert import polygon_to_pb, region_from_pb, request_from_pb
from drvs.wire.report_auth import MAX_SECRET_BYTES
from drvs.wire.report_bounds import serve_report_stream
from drvs.wire.request_stream import ReplyQueue, serve_request_stream_queued
from drvs.wire.security import ROBOT, Security, TokenAuthority, bearer_token, caller_identity, camera_identity

if TYPE_CHECKING:
    from drvs.server.liveview import ServerView

#: Fused single shots one request stream may have waiting for their answers at once.
MAX_FUSED_WAITING_PER_STREAM = 256
REPORT_TO_SERVER_REFUSED = (
    "report_to_server: set only by the server on its forwards to cameras; a robot asks for fusion instead"
)
FUSED_CONTINUOUS_UNARY = (
    "fusion: a continuous fused request needs a request stream (DetectStream), whose call carries its "
    "snapshots; DetectObjects takes fused single shots only"
)


class Served(Protocol):
    """What the servicers need of the server (DrvsServer is one): its credentials, its limits and
    door, and the rooms they delegate to."""

    @property
    def tokens(self) -> TokenAuthority: ...
    @property
    def security(self) -> Security: ...
    @property
    def limits(self) -> RequestLimits: ...
    @property
    def door(self) -> Door: ...
    @property
    def fusion(self) -> FusionSessions: ...
    @property
    def registry(self) -> Registry: ...
    @property
    def view(self) -> ServerView | None: ...
    @property
    def dispatcher(self) -> Dispatcher: ...
    @property
    def registrations(self) -> RegistryBackend: ...
    @property
    def mobile(self) -> MobileCameras: ...

    def camera_owner(self, who: str, method: str) -> str:
        """`who`, the identity a call proved ("" anonymous), or Unauthenticated."""
        ...


class RobotFacing(detection_pb2_grpc.DetectObjectBoundaryServicer):
    def __init__(self, server: Served) -> None:
        self._s = server

    def _robot(self, context: aio.ServicerContext[Any, Any]) -> str:
        """Whom limits count against: the robot's credential, or without one its connection."""
        return caller_identity(context, self._s.tokens, ROBOT) or context.peer()

    async def _answer(
        self,
        message: detection_pb2.DetectionRequest,
        peer: IPAddress | None,
        allowed: dict[str, str],
        robot: str,
        slots: Slots | None = None,
        stream: _FusedOnStream | None = None,
    ) -> detection_pb2.DetectionReply | None:
        """Validate, check the callback (once per address per call), dispatch, reply at once (a
        fused single shot on a stream: None, its reply follows on `stream` when it is ready)."""
        started = time.perf_counter()
        token = logs.request_id.set(message.request_id)
        try:
            reply = await self._dispatch(message, peer, allowed, robot, slots, stream)
        except DrvsError:
            metrics.REFUSED.inc()
            raise
        finally:
            logs.request_id.reset(token)
        metrics.DISPATCHED.inc()
        metrics.STAGE_ROUTE.observe(time.perf_counter() - started)
        return reply

    async def _dispatch(
        self,
        message: detection_pb2.DetectionRequest,
        peer: IPAddress | None,
        allowed: dict[str, str],
        robot: str,
        slots: Slots | None,
        stream: _FusedOnStream | None = None,
    ) -> detection_pb2.DetectionReply | None:
        self._s.door.check_server(robot)  # first: a server past capacity spends nothing more on it
        request = request_from_pb(message, require_request_id=False)
        if request.report_to_server:
            raise InvalidArgument(REPORT_TO_SERVER_REFUSED)
        if request.report_address:
            raise InvalidArgument("report_address: set only by the server on its forwards to cameras")
        # Unknown fields are not forwarded: they would make every camera's copy as large as the sender likes.
        message.DiscardUnknownFields()
        secret = message.report_secret
        if len(secret) > MAX_SECRET_BYTES:
            raise InvalidArgument(f"report_secret: longer than {MAX_SECRET_BYTES} bytes")
        # The robot's secret stays here; keys are the server's to make, one per camera.
        message.ClearField("report_secret")
        message.ClearField("report_key")
        message.requester = robot  # cameras count a robot's requests by whom it proved to be, not by robot_id
        if not request.request_id:
            request = dataclasses.replace(request, request_id=uuid.uuid4().hex)
            message.request_id = request.request_id
            logs.request_id.set(request.request_id)
        if request.fusion is not None:
            return await self._fused(request, message, robot, slots, stream)
        return await self._s.dispatcher.submit(request, message, secret, robot, peer, allowed, slots)

    async def _fused(
        self,
        request: DetectionRequest,
        message: detection_pb2.DetectionRequest,
        robot: str,
        slots: Slots | None,
        stream: _FusedOnStream | None,
    ) -> detection_pb2.DetectionReply | None:
        """A fused request: on a stream, its replies go on the stream's queue (a single shot's one
        reply when it is ready: None now); on DetectObjects (single shots only), awaited here."""
        single_shot = request.continuous.single_shot
        if stream is None:
            if not single_shot:
                raise InvalidArgument(FUSED_CONTINUOUS_UNARY)
            delivery = _CallDelivery()
            _, session = self._s.dispatcher.submit_fused(request, message, robot, delivery)
            try:
                reply = await delivery.future
            finally:
                session.end("its call ended")
            if reply.HasField("error"):
                raise _grpc.error_from_code(reply.error.code, reply.error.message, reply.error.retry_after_s)
            return reply
        stream.check(request.request_id, single_shot)
        out = stream.out
        out.owe()
        try:
            reply, session = self._s.dispatcher.submit_fused(
                request, message, robot, _QueueDelivery(out), slots, on_end=stream.ended
            )
        except BaseException:
            out.settle()
            raise
        stream.sessions[request.request_id] = session
        return None if single_shot else reply

    @_grpc.servicer_method
    async def DetectObjects(
        self, message: detection_pb2.DetectionRequest, context: aio.ServicerContext[Any, Any]
    ) -> detection_pb2.DetectionReply:
        view = self._s.view
        if message.cancel:
            raise InvalidArgument("cancel: only a request stream (DetectStream) can cancel its continuous requests")
        seen = view.copy(message) if view is not None else None  # as it came: answering may change it
        reply = await self._answer(message, peer_ip(context.peer()), {}, self._robot(context))
        assert reply is not None  # only a fused single shot on a stream answers later
        if view is not None:  # recorded once taken: a refused request is not (it raised)
            view.request(seen)
            view.reply(reply)
        return reply

    async def DetectStream(
        self,
        request_iterator: AsyncIterator[detection_pb2.DetectionRequest],
        context: aio.ServicerContext[Any, Any],
    ) -> AsyncIterator[detection_pb2.DetectionReply]:
        peer = peer_ip(context.peer())
        allowed: dict[str, str] = {}
        robot = self._robot(context)
        slots = Slots(self._s.limits, robot)
        out = ReplyQueue()
        fused = _FusedOnStream(out)
        view = self._s.view

        async def answer(
            message: detection_pb2.DetectionRequest, out: ReplyQueue
        ) -> detection_pb2.DetectionReply | None:
            if not message.request_id:
                raise InvalidArgument("request_id: empty; a streamed request needs its own id")
            seen = view.copy(message) if view is not None else None  # as it came: answering may change it
            if message.cancel:
                check_id(message.request_id, "request_id")  # echoed back: no longer than an id may be
                slots.release(message.request_id)
                session = fused.sessions.get(message.request_id)
                if session is not None:
                    session.end("cancelled by the robot")
                reply: detection_pb2.DetectionReply | None = detection_pb2.DetectionReply(request_id=message.request_id)
            else:
                reply = await self._answer(message, peer, allowed, robot, slots, fused)
            if view is not None:  # recorded once taken: a refused request is not (it raised)
                view.request(seen)
            return reply

        try:
            async for reply in serve_request_stream_queued(request_iterator, answer, "drvs-server", out):
                if view is not None:
                    view.reply(reply)
                yield reply
        finally:
            for session in list(fused.sessions.values()):
                session.end("the robot's request stream ended")

    async def DetectBatches(
        self,
        request_iterator: AsyncIterator[detection_pb2.DetectionRequests],
        context: aio.ServicerContext[Any, Any],
    ) -> AsyncIterator[detection_pb2.DetectionReplies]:
        await context.abort(
            grpc.StatusCode.UNIMPLEMENTED,
            "DetectBatches is the hop from a server to its cameras; robots send requests on DetectStream",
        )
        yield detection_pb2.DetectionReplies()  # never reached: abort raises


class _FusedOnStream:
    """The fused requests of one robot's request stream, and the queue their replies go on."""

    def __init__(self, out: ReplyQueue) -> None:
        self.out = out
        self.sessions: dict[str, FusionSession] = {}

    def check(self, request_id: str, single_shot: bool) -> None:
        if request_id in self.sessions:
            raise InvalidArgument(
                f"request_id: {request_id[:40]!r} is already a fused request in flight on this stream"
            )
        if single_shot:
            waiting = sum(1 for s in self.sessions.values() if isinstance(s, SingleShot))
            if waiting >= MAX_FUSED_WAITING_PER_STREAM:
                raise ResourceExhausted(
                    f"fusion: {waiting} fused single shots already waiting for their answers on this stream "
                    f"(limit {MAX_FUSED_WAITING_PER_STREAM}); wait for one"
                )

    def ended(self, session: FusionSession) -> None:
        if self.sessions.get(session.request_id) is session:
            del self.sessions[session.request_id]


class _QueueDelivery:
    """A fused request's replies on its robot's request stream."""

    __slots__ = ("out",)

    def __init__(self, out: ReplyQueue) -> None:
        self.out = out

    def send(self, reply: detection_pb2.DetectionReply, last: bool) -> bool:
        return self.out.put_later(reply, last=last)

    def abandon(self) -> None:
        self.out.settle()


class _CallDelivery:
    """A fused single shot's one reply, for its DetectObjects call."""

    def __init__(self) -> None:
        self.future: asyncio.Future[detection_pb2.DetectionReply] = asyncio.get_running_loop().create_future()

    def send(self, reply: detection_pb2.DetectionReply, last: bool) -> bool:
        if self.future.done():
            return False
        self.future.set_result(reply)
        return True

    def abandon(self) -> None:
        if not self.future.done():
            self.future.set_exception(Unavailable("drvs-server: the fused request ended before its answer"))


class CameraReports(detection_pb2_grpc.CallbackCoordinatesServicer):
    """Cameras' reports for fused requests (CallbackCoordinates, as a robot serves it): only cameras
    may call (a camera token or a camera certificate where those are configured, as for
    registration); each stream is a ReportIntake, which takes only the reports a key proves."""

    def __init__(self, server: Served) -> None:
        self._s = server

    async def ReportDetections(
        self,
        request_iterator: AsyncIterator[detection_pb2.DetectionReport],
        context: aio.ServicerContext[Any, Any],
    ) -> None:
        server = self._s
        try:
            who = camera_identity(context, server.tokens, server.security.require_client_cert, "ReportDetections")
            server.camera_owner(who, "ReportDetections")
        except DrvsError as exc:
            # Take the first message before refusing (see security._refusal).
            with contextlib.suppress(Exception):
                await asyncio.wait_for(anext(aiter(request_iterator)), 1.0)
            await context.abort(_grpc.status_of(exc), str(exc))
        view = server.view
        seen = view.report if view is not None else None
        await serve_report_stream(request_iterator, context, ReportIntake(server.fusion, context.peer()), seen)


class Registration(registry_pb2_grpc.RegisterVisionServiceServicer):
    """Converts and delegates: protobuf and call context in, the registry backend (registration.py)
    or the mobile cameras (mobile.py) called, protobuf out."""

    def __init__(self, server: Served) -> None:
        self._s = server

    def _caller(self, context: aio.ServicerContext[Any, Any], method: str) -> str:
        """The identity the call proves ("" anonymous): a camera token or a camera certificate."""
        return camera_identity(context, self._s.tokens, self._s.security.require_client_cert, method)

    @_grpc.servicer_method
    async def Register(
        self, message: registry_pb2.RegisterRequest, context: aio.ServicerContext[Any, Any]
    ) -> registry_pb2.RegisterReply:
        if not message.HasField("homography"):
            raise InvalidArgument("homography: missing")
        who = self._caller(context, "Register")
        registration = CameraRegistration(
            camera_id=message.camera_id,
            address=message.address,
            homography=tuple(message.homography.m),
            image_size=(message.image_width, message.image_height),
            detector_kinds=tuple(message.detector_kinds),
            max_range_m=message.max_range_m,
            registration_secret=message.registration_secret,
            forward_secret=message.forward_secret,
            mobile=message.mobile,
            pose_lease_s=message.pose_lease_s,
            frame=message.frame,
            max_speed_mps=message.max_speed_mps,
        )
        peer = str(peer_ip(context.peer()) or context.peer())
        token = bearer_token(list(context.invocation_metadata() or ()))
        entry, secret = await self._s.registrations.register(registration, who, peer, token)
        state = self._s.registry.mobile_state(entry.camera_id)
        fov: Polygon | None = entry.field_of_view if state is None else state.base_fov
        return registry_pb2.RegisterReply(
            lease_ttl_s=self._s.registry.lease_ttl_s,
            field_of_view=polygon_to_pb(fov) if fov is not None and not fov.is_empty else None,
            registration_secret=secret,
            unroutable=state.no_floor if state is not None else "",
            pose_lease_s=state.pose_lease_s if state is not None else 0.0,
            min_pose_interval_s=self._s.registry.min_pose_interval_s if state is not None else 0.0,
        )

    @_grpc.servicer_method
    async def Heartbeat(
        self, message: registry_pb2.HeartbeatRequest, context: aio.ServicerContext[Any, Any]
    ) -> registry_pb2.HeartbeatReply:
        who = self._caller(context, "Heartbeat")
        await self._s.registrations.renew(message.camera_id, who, message.registration_secret)
        return registry_pb2.HeartbeatReply(lease_ttl_s=self._s.registry.lease_ttl_s)

    @_grpc.servicer_method
    async def UpdatePose(
        self, message: registry_pb2.UpdatePoseRequest, context: aio.ServicerContext[Any, Any]
    ) -> registry_pb2.UpdatePoseReply:
        if not message.HasField("pose"):
            raise InvalidArgument("pose: missing")
        entry = self._s.mobile.update_pose(
            message.camera_id,
            self._caller(context, "UpdatePose"),
            message.registration_secret,
            Pose2(message.pose.x, message.pose.y, message.pose.yaw),
            message.pose_time_unix,
        )
        state = self._s.registry.mobile_state(entry.camera_id)
        return registry_pb2.UpdatePoseReply(
            field_of_view=polygon_to_pb(entry.field_of_view) if not entry.field_of_view.is_empty else None,
            pose_lease_s=state.pose_lease_s if state is not None else 0.0,
        )

    @_grpc.servicer_method
    async def Deregister(
        self, message: registry_pb2.DeregisterRequest, context: aio.ServicerContext[Any, Any]
    ) -> registry_pb2.DeregisterReply:
        who = self._caller(context, "Deregister")
        await self._s.registrations.deregister(message.camera_id, who, message.registration_secret)
        return registry_pb2.DeregisterReply()

    @_grpc.servicer_method
    async def ListCameras(
        self, message: registry_pb2.ListCamerasRequest, context: aio.ServicerContext[Any, Any]
    ) -> registry_pb2.ListCamerasReply:
        region = region_from_pb(message.region) if message.HasField("region") else None
        entries, next_token = list_cameras(
            self._s.registry, region, message.page_token, message.page_size, message.frame
        )
        return registry_pb2.ListCamerasReply(
            next_page_token=next_token,
            cameras=[camera_info(self._s.registry, e) for e in entries],
        )


def add_servicers(server: aio.Server, served: Served) -> None:
    """The three services on `server`, each delegating to `served`."""
    detection_pb2_grpc.add_DetectObjectBoundaryServicer_to_server(RobotFacing(served), server)
    registry_pb2_grpc.add_RegisterVisionServiceServicer_to_server(Registration(served), server)
    detection_pb2_grpc.add_CallbackCoordinatesServicer_to_server(CameraReports(served), server)

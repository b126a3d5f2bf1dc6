"""The DRVS server: routes robots' requests to the cameras that see the region."""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import time
import uuid
from collections import OrderedDict
from collections.abc import AsyncIterator, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import grpc
import shapely
from grpc import aio
from shapely.geometry import Polygon

from drvs import _grpc, logs, metrics
from drvs._service import Endpoint, Lifecycle
from drvs.callback import CallbackSender
from drvs.convert import (
    homography_from_pb,
    polygon_to_pb,
    region_from_pb,
    request_from_pb,
)
from drvs.errors import (
    DeadlineExceeded,
    DrvsError,
    InvalidArgument,
    PermissionDenied,
    ResourceExhausted,
    Unavailable,
)
from drvs.geometry import DEFAULT_MAX_RANGE_M
from drvs.model import DetectionReport, DetectionRequest, check_id
from drvs.net import host_of, is_loopback_host
from drvs.registry import DEFAULT_LEASE_TTL_S, CameraEntry, Registry
from drvs.report_auth import MAX_SECRET_BYTES, report_key
from drvs.request_stream import BatchSender, serve_request_stream
from drvs.security import CAMERA, ROBOT, Security, TokenAuthority, TokenInterceptor, bearer_token, caller_identity
from drvs.server.policy import CallbackPolicy, IPAddress, RequestLimits, peer_ip
from drvs.v1 import detection_pb2, detection_pb2_grpc, geometry_pb2, registry_pb2, registry_pb2_grpc

log = logging.getLogger("drvs.server")

DEFAULT_LISTEN = "127.0.0.1:50051"
#: How long the server waits for a camera to accept a forwarded request.
DEFAULT_FORWARD_TIMEOUT_S = 2.0
#: Forwards to one camera waiting for its acceptance at once; past this the server sheds load:
#: the robot gets an error report for that camera at once (RESOURCE_EXHAUSTED, "busy").
DEFAULT_MAX_QUEUED_FORWARDS = 64
#: A camera whose lease ran out without it deregistering is remembered this long (at most MAX_LOST
#: of them): requests whose region it sees name it as missing until it registers again.
LOST_MEMORY_S = 3600.0
MAX_LOST = 1024
#: Uncovered parts smaller than this (m²) are slivers along field-of-view edges, not reported.
MIN_UNCOVERED_M2 = 0.01
UNCOVERED_CACHE_SIZE = 256
SERVICE_NAMES = (
    detection_pb2.DESCRIPTOR.services_by_name["DetectObjectBoundary"].full_name,
    registry_pb2.DESCRIPTOR.services_by_name["RegisterVisionService"].full_name,
)


@dataclass(frozen=True)
class MissingCamera:
    """A camera that sees a request's region and runs its detector, but is not asked."""

    camera_id: str
    code: str
    message: str
    field_of_view: Polygon


class _CameraLink:
    """One reused channel per camera, replaced when the camera registers a new address."""

    def __init__(self, address: str, security: Security, token: str, timeout_s: float) -> None:
        self.address = address
        self.token = token
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


class DrvsServer(Lifecycle):
    """The server role as an object: start(), stop(grace), `async with`; port 0 picks a free port."""

    def __init__(
        self,
        listen: str = DEFAULT_LISTEN,
        *,
        lease_ttl_s: float = DEFAULT_LEASE_TTL_S,
        forward_timeout_s: float = DEFAULT_FORWARD_TIMEOUT_S,
        max_queued_forwards: int = DEFAULT_MAX_QUEUED_FORWARDS,
        default_max_range_m: float = DEFAULT_MAX_RANGE_M,
        allow_callback: Iterable[str] = (),
        allow_any_callback: bool = False,
        security: Security | None = None,
        camera_tokens: Mapping[str, str] | None = None,
        robot_tokens: Mapping[str, str] | None = None,
        limits: RequestLimits | None = None,
        warm_up_s: float | None = None,
    ) -> None:
        self.callback_policy = CallbackPolicy(allow_callback, allow_any_callback)
        self.security = security or Security()
        self.tokens = TokenAuthority(camera_tokens, robot_tokens)
        self.limits = limits or RequestLimits()
        # camera id -> the identity that registered it (token name or certificate name): another
        # identity may not re-register, renew or deregister it.
        self.owners: dict[str, str] = {}
        # camera id -> the token it registered with, presented back when forwarding to it.
        self._camera_tokens: dict[str, str] = {}
        self.registry = Registry(lease_ttl_s)
        self.forward_timeout_s = forward_timeout_s
        if max_queued_forwards < 1:
            raise InvalidArgument(f"max_queued_forwards: {max_queued_forwards} must be at least 1")
        self.max_queued_forwards = max_queued_forwards
        self.default_max_range_m = default_max_range_m
        self._endpoint = Endpoint(
            listen,
            SERVICE_NAMES,
            self._add_servicers,
            security=self.security,
            interceptors=[TokenInterceptor(self.tokens)] if self.tokens.enabled else [],
        )
        self._links: dict[str, _CameraLink] = {}
        # Cameras whose last forward failed: skipped until their next heartbeat proves them alive.
        self._unreachable: set[str] = set()
        self._unreachable_why: dict[str, str] = {}
        # Cameras whose lease ran out without deregistering: id -> (entry, when, why).
        self._lost: OrderedDict[str, tuple[CameraEntry, float, str]] = OrderedDict()
        # ids of (region, fields of view asked and missing) -> (region, fields of view, unseen parts)
        self._uncovered_cache: dict[
            tuple[int, ...], tuple[Polygon, tuple[Polygon, ...], list[geometry_pb2.Polygon]]
        ] = {}
        # After a start, cameras registered with a previous run may not be back yet for this long.
        self.warm_up_s = lease_ttl_s if warm_up_s is None else warm_up_s
        if not (self.warm_up_s >= 0):
            raise InvalidArgument(f"warm_up_s: {warm_up_s} must be >= 0")
        self._started_at = time.monotonic()
        self._tasks: set[asyncio.Task[None]] = set()
        self._sweeper: asyncio.Task[None] | None = None
        self._callbacks = CallbackSender(security=self.security)
        self._stopped = False

    @property
    def port(self) -> int:
        return self._endpoint.port

    @property
    def address(self) -> str:
        return self._endpoint.address

    def _add_servicers(self, server: aio.Server) -> None:
        detection_pb2_grpc.add_DetectObjectBoundaryServicer_to_server(_RobotFacing(self), server)
        registry_pb2_grpc.add_RegisterVisionServiceServicer_to_server(_Registration(self), server)

    async def start(self) -> None:
        await self._endpoint.start()
        self._started_at = time.monotonic()
        self._sweeper = asyncio.get_running_loop().create_task(self._sweep_leases())
        log.info("security: %s", self.describe_security())
        log.info("drvs-server listening on %s (lease %.1f s)", self.address, self.registry.lease_ttl_s)

    def describe_security(self) -> str:
        parts = []
        if self.security.tls:
            parts.append("mutual TLS" if self.security.require_client_cert else "TLS")
        for role, table in self.tokens.tables.items():
            if table is not None:
                parts.append(f"{len(table)} {role} token(s)")
        if parts:
            return ", ".join(parts)
        if is_loopback_host(host_of(self.address)):
            return "none (plain TCP, no tokens): serving this host only; configure TLS or tokens to serve others"
        return (
            "NONE on a non-loopback address: anyone who can reach "
            f"{self.address} can register cameras and ask for detections"
        )

    async def stop(self, grace: float = 2.0) -> None:
        if self._stopped or not self._endpoint.started:
            return
        self._stopped = True
        if self._sweeper is not None:
            self._sweeper.cancel()
        await self._endpoint.stop(grace)
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        await asyncio.gather(*(link.close() for link in self._links.values()), return_exceptions=True)
        self._links.clear()
        await self._callbacks.close()
        log.info("drvs-server stopped")

    async def wait_for_termination(self) -> None:
        await self._endpoint.wait_for_termination()

    # --- routing ---------------------------------------------------------------------------

    def route(self, request: DetectionRequest) -> list[CameraEntry]:
        """The live cameras that see the request's region, run its detector and are reachable."""
        return self.plan(request)[0]

    def plan(self, request: DetectionRequest) -> tuple[list[CameraEntry], list[MissingCamera]]:
        """The cameras to ask, and those that see the region and run the detector but will not be
        asked: skipped after a failed forward, or gone without deregistering."""
        seeing = self.registry.cameras_seeing(request.region, request.kind)
        if not self._unreachable and not self._lost:
            return seeing, []  # the common case costs nothing more
        cameras = [c for c in seeing if c.camera_id not in self._unreachable]
        missing = [
            MissingCamera(
                c.camera_id,
                "UNAVAILABLE",
                f"skipped until it heartbeats: {self._unreachable_why.get(c.camera_id, 'its last forward failed')}",
                c.field_of_view,
            )
            for c in seeing
            if c.camera_id in self._unreachable
        ]
        now = time.monotonic()
        x0, y0, x1, y1 = request.region.bounds
        for camera_id, (entry, since, why) in list(self._lost.items()):
            if camera_id in self.registry or now - since > LOST_MEMORY_S:
                del self._lost[camera_id]  # back (routed or refused as itself), or forgotten
                continue
            fx0, fy0, fx1, fy1 = entry.field_of_view.bounds  # cheap test first: most are far away
            if fx0 >= x1 or fx1 <= x0 or fy0 >= y1 or fy1 <= y0 or request.kind not in entry.detector_kinds:
                continue
            if shapely.relate_pattern(entry.field_of_view, request.region, "T********"):
                message = f"{why} {now - since:.0f} s ago"
                missing.append(MissingCamera(camera_id, "UNAVAILABLE", message, entry.field_of_view))
        return cameras, missing

    def _uncovered(
        self, region: Polygon, cameras: list[CameraEntry], missing: list[MissingCamera]
    ) -> list[geometry_pb2.Polygon]:
        """`_uncovered`, encoded, kept per region object and cameras: while a camera is gone, robots
        ask about the same regions again and again."""
        fovs = tuple(c.field_of_view for c in cameras) + tuple(m.field_of_view for m in missing)
        key = (id(region), *map(id, fovs))
        hit = self._uncovered_cache.get(key)
        if hit is not None and hit[0] is region and all(a is b for a, b in zip(hit[1], fovs, strict=True)):
            return hit[2]
        parts = [polygon_to_pb(part) for part in _uncovered(region, cameras, missing)]
        if len(self._uncovered_cache) >= UNCOVERED_CACHE_SIZE:
            del self._uncovered_cache[next(iter(self._uncovered_cache))]
        self._uncovered_cache[key] = (region, fovs, parts)  # held: their ids stay theirs
        return parts

    def coverage_uncertain_s(self) -> float:
        """How much longer cameras registered with a previous run of the server may still be on
        their way back (0 once a lease has passed since the start)."""
        return max(0.0, self._started_at + self.warm_up_s - time.monotonic())

    def dispatch(
        self, request: DetectionRequest, message: detection_pb2.DetectionRequest, secret: bytes = b""
    ) -> detection_pb2.DetectionReply:
        """Forward to every camera planned and answer the robot: whom it asked, whom it could not, and
        what part of the region nobody looks at. `secret`: the robot's report secret."""
        cameras, missing = self.plan(request)
        for camera in cameras:
            self._forward(camera, request, message, secret)
        log.debug(
            "request %s from robot %r (%s): dispatched to %s",
            request.request_id,
            request.robot_id,
            request.filter_def,
            ", ".join(c.camera_id for c in cameras) or "no camera",
        )
        reply = detection_pb2.DetectionReply(request_id=request.request_id, camera_ids=[c.camera_id for c in cameras])
        if missing:
            for m in missing:
                reply.missing_cameras.add(camera_id=m.camera_id, code=m.code, message=m.message)
            reply.uncovered.extend(self._uncovered(request.region, cameras, missing))
        uncertain = self.coverage_uncertain_s()
        if uncertain:
            reply.coverage_uncertain_s = uncertain
        return reply

    def _spawn(self, coro: Any) -> None:
        task = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def _link(self, camera: CameraEntry) -> _CameraLink:
        link = self._links.get(camera.camera_id)
        token = self._camera_tokens.get(camera.camera_id, "")
        if link is None or link.address != camera.address or link.token != token:
            if link is not None:
                self._spawn(link.close())
            link = _CameraLink(camera.address, self.security, token, self.forward_timeout_s)
            self._links[camera.camera_id] = link
        return link

    def _forward(
        self,
        camera: CameraEntry,
        request: DetectionRequest,
        message: detection_pb2.DetectionRequest,
        secret: bytes = b"",
    ) -> None:
        key = report_key(secret, camera.camera_id)
        link = self._link(camera)
        if link.requests.in_flight >= self.max_queued_forwards:
            # Shed load at once rather than queue until the forward timeout: the robot hears
            # now that this camera is busy, and the camera stays in routing.
            self._not_accepted(
                camera,
                request,
                ResourceExhausted(
                    f"busy: {link.requests.in_flight} requests already waiting for it "
                    f"(limit {self.max_queued_forwards}); try again later"
                ),
                key,
            )
            return
        started = time.perf_counter()

        def done(result: detection_pb2.DetectionReply | DrvsError) -> None:
            if isinstance(result, DrvsError):
                self._not_accepted(camera, request, result, key)
            else:
                metrics.ROUTED_OK.inc()
                metrics.STAGE_FORWARD.observe(time.perf_counter() - started)

        if key:
            # Each camera gets its own key, and only its own: a copy of the request per camera.
            forwarded = detection_pb2.DetectionRequest()
            forwarded.CopyFrom(message)
            forwarded.report_key = key
            message = forwarded
        link.requests.submit(message, done)

    def _not_accepted(self, camera: CameraEntry, request: DetectionRequest, exc: DrvsError, key: bytes = b"") -> None:
        """The camera will not report on this request: tell the robot in the camera's name, so it
        need not wait for it. A camera that could not be reached is skipped until it heartbeats."""
        if self._stopped:
            return  # the server's own shutdown closed the links: nobody is waiting to hear
        metrics.ROUTED_FAILED.inc()
        code = _grpc.status_of(exc).name
        reason = f"camera {camera.camera_id} did not accept the request: {code} {exc}"
        token = logs.request_id.set(request.request_id)
        try:
            log.warning("request %s: %s", request.request_id, reason)
            if isinstance(exc, (Unavailable, DeadlineExceeded)):
                self._unreachable.add(camera.camera_id)
                self._unreachable_why[camera.camera_id] = f"{code} {exc}"
            report = DetectionReport(
                request_id=request.request_id,
                camera_id=camera.camera_id,
                capture_time=time.time(),
                sequence=0,
                final=True,
                error=reason,
                error_code=code,
            )
            self._spawn(self._tell_robot(request, report, key))
        finally:
            logs.request_id.reset(token)

    async def _tell_robot(self, request: DetectionRequest, report: DetectionReport, key: bytes = b"") -> None:
        try:
            await self._callbacks.send(request.callback_address, report, key=key)
        except Exception as exc:
            log.warning("request %s: could not tell the robot: %s", request.request_id, exc)

    def _forget(self, camera_id: str) -> None:
        self._unreachable.discard(camera_id)
        self._unreachable_why.pop(camera_id, None)
        self._lost.pop(camera_id, None)
        self._camera_tokens.pop(camera_id, None)
        link = self._links.pop(camera_id, None)
        if link is not None:
            self._spawn(link.close())

    async def _sweep_leases(self) -> None:
        period = min(1.0, self.registry.lease_ttl_s / 4)
        while True:
            await asyncio.sleep(period)
            for entry in self.registry.expire():
                log.info("camera %s left routing: lease expired", entry.camera_id)
                self._forget(entry.camera_id)
                # It did not deregister: requests whose region it saw say it is missing.
                self._lost[entry.camera_id] = (entry, time.monotonic(), "its lease ran out without it deregistering")
                while len(self._lost) > MAX_LOST:
                    self._lost.popitem(last=False)
                metrics.CAMERAS.set(len(self.registry))


class _RobotFacing(detection_pb2_grpc.DetectObjectBoundaryServicer):
    def __init__(self, server: DrvsServer) -> None:
        self._s = server

    def _robot(self, context: aio.ServicerContext[Any, Any]) -> str:
        """Whom limits count against: the robot's credential, or without one its connection."""
        return caller_identity(context, self._s.tokens, ROBOT) or context.peer()

    async def _answer(
        self, message: detection_pb2.DetectionRequest, peer: IPAddress | None, allowed: dict[str, str], robot: str
    ) -> detection_pb2.DetectionReply:
        """Validate, check the callback (once per address per call), dispatch, reply at once."""
        started = time.perf_counter()
        token = logs.request_id.set(message.request_id)
        try:
            reply = await self._dispatch(message, peer, allowed, robot)
        except DrvsError:
            metrics.REFUSED.inc()
            raise
        finally:
            logs.request_id.reset(token)
        metrics.DISPATCHED.inc()
        metrics.STAGE_ROUTE.observe(time.perf_counter() - started)
        return reply

    async def _dispatch(
        self, message: detection_pb2.DetectionRequest, peer: IPAddress | None, allowed: dict[str, str], robot: str
    ) -> detection_pb2.DetectionReply:
        request = request_from_pb(message, require_request_id=False)
        secret = message.report_secret
        if len(secret) > MAX_SECRET_BYTES:
            raise InvalidArgument(f"report_secret: longer than {MAX_SECRET_BYTES} bytes")
        # The robot's secret stays here; keys are the server's to make, one per camera.
        message.ClearField("report_secret")
        message.ClearField("report_key")
        self._s.limits.admit(robot, request.continuous.duration_s)
        verified = allowed.get(request.callback_address)
        if verified is None:
            verified = await self._s.callback_policy.check(request.callback_address, peer)
            allowed[request.callback_address] = verified
        if verified != request.callback_address:
            # Cameras dial the address that was checked, not a name that may resolve anew.
            request = dataclasses.replace(request, callback_address=verified)
            message.callback_address = verified
        if not request.request_id:
            request = dataclasses.replace(request, request_id=uuid.uuid4().hex)
            message.request_id = request.request_id
            logs.request_id.set(request.request_id)
        return self._s.dispatch(request, message, secret)

    @_grpc.servicer_method
    async def DetectObjects(
        self, message: detection_pb2.DetectionRequest, context: aio.ServicerContext[Any, Any]
    ) -> detection_pb2.DetectionReply:
        return await self._answer(message, peer_ip(context.peer()), {}, self._robot(context))

    async def DetectStream(
        self,
        request_iterator: AsyncIterator[detection_pb2.DetectionRequest],
        context: aio.ServicerContext[Any, Any],
    ) -> AsyncIterator[detection_pb2.DetectionReply]:
        peer = peer_ip(context.peer())
        allowed: dict[str, str] = {}
        robot = self._robot(context)

        async def answer(message: detection_pb2.DetectionRequest) -> detection_pb2.DetectionReply:
            if not message.request_id:
                raise InvalidArgument("request_id: empty; a streamed request needs its own id")
            return await self._answer(message, peer, allowed, robot)

        async for reply in serve_request_stream(request_iterator, answer, "drvs-server"):
            yield reply

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


class _Registration(registry_pb2_grpc.RegisterVisionServiceServicer):
    def __init__(self, server: DrvsServer) -> None:
        self._s = server

    def _owner(self, camera_id: str, context: aio.ServicerContext[Any, Any]) -> str:
        """The caller's identity, if it may act for `camera_id`: nobody takes over a camera id
        registered under another credential, or deregisters it."""
        who = caller_identity(context, self._s.tokens, CAMERA)
        owner = self._s.owners.get(camera_id)
        if owner is not None and owner != who:
            raise PermissionDenied(f"camera_id: {camera_id!r} belongs to another credential")
        return who

    @_grpc.servicer_method
    async def Register(
        self, message: registry_pb2.RegisterRequest, context: aio.ServicerContext[Any, Any]
    ) -> registry_pb2.RegisterReply:
        if not message.HasField("homography"):
            raise InvalidArgument("homography: missing")
        owner = self._owner(message.camera_id, context)
        max_range = message.max_range_m or self._s.default_max_range_m
        entry = self._s.registry.register(
            camera_id=message.camera_id,
            address=message.address,
            homography=homography_from_pb(message.homography),
            image_size=(message.image_width, message.image_height),
            detector_kinds=set(message.detector_kinds),
            max_range_m=max_range,
        )
        self._s.owners[entry.camera_id] = owner
        metrics.CAMERAS.set(len(self._s.registry))
        token = bearer_token(list(context.invocation_metadata() or ()))
        if token:
            self._s._camera_tokens[entry.camera_id] = token
        self._s._unreachable.discard(entry.camera_id)
        self._s._link(entry)
        log.info(
            "camera %s registered at %s: field of view %.1f m², detectors %s",
            entry.camera_id,
            entry.address,
            entry.field_of_view.area,
            ",".join(sorted(entry.detector_kinds)),
        )
        return registry_pb2.RegisterReply(
            lease_ttl_s=self._s.registry.lease_ttl_s, field_of_view=polygon_to_pb(entry.field_of_view)
        )

    @_grpc.servicer_method
    async def Heartbeat(
        self, message: registry_pb2.HeartbeatRequest, context: aio.ServicerContext[Any, Any]
    ) -> registry_pb2.HeartbeatReply:
        check_id(message.camera_id, "camera_id")
        self._owner(message.camera_id, context)
        self._s.registry.renew(message.camera_id)
        self._s._unreachable.discard(message.camera_id)
        return registry_pb2.HeartbeatReply(lease_ttl_s=self._s.registry.lease_ttl_s)

    @_grpc.servicer_method
    async def Deregister(
        self, message: registry_pb2.DeregisterRequest, context: aio.ServicerContext[Any, Any]
    ) -> registry_pb2.DeregisterReply:
        check_id(message.camera_id, "camera_id")
        self._owner(message.camera_id, context)
        self._s.registry.remove(message.camera_id)
        self._s.owners.pop(message.camera_id, None)
        self._s._forget(message.camera_id)
        metrics.CAMERAS.set(len(self._s.registry))
        log.info("camera %s deregistered", message.camera_id)
        return registry_pb2.DeregisterReply()

    @_grpc.servicer_method
    async def ListCameras(
        self, message: registry_pb2.ListCamerasRequest, context: aio.ServicerContext[Any, Any]
    ) -> registry_pb2.ListCamerasReply:
        entries: list[CameraEntry]
        if message.HasField("region"):
            region: Polygon = region_from_pb(message.region)
            entries = self._s.registry.cameras_seeing(region)
        else:
            entries = self._s.registry.cameras()
        return registry_pb2.ListCamerasReply(
            cameras=[
                registry_pb2.CameraInfo(
                    camera_id=e.camera_id,
                    address=e.address,
                    field_of_view=polygon_to_pb(e.field_of_view),
                    detector_kinds=sorted(e.detector_kinds),
                    lease_remaining_s=self._s.registry.remaining_s(e.camera_id),
                )
                for e in entries
            ]
        )


def _uncovered(region: Polygon, cameras: list[CameraEntry], missing: list[MissingCamera]) -> list[Polygon]:
    """The parts of `region` that a missing camera sees and no dispatched camera does, each as its
    outer ring (a hole, seen by someone, is counted as unseen: the robot errs on the safe side)."""
    lost = shapely.intersection(shapely.union_all([m.field_of_view for m in missing]), region)
    if cameras:
        lost = shapely.difference(lost, shapely.union_all([c.field_of_view for c in cameras]))
    parts = []
    for part in shapely.get_parts(lost):
        if isinstance(part, Polygon) and part.area >= MIN_UNCOVERED_M2:
            parts.append(Polygon(part.exterior.coords))
    return parts

"""The DRVS server: routes robots' requests to the cameras that see the region."""

from __future__ import annotations

import asyncio
import bisect
import contextlib
import dataclasses
import functools
import itertools
import logging
import math
import secrets
import time
import uuid
from collections import OrderedDict
from collections.abc import AsyncIterator, Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import grpc
import shapely
from grpc import aio
from shapely.geometry import Polygon

from drvs.core.errors import (
    DeadlineExceeded,
    DrvsError,
    FailedPrecondition,
    InvalidArgument,
    NotFound,
    ResourceExhausted,
    Unauthenticated,
    Unavailable,
)
from drvs.core.geometry import Homography
from drvs.core.model import DEFAULT_FRAME, CameraError, DetectionReport, DetectionRequest, Pose2, check_frame, check_id
from drvs.core.net import format_address, host_of, is_loopback_host
from drvs.server.admission import Door, LinkDelay
from drvs.server.config import (
    DEFAULT_LISTEN,
    WILDCARDS,
    ServerConfig,
)
from drvs.server.coverage import uncovered
from drvs.server.etcd import Endpoints, EtcdClient
from drvs.server.fusion_session import Continuous, FusionSession, FusionSessions, ReportIntake, SingleShot
from drvs.server.policy import CallbackPolicy, IPAddress, RequestLimits, peer_ip
from drvs.server.registry import (
    CameraEntry,
    Claims,
    Registry,
)
from drvs.server.routing_errors import KEPT, RoutingErrors
from drvs.server.shared import PoseRecord, Record, SharedRegistry, secret_digest
from drvs.v1 import detection_pb2, detection_pb2_grpc, geometry_pb2, registry_pb2, registry_pb2_grpc
from drvs.wire import _grpc, logs, metrics
from drvs.wire._service import Endpoint, Lifecycle
from drvs.wire.callback import CallbackSender
from drvs.wire.convert import (
    polygon_to_pb,
    pose_to_pb,
    region_from_pb,
    request_from_pb,
)
from drvs.wire.report_auth import MAX_SECRET_BYTES, new_secret, report_key
from drvs.wire.report_bounds import serve_report_stream
from drvs.wire.request_stream import BatchSender, ReplyQueue, serve_request_stream_queued
from drvs.wire.security import (
    CAMERA,
    ROBOT,
    Security,
    TokenAuthority,
    TokenInterceptor,
    bearer_token,
    caller_identity,
    camera_identity,
)

if TYPE_CHECKING:
    from drvs.server.liveview import ServerView

#: How long a server sharing its registry in etcd waits for it at start before serving, seconds.
SHARED_SYNC_WAIT_S = 5.0
log = logging.getLogger("drvs.server")

#: ListCameras: cameras per reply unless the caller asks for fewer, and the most it may ask for.
#: A camera's entry is at most about 4 kB (id, address, 16 detector kinds, a field of view of at
#: most about 70 vertices): 500 of them stay far below the 4 MB message limit.
DEFAULT_PAGE_SIZE = 500
MAX_PAGE_SIZE = 500
#: Longest secret a camera may hand over (it travels as call metadata on every forward).
MAX_SECRET_LENGTH = 256
#: A camera whose lease ran out without it deregistering is remembered this long (at most MAX_LOST
#: of them): requests whose region it sees name it as missing until it registers again.
LOST_MEMORY_S = 3600.0
MAX_LOST = 1024
UNCOVERED_CACHE_SIZE = 256
SERVICE_NAMES = (
    detection_pb2.DESCRIPTOR.services_by_name["DetectObjectBoundary"].full_name,
    registry_pb2.DESCRIPTOR.services_by_name["RegisterVisionService"].full_name,
    detection_pb2.DESCRIPTOR.services_by_name["CallbackCoordinates"].full_name,
)
REGISTRATION_SERVICE = SERVICE_NAMES[1]
#: Fused single shots one request stream may have waiting for their answers at once.
MAX_FUSED_WAITING_PER_STREAM = 256
REPORT_TO_SERVER_REFUSED = (
    "report_to_server: set only by the server on its forwards to cameras; a robot asks for fusion instead"
)
FUSED_CONTINUOUS_UNARY = (
    "fusion: a continuous fused request needs a request stream (DetectStream), whose call carries its "
    "snapshots; DetectObjects takes fused single shots only"
)


#: The DEBUG line of every pose a mobile camera's field of view moves to (tests wait on it).
POSE_APPLIED = "camera %s at pose x=%.3f y=%.3f yaw=%.4f %s"


class _Outcome:
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


class _Slots:
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


@dataclass(frozen=True)
class MissingCamera:
    """A camera that sees a request's region and runs its detector, but is not asked."""

    camera_id: str
    code: str
    message: str
    field_of_view: Polygon


@dataclass(frozen=True)
class CameraRegistration:
    """What a camera registers: `RegisterRequest` as the server object takes it."""

    camera_id: str
    #: host:port the server dials to forward requests.
    address: str
    #: image pixels -> floor metres: the 3x3 matrix, row-major (checked when registered, after the
    #: caller's claim on the id, so a caller without one learns nothing else).
    homography: tuple[float, ...]
    #: (width, height) of the camera's images, pixels.
    image_size: tuple[int, int]
    detector_kinds: tuple[str, ...]
    #: Metres the camera sees; 0 means the server's default.
    max_range_m: float = 0.0
    #: The previous registration's secret: proves an anonymous camera is coming back.
    registration_secret: str = ""
    #: What the server is to present back on every forward to this camera.
    forward_secret: str = ""
    #: A camera on a robot: `homography` maps to the robot's base frame; its poses move it.
    mobile: bool = False
    #: Mobile: seconds a pose update keeps it routed (0: the server's default; capped).
    pose_lease_s: float = 0.0
    #: The floor plan its homography maps to ("" or "map": the default).
    frame: str = DEFAULT_FRAME
    #: Mobile: the fastest its robot moves, m/s (0: the server's default).
    max_speed_mps: float = 0.0


class _CameraLink:
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


class DrvsServer(Lifecycle):
    """The server role as an object: start(), stop(grace), `async with`; port 0 picks a free port.

    The keyword arguments are `ServerConfig`'s settings (see there for units and ranges), checked
    by it exactly as drvs-server checks its flags. `config` gives them all at once instead (as
    `DrvsServer.from_config` does); `limits` and `connection_limits`, when given, replace the
    request and connection limits the config describes."""

    def __init__(
        self,
        listen: str = DEFAULT_LISTEN,
        *,
        security: Security | None = None,
        camera_tokens: Mapping[str, str] | None = None,
        robot_tokens: Mapping[str, str] | None = None,
        limits: RequestLimits | None = None,
        connection_limits: _grpc.ConnectionLimits | None = None,
        config: ServerConfig | None = None,
        **settings: Any,
    ) -> None:
        # Any ServerConfig field is a keyword (an unknown one: TypeError naming it); no list here.
        given = ServerConfig(listen=listen, **settings)
        if config is None:
            config = given
        elif given != ServerConfig():
            raise InvalidArgument("config: give the settings either as a ServerConfig or as keywords, not both")
        self.config = config
        self.callback_policy = CallbackPolicy(config.allow_callback, config.allow_any_callback)
        self.security = security or Security()
        self.tokens = TokenAuthority(camera_tokens, robot_tokens)
        self.limits = limits or config.request_limits()
        self.connection_limits = connection_limits or config.connection_limits()
        self.trust_network = config.trust_network
        # camera id -> the secret its current registration handed over (or the token it carried),
        # presented back when forwarding to it; replaced, never inherited, at every registration.
        self._camera_tokens: dict[str, str] = {}
        self.registry = Registry(
            config.lease_ttl_s,
            max_fov_range_m=config.max_fov_range_m,
            max_fov_area_m2=config.max_fov_area_m2,
            pose_lease_s=config.pose_lease_s,
            max_pose_lease_s=config.max_pose_lease_s,
            min_pose_interval_s=config.min_pose_interval_s,
        )
        # camera id -> who holds it (token name, certificate name, or an anonymous registration's
        # secret): another identity may not re-register, renew or deregister it.
        self.claims = Claims(config.registration_grace_s, config.max_cameras_per_identity)
        self.forward_timeout_s = config.forward_timeout_s
        self.max_queued_forwards = config.max_queued_forwards
        self.default_max_range_m = config.default_max_range_m
        options = self.connection_limits.options()
        also_listen: list[str] = []
        if config.workers > 1:
            # One of several processes on `listen` (drvs.server.workers): the kernel spreads
            # connections over them, so cameras send a fused request's reports to a port of this
            # process's own, where the request's session is.
            options.append(("grpc.so_reuseport", 1))
            also_listen.append(format_address(host_of(config.listen), 0))
        self._endpoint = Endpoint(
            config.listen,
            SERVICE_NAMES,
            self._add_servicers,
            security=self.security,
            interceptors=[TokenInterceptor(self.tokens)] if self.tokens.enabled else [],
            options=options,
            also_listen=also_listen,
        )
        self._links: dict[str, _CameraLink] = {}
        #: Admission: past capacity requests are refused here, before anything is forwarded.
        self.door = Door(config.admission_target_s)
        # Cameras whose last forward failed: skipped until their next heartbeat proves them alive.
        self._unreachable: set[str] = set()
        self._unreachable_why: dict[str, str] = {}
        self._routing_errors = RoutingErrors()
        # Cameras whose lease ran out without deregistering: id -> (entry, when, why).
        self._lost: OrderedDict[str, tuple[CameraEntry, float, str]] = OrderedDict()
        # ids of (region, fields of view asked and missing) -> (region, fields of view, unseen parts)
        self._uncovered_cache: dict[
            tuple[int, ...], tuple[Polygon, tuple[Polygon, ...], list[geometry_pb2.Polygon]]
        ] = {}
        # After a start, cameras registered with a previous run may not be back yet for this long.
        self.warm_up_s = config.warm_up
        self._started_at = time.monotonic()
        self._tasks: set[asyncio.Task[None]] = set()
        self._sweeper: asyncio.Task[None] | None = None
        self._callbacks = CallbackSender(security=self.security)
        #: Fused requests in flight, whose cameras report here (fusion_session.py).
        self.fusion = FusionSessions()
        self._fused_ids = itertools.count(1)
        self._stopped = False
        #: The registry's etcd side when it is shared with other servers (--registry etcd://...).
        self.shared: SharedRegistry | None = None
        #: The live view and recording (--foxglove, --record): see `show`.
        self.view: ServerView | None = None
        if config.registry != "memory":
            endpoints = Endpoints.parse(config.registry, "registry")
            self.shared = SharedRegistry(
                endpoints,
                self._apply_shared,
                self._drop_shared,
                lambda: [e.camera_id for e in self.registry.cameras()],
                on_reachable=self._registry_reachable,
                apply_pose=self._apply_shared_pose,
                client=EtcdClient(endpoints, credentials=config.etcd_credentials()),
                registration_rate=config.registration_rate,
                pose_write_rate=config.pose_write_rate,
            )

    @classmethod
    def from_config(
        cls,
        config: ServerConfig,
        *,
        security: Security | None = None,
        camera_tokens: Mapping[str, str] | None = None,
        robot_tokens: Mapping[str, str] | None = None,
    ) -> DrvsServer:
        """A server with `config`'s settings and these credentials (drvs-server's way in)."""
        return cls(config=config, security=security, camera_tokens=camera_tokens, robot_tokens=robot_tokens)

    def show(
        self,
        listen: tuple[str, int] | None = None,
        record: Path | None = None,
        floor_plan: Path | None = None,
        *,
        token: str | None = None,
        bytes_per_s: float | None = None,
    ) -> None:
        """Before start(): a Foxglove live view on `listen` (host, port; port 0 picks one) and/or a
        recording to the MCAP file `record`, drawing `floor_plan` (see drvs.server.liveview); the
        view needs `token` if given; both take in at most `bytes_per_s` (drvs.live.liveview.LiveHub).
        Needs the live extra (FailedPrecondition names it)."""
        from drvs.server.liveview import ServerView

        self.view = ServerView.open(self, listen, record, floor_plan, token=token, bytes_per_s=bytes_per_s)

    @property
    def port(self) -> int:
        return self._endpoint.port

    @property
    def address(self) -> str:
        return self._endpoint.address

    def _add_servicers(self, server: aio.Server) -> None:
        detection_pb2_grpc.add_DetectObjectBoundaryServicer_to_server(_RobotFacing(self), server)
        registry_pb2_grpc.add_RegisterVisionServiceServicer_to_server(_Registration(self), server)
        detection_pb2_grpc.add_CallbackCoordinatesServicer_to_server(_CameraReports(self), server)

    async def start(self) -> None:
        if self.shared is not None:
            await self.shared.start()
            try:  # the registry as etcd holds it before serving; if etcd does not answer, serve anyway
                await asyncio.wait_for(self.shared.synced.wait(), SHARED_SYNC_WAIT_S)
            except TimeoutError:
                log.warning("registry: etcd %s has not answered yet; serving with no camera", self.shared.endpoints)
        await self._endpoint.start()
        if self.shared is not None and self.shared.trouble:
            await self._registry_reachable(False)
        self._started_at = time.monotonic()
        self._sweeper = asyncio.get_running_loop().create_task(self._sweep_leases())
        self.door.start()
        if self.view is not None:
            self.view.start()
            hub = self.view.hub
            if hub.server is not None:
                log.info("live view on %s (open it in Foxglove)", hub.url)
            if hub.record is not None:
                log.info("recording to %s", hub.record)
        log.info("security: %s", self.describe_security())
        log.log(
            logging.INFO if self.anonymous_cameras or self._camera_credentials else logging.ERROR,
            "registration: %s",
            self.describe_registration(),
        )
        if self._endpoint.also_ports:
            log.info(
                "one of %d workers: reports of its fused requests come to %s", self.config.workers, self.report_address
            )
        log.info(
            "drvs-server listening on %s (lease %.1f s; registry %s)",
            self.address,
            self.registry.lease_ttl_s,
            f"shared in etcd {self.shared.endpoints}" if self.shared is not None else "in memory",
        )

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
        return f"NONE on a non-loopback address: anyone who can reach {self.address} can " + (
            "register cameras and ask for detections" if self.trust_network else "ask for detections"
        )

    @property
    def anonymous_cameras(self) -> bool:
        """May a camera register without a credential? On loopback, or when the operator says the
        network is trusted: elsewhere anyone who reaches the port could claim camera ids."""
        return self.trust_network or is_loopback_host(host_of(self.address))

    @property
    def _camera_credentials(self) -> bool:
        return self.tokens.tables[CAMERA] is not None or self.security.require_client_cert

    def describe_registration(self) -> str:
        kinds = []
        if self.tokens.tables[CAMERA] is not None:
            kinds.append("a camera token")
        if self.security.require_client_cert:
            kinds.append("a client certificate with the camera role (OU=camera)")
        credential = " or ".join(kinds)
        if self.anonymous_cameras and not kinds:
            why = "--trust-network" if self.trust_network else "loopback only"
            return f"open to cameras without a credential ({why}); an id is held by its registration's secret"
        if self.anonymous_cameras and self.tokens.tables[CAMERA] is None:
            why = "--trust-network" if self.trust_network else "loopback only"
            return f"cameras identify with {credential}, or register without one ({why})"
        if kinds:
            return f"cameras need {credential}"
        return (
            f"REFUSED: {self.address} is beyond this host and no camera credential is configured; give "
            "--camera-tokens or --tls-client-auth, or --trust-network if everyone on this network is trusted"
        )

    async def stop(self, grace: float = 2.0) -> None:
        if self._stopped or not self._endpoint.started:
            return
        self._stopped = True
        if self._sweeper is not None:
            self._sweeper.cancel()
        await self.door.loop.stop()
        self.fusion.end_all("the server is stopping")
        await self._endpoint.stop(grace)
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        await asyncio.gather(*(link.close() for link in self._links.values()), return_exceptions=True)
        self._links.clear()
        await self._callbacks.close()
        if self.shared is not None:
            await self.shared.stop()
        if self.view is not None:
            await self.view.stop()
            if self.view.dropped:
                log.warning("live view: %d messages dropped (too large, too fast, or behind)", self.view.dropped)
        log.info("drvs-server stopped")

    async def wait_for_termination(self) -> None:
        await self._endpoint.wait_for_termination()

    # --- registration ------------------------------------------------------------------------

    def _camera_owner(self, who: str, method: str) -> str:
        """`who`, the identity a call proved ("" anonymous: no camera token or camera certificate),
        or UNAUTHENTICATED where anonymity is not allowed."""
        if not who and not self.anonymous_cameras:
            raise Unauthenticated(
                f"{method}: this server serves {self.address}, beyond this host: a camera needs a camera "
                "token or a client certificate with the camera role (the server's --trust-network allows "
                "cameras without one)"
            )
        return who

    def _registrant(self, registration: CameraRegistration, who: str, peer: str) -> tuple[str, str, str]:
        """A registration's secrets and id checked: (camera id, owner, the quota its ids count against)."""
        for name in ("registration_secret", "forward_secret"):
            value = getattr(registration, name)
            if len(value) > MAX_SECRET_LENGTH or not (value.isascii() and value.isprintable()) or " " in value:
                raise InvalidArgument(f"{name}: at most {MAX_SECRET_LENGTH} printable ASCII characters, no spaces")
        camera_id = check_id(registration.camera_id, "camera_id")
        owner = self._camera_owner(who, "Register")
        return camera_id, owner, owner or f"the anonymous caller at {peer}"

    def register_camera(
        self, registration: CameraRegistration, who: str, peer: str, presented_token: str = ""
    ) -> tuple[CameraEntry, str]:
        """Register (or register again) a camera for identity `who` ("" anonymous): the id's claim is checked
        and granted, its lease starts, and the server forwards to it from now on presenting its
        forward secret (or `presented_token`, the token the registration carried). `peer`: the
        caller's IP, whose quota an anonymous caller's ids count against. Returns the camera's entry
        and the registration's secret, which its heartbeats and deregistration must carry."""
        camera_id, owner, quota = self._registrant(registration, who, peer)
        self.claims.check_register(
            camera_id, owner, registration.registration_secret, quota, registration.forward_secret
        )
        entry = self.registry.register(
            camera_id=camera_id,
            address=registration.address,
            homography=Homography.from_values(registration.homography, "homography"),
            image_size=registration.image_size,
            detector_kinds=set(registration.detector_kinds),
            max_range_m=registration.max_range_m or self.default_max_range_m,
            mobile=registration.mobile,
            pose_lease_s=registration.pose_lease_s,
            frame=registration.frame,
            max_speed_mps=registration.max_speed_mps,
        )
        expires = self.registry.expires_at(entry.camera_id)
        secret = self.claims.grant(entry.camera_id, owner, quota, expires, registration.forward_secret)
        metrics.CAMERAS.set(len(self.registry))
        # What the server presents on forwards: this registration's own secret (or token), never
        # the previous registration's, which could hand one camera's credential to another address.
        self._camera_tokens[entry.camera_id] = registration.forward_secret or presented_token
        self._unreachable.discard(entry.camera_id)
        self._link(entry)
        state = self.registry.mobile_state(entry.camera_id)
        log.info(
            "camera %s registered at %s by %s: %s, detectors %s",
            entry.camera_id,
            entry.address,
            owner or "an anonymous caller",
            f"field of view {entry.field_of_view.area:.1f} m²"
            if state is None
            else f"mobile, {state.base_fov.area if state.base_fov is not None else 0.0:.1f} m² in its base frame"
            + (f" (unroutable: {state.no_floor})" if state.no_floor else ""),
            ",".join(sorted(entry.detector_kinds)),
        )
        return entry, secret

    # --- the registry shared in etcd (--registry etcd://...) ---------------------------------------

    def _shared(self) -> SharedRegistry:
        assert self.shared is not None
        return self.shared

    async def register_camera_shared(
        self, registration: CameraRegistration, who: str, peer: str, presented_token: str = ""
    ) -> tuple[CameraEntry, str]:
        """`register_camera` on a registry shared in etcd: the id's holder is read from etcd (another
        server may have registered it), the registration is checked as always, then stored by
        compare-and-put under a new etcd lease; every server (this one at once) routes to it.
        UNAVAILABLE while etcd cannot be reached."""
        shared = self._shared()
        camera_id, owner, quota = self._registrant(registration, who, peer)
        previous = await shared.get(camera_id)
        self.claims.adopt(camera_id, previous.claim() if previous is not None else None)
        self.claims.check_register(
            camera_id, owner, secret_digest(registration.registration_secret), quota, registration.forward_secret
        )
        max_range_m = registration.max_range_m or self.default_max_range_m
        _, state = self.registry.check(
            camera_id, registration.address, Homography.from_values(registration.homography, "homography"),
            registration.image_size, set(registration.detector_kinds), max_range_m, frame=registration.frame,
            mobile=registration.mobile, pose_lease_s=registration.pose_lease_s,
            max_speed_mps=registration.max_speed_mps,
        )  # fmt: skip
        record = Record(
            camera_id=camera_id,
            address=registration.address,
            homography=tuple(float(v) for v in registration.homography),
            image_size=registration.image_size,
            detector_kinds=tuple(sorted(set(registration.detector_kinds))),
            max_range_m=max_range_m,
            owner=owner,
            quota=quota,
            secret=secret_digest(secret := secrets.token_urlsafe(24)),  # etcd keeps its digest only
            forward_secret=registration.forward_secret or presented_token,
            server=self.address,
            registered_at=time.time(),
            frame=check_frame(registration.frame),
            mobile=registration.mobile,
            pose_lease_s=state.pose_lease_s if state is not None else 0.0,
        )
        shared.registrations.take(quota)  # each one a write etcd keeps until it is compacted
        self.claims.reserve(camera_id, quota)  # no await since check_register: concurrent ones count
        try:
            stored = await shared.put(record, previous, self.registry.lease_ttl_s)
        finally:
            self.claims.unreserve(camera_id, quota)  # held from here on (_apply_shared), or failed
        shared.records[camera_id] = stored
        entry = self._apply_shared(stored)
        if state is not None and (applied := self.registry.mobile_state(camera_id)) is not None:
            applied.max_speed_mps = state.max_speed_mps  # the speed its updates here are held to
        return entry, secret

    async def _held_record(self, camera_id: str, who: str, registration_secret: str, method: str) -> Record:
        """The id's record in etcd, once the caller is shown to hold it (as etcd records the holder)."""
        check_id(camera_id, "camera_id")
        owner = self._camera_owner(who, method)
        record = await self._shared().get(camera_id)
        if record is None:
            raise NotFound(f"camera_id: {camera_id!r} is not registered")
        self.claims.adopt(camera_id, record.claim())
        self.claims.check(camera_id, owner, secret_digest(registration_secret))
        return record

    async def renew_camera_shared(self, camera_id: str, who: str, registration_secret: str) -> None:
        """A heartbeat through any server: the holder (as etcd records it) keeps the etcd lease alive."""
        record = await self._held_record(camera_id, who, registration_secret, "Heartbeat")
        if not await self._shared().renew(record):
            raise NotFound(f"camera_id: {camera_id!r}'s lease expired; register again")
        self._unreachable.discard(camera_id)
        log.debug("camera %s: heartbeat; its lease in etcd renewed", camera_id)

    async def deregister_camera_shared(self, camera_id: str, who: str, registration_secret: str) -> None:
        """The holder leaves through any server: its key goes from etcd, and every server drops it."""
        record = await self._held_record(camera_id, who, registration_secret, "Deregister")
        await self._shared().delete(record)
        self._shared().records.pop(camera_id, None)
        self._drop_shared(camera_id, "deregistered")

    @property
    def report_address(self) -> str:
        """Where cameras send a fused request's reports: `advertise`, else the bound address unless
        it is a wildcard ("": the server each camera registered with, which is this one when a
        camera knows a single server)."""
        if self._endpoint.also_ports:  # one of several workers: its own port
            host = host_of(self.config.advertise or self.config.listen)
            return format_address(host, self._endpoint.also_ports[0])
        if self.config.advertise:
            return self.config.advertise
        host = host_of(self.config.listen)
        return "" if host in WILDCARDS else self.address

    async def _registry_reachable(self, reachable: bool) -> None:
        """Health says whether registrations can be taken: the registration service is NOT_SERVING
        while etcd cannot be reached (routing, the whole process's health, goes on)."""
        await self._endpoint.set_service_serving(REGISTRATION_SERVICE, reachable)

    def _apply_shared(self, record: Record) -> CameraEntry:
        """A registration etcd holds (made through this server or another): routed here until its
        key goes; the id held as recorded; forwards present the camera's forward secret."""
        entry, state = self.registry.check(
            record.camera_id, record.address, Homography.from_values(record.homography, "homography"),
            record.image_size, set(record.detector_kinds), record.max_range_m, frame=record.frame,
            mobile=record.mobile, pose_lease_s=record.pose_lease_s,
        )  # fmt: skip
        self.registry.store(entry, state)
        self.registry.hold(entry.camera_id)  # etcd's lease decides when it goes
        self.claims.adopt(entry.camera_id, record.claim())
        self._camera_tokens[entry.camera_id] = record.forward_secret
        self._unreachable.discard(entry.camera_id)
        self._lost.pop(entry.camera_id, None)
        self._link(entry)
        metrics.CAMERAS.set(len(self.registry))
        log.info(
            "camera %s registered at %s through %s (shared registry): field of view %.1f m², detectors %s",
            entry.camera_id,
            entry.address,
            record.server or "another server",
            entry.field_of_view.area,
            ",".join(sorted(entry.detector_kinds)),
        )
        return entry

    def _apply_shared_pose(self, camera_id: str, pose: PoseRecord) -> None:
        """A mobile camera's pose another server took: its field of view moves here too (the rate
        was checked where the update came in), and it may join this server's tracks."""
        entry = self.registry.update_pose(camera_id, Pose2(pose.x, pose.y, pose.yaw), pose.time_unix, check_rate=False)
        log.debug(POSE_APPLIED, camera_id, pose.x, pose.y, pose.yaw, "from the shared registry")
        self._pick_up(entry)

    def _drop_shared(self, camera_id: str, why: str, lapsed: bool = False) -> None:
        """A registration etcd no longer holds: out of routing here, its id free; `lapsed` (its
        lease ran out without it deregistering): remembered as lost, as `_sweep_leases` does."""
        self.claims.release(camera_id)
        entry = self.registry.remove(camera_id) if camera_id in self.registry else None
        self._forget(camera_id)
        if lapsed and entry is not None:
            self._remember_lost(entry, why)
        metrics.CAMERAS.set(len(self.registry))
        log.info("camera %s left routing: %s", camera_id, why)

    def update_pose(
        self, camera_id: str, who: str, registration_secret: str, pose: Pose2, pose_time_unix: float = 0.0
    ) -> CameraEntry:
        """A mobile camera's new pose, from the id's holder with its registration's secret: its field
        of view moves there and is routed for its pose lease (see Registry.update_pose).

        A camera routable now (a fresh pose that puts its field of view on the floor, and not
        skipped after a failed forward) joins every continuous fused request in flight whose region
        its new field of view meets and whose object type it serves, for what remains of the
        request (`_pick_up`). Fused single shots are not extended (they answer once, soon), nor are
        continuous requests without fusion: their cameras report straight to the robot's callback,
        and the robot asked the cameras the dispatch named."""
        check_id(camera_id, "camera_id")
        owner = self._camera_owner(who, "UpdatePose")
        self.claims.check(camera_id, owner, secret_digest(registration_secret) if self.shared else registration_secret)
        try:
            if self.shared is not None:  # each one a write etcd keeps until compacted
                self.shared.admit_pose(camera_id)
            entry = self.registry.update_pose(camera_id, pose, pose_time_unix)
        except DrvsError as exc:
            metrics.POSE_UPDATES.labels(outcome=exc.code.lower()).inc()
            raise
        metrics.POSE_UPDATES.labels(outcome="ok").inc()
        log.debug(POSE_APPLIED, camera_id, pose.x, pose.y, pose.yaw, "")
        if self.shared is not None:  # the other servers route it by this pose too
            self.shared.share_pose(camera_id, PoseRecord(pose.x, pose.y, pose.yaw, pose_time_unix, self.shared.origin))
        self._pick_up(entry)
        return entry

    def _pick_up(self, camera: CameraEntry) -> None:
        """Ask a mobile camera that just moved to join the continuous fused requests in flight that
        it was not asked for and now can serve: routable as `plan` would route it, serving the
        request's object type, its field of view meeting the region with positive area (as
        Registry.cameras_seeing tests), and at least one period of the request left."""
        fov = camera.field_of_view
        for left in self.fusion.leave(camera.camera_id, fov):
            log.info("fused request %s: mobile camera %s left its region", left.request_id, camera.camera_id)
        if fov.is_empty or camera.camera_id in self._unreachable or self.registry.unroutable(camera.camera_id):
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
                self._join(session, camera)
            elif session.rejoin(camera.camera_id):
                log.info("fused request %s: mobile camera %s is back over its region", session.request_id,
                         camera.camera_id)  # fmt: skip

    def _join(self, session: Continuous, camera: CameraEntry) -> None:
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
            self._forward(camera, session.request, message, session.secret, session=session)
        finally:
            logs.request_id.reset(token)

    def renew_camera(self, camera_id: str, who: str, registration_secret: str) -> None:
        """A heartbeat: the id's holder, with its registration's secret, renews the lease; a camera
        skipped after a failed forward is routed to again."""
        check_id(camera_id, "camera_id")
        owner = self._camera_owner(who, "Heartbeat")
        self.claims.check(camera_id, owner, registration_secret)
        self.registry.renew(camera_id)
        self.claims.renew(camera_id, self.registry.expires_at(camera_id))
        self._unreachable.discard(camera_id)

    def deregister_camera(self, camera_id: str, who: str, registration_secret: str) -> None:
        """The id's holder leaves: out of routing, its id free at once, its link closed."""
        check_id(camera_id, "camera_id")
        owner = self._camera_owner(who, "Deregister")
        self.claims.check(camera_id, owner, registration_secret)
        self.claims.release(camera_id)
        if camera_id in self.registry:
            self.registry.remove(camera_id)
        self._forget(camera_id)
        metrics.CAMERAS.set(len(self.registry))
        log.info("camera %s deregistered", camera_id)

    def list_cameras(
        self, region: Polygon | None = None, page_token: str = "", page_size: int = 0, frame: str = ""
    ) -> tuple[list[CameraEntry], str]:
        """One page of the live cameras (those of `frame`, "" every frame, that see `region`, if
        given), sorted by id, after the id `page_token` names; `page_size` 0 or above MAX_PAGE_SIZE
        means MAX_PAGE_SIZE. Returns the page and the next page's token ("" on the last page)."""
        if page_token:
            check_id(page_token, "page_token")
        only = check_frame(frame) if frame else None
        size = min(page_size or DEFAULT_PAGE_SIZE, MAX_PAGE_SIZE)
        if region is None:
            entries = [e for e in self.registry.cameras() if only is None or e.frame == only]
        else:
            entries = self.registry.cameras_seeing(region, frame=only)
        # Both lists are sorted by camera id: a page starts after the id its token names.
        start = bisect.bisect_right([e.camera_id for e in entries], page_token) if page_token else 0
        more = len(entries) > start + size
        entries = entries[start : start + size]
        return entries, entries[-1].camera_id if more else ""

    def camera_info(self, e: CameraEntry) -> registry_pb2.CameraInfo:
        """A camera as ListCameras describes it."""
        registry = self.registry
        info = registry_pb2.CameraInfo(
            camera_id=e.camera_id,
            address=e.address,
            field_of_view=polygon_to_pb(e.field_of_view) if not e.field_of_view.is_empty else None,
            detector_kinds=sorted(e.detector_kinds),
            # (0 on a registry shared in etcd: etcd's lease decides, renewed through any server.)
            lease_remaining_s=left if math.isfinite(left := registry.remaining_s(e.camera_id)) else 0.0,
            frame=e.frame,
        )
        state = registry.mobile_state(e.camera_id)
        if state is not None:
            info.mobile = True
            info.unroutable = registry.unroutable(e.camera_id)
            if state.pose is not None:
                info.pose.CopyFrom(pose_to_pb(state.pose))
                info.pose_age_s = registry.pose_age_s(e.camera_id)
        return info

    # --- routing ---------------------------------------------------------------------------

    def route(self, request: DetectionRequest) -> list[CameraEntry]:
        """The live cameras that see the request's region, run its detector and are reachable."""
        return self.plan(request)[0]

    def plan(self, request: DetectionRequest) -> tuple[list[CameraEntry], list[MissingCamera]]:
        """The cameras to ask, and those that see the region and run the detector but will not be
        asked: skipped after a failed forward, or gone without deregistering."""
        seeing = self.registry.cameras_seeing(request.region, request.kind, request.frame)
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

    def _uncovered(self, region: Polygon, cameras: list[CameraEntry]) -> list[geometry_pb2.Polygon]:
        """`uncovered`, encoded, kept per region object and cameras: robots ask about the same
        regions again and again (a stream sends a repeated region once)."""
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
        return max(0.0, self._started_at + self.warm_up_s - time.monotonic())

    def dispatch(
        self,
        request: DetectionRequest,
        message: detection_pb2.DetectionRequest,
        secret: bytes = b"",
        plan: tuple[list[CameraEntry], list[MissingCamera]] | None = None,
        on_none_accepted: Callable[[], None] | None = None,
        session: FusionSession | None = None,
    ) -> detection_pb2.DetectionReply:
        """Forward to every camera planned (`plan`, by default the one `plan()` makes) and answer the
        robot: whom it asked, whom it could not, and what part of the region nobody looks at.
        `secret`: the robot's report secret (a fused request's: the server's own for it). `on_none_accepted`
        is called once if every camera refused or failed the request (so it holds no resources
        anywhere). `session`: a fused request's, told of cameras that do not take it."""
        cameras, missing = self.plan(request) if plan is None else plan
        outcome = _Outcome(len(cameras), on_none_accepted)
        for camera in cameras:
            self._forward(camera, request, message, secret, outcome, session)
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
        reply.uncovered.extend(self._uncovered(request.region, cameras))
        uncertain = self.coverage_uncertain_s()
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
        slots: _Slots | None = None,
    ) -> detection_pb2.DetectionReply:
        """A robot's validated request (`request`, and `message` as it is to be forwarded): refused
        if no camera serves its type; counted against `robot`'s limits; its callback checked against
        the robot's address `peer` (once per address per call: `checked_callbacks`); forwarded to the
        cameras that see its region. `secret`: the robot's report secret. `slots`: the continuous
        requests of the robot's request stream, freed when cancelled. The reply, at once."""
        plan = self.plan(request)
        cameras = plan[0]
        if not cameras and not plan[1]:
            self.refuse_unserved(request)
        # What this request costs the cameras, counted against the robot's budget (not what it
        # cost the robot to send: on a stream a repeated region is left out). The robot's own
        # budget first: one over it hears so, not that the server is busy.
        limits = self.limits
        size = message.ByteSize()
        slot = limits.admit(robot, request.continuous.duration_s, size * len(cameras))
        try:
            self.admit(cameras)
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
        delivery: Any,
        slots: _Slots | None = None,
        on_end: Callable[[FusionSession], None] | None = None,
    ) -> tuple[detection_pb2.DetectionReply, FusionSession]:
        """A robot's validated fused request: counted against `robot`'s limits as any request,
        forwarded to the cameras that see its region with `report_to_server` and a key per camera
        from a secret made for it, and gathered by a FusionSession whose replies go to `delivery`
        (fusion_session.Delivery). Returns the reply to the request as dispatched (a single shot's
        session answers with it later, its snapshot added) and the session. `on_end`: called when
        the session ends."""
        self.fusion.check_room()
        plan = self.plan(request)
        cameras, missing = plan
        if not cameras and not missing:
            self.refuse_unserved(request)
        limits = self.limits
        # The cameras report to the server, with outlines (fusion matches by them); no callback.
        message.ClearField("fusion")
        message.callback_address = ""
        message.report_to_server = True
        message.report_address = self.report_address
        message.omit_outlines = False
        # The cameras know it by an id unique in this server (robots choose theirs, and two may
        # choose the same): a cancel one robot's request sends a camera stops no other's.
        forward_id = f"{request.request_id[:100]}:{next(self._fused_ids):x}"
        message.request_id = forward_id
        size = message.ByteSize()
        slot = limits.admit(robot, request.continuous.duration_s, size * len(cameras))
        single_shot = request.continuous.single_shot
        try:
            self.admit(cameras, fused=single_shot)
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
            # A continuous one keeps what it forwards: a mobile camera may join it later (_pick_up).
            None if single_shot else message,
        )
        self.fusion.add(session)
        reply = self.dispatch(request, message, secret, plan, session=session)
        session.start(reply)
        metrics.FORWARDED_BYTES.inc(size * len(cameras))
        return reply, session

    def admit(self, cameras: list[CameraEntry], fused: bool = False) -> None:
        """The door, once a request is routed: ResourceExhausted, before anything is forwarded, if a
        camera it needs has as many forwards waiting as it may, or its link is shedding this one."""
        links = [(c.camera_id, self._link(c)) for c in cameras]
        for camera_id, link in links:
            waiting = link.requests.in_flight
            if waiting >= self.max_queued_forwards:
                link.delay.shedder.congested()
                metrics.ADMISSION_REFUSED("queue").inc()
                raise ResourceExhausted(
                    f"busy: camera {camera_id} has {waiting} requests already waiting for it "
                    f"(limit {self.max_queued_forwards}); retry in 100 ms",
                    retry_after_s=0.1,
                )
        self.door.check_cameras(((camera_id, link.delay.shedder) for camera_id, link in links), fused)

    def _homography_of(self, camera_id: str) -> Homography | None:
        if camera_id not in self.registry:
            return None
        return self.registry.get(camera_id).homography

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
            link = _CameraLink(camera.address, self.security, token, self.forward_timeout_s, self.door.link())
            self._links[camera.camera_id] = link
        return link

    def _forward(
        self,
        camera: CameraEntry,
        request: DetectionRequest,
        message: detection_pb2.DetectionRequest,
        secret: bytes = b"",
        outcome: _Outcome | None = None,
        session: FusionSession | None = None,
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
                current = self._links.get(camera.camera_id) is link
                self._not_accepted(camera, request, result, key, mark_unreachable=current, session=session)
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

    def _not_accepted(
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
        if self._stopped:
            return  # the server's own shutdown closed the links: nobody is waiting to hear
        metrics.ROUTED_FAILED.inc()
        token = logs.request_id.set(request.request_id)
        try:
            # What failed on the hop itself stays in the log (routing_errors): the robot hears UNAVAILABLE.
            code, said = self._routing_errors.for_robot(camera.camera_id, exc, request.request_id)
            reason = f"camera {camera.camera_id} did not accept the request: {code} {said}"
            if code in KEPT:
                log.warning("request %s: %s", request.request_id, reason)
            if mark_unreachable and isinstance(exc, (Unavailable, DeadlineExceeded)):
                self._unreachable.add(camera.camera_id)
                self._unreachable_why[camera.camera_id] = f"{code} {said}"
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
        self._routing_errors.forget(camera_id)
        self._lost.pop(camera_id, None)
        self._camera_tokens.pop(camera_id, None)
        link = self._links.pop(camera_id, None)
        if link is not None:
            self._spawn(link.close())

    def _remember_lost(self, entry: CameraEntry, why: str) -> None:
        """It did not deregister: requests whose region it saw say it is missing (`plan`)."""
        self._lost[entry.camera_id] = (entry, time.monotonic(), why)
        while len(self._lost) > MAX_LOST:
            self._lost.popitem(last=False)

    async def _sweep_leases(self) -> None:
        period = min(1.0, self.registry.lease_ttl_s / 4)
        while True:
            await asyncio.sleep(period)
            for entry in self.registry.expire():
                log.info("camera %s left routing: lease expired", entry.camera_id)
                self._forget(entry.camera_id)
                self._remember_lost(entry, "its lease ran out without it deregistering")
                metrics.CAMERAS.set(len(self.registry))
            for camera_id in self.claims.expire():
                if camera_id not in self.registry:
                    log.info("camera id %s is free: its lease and grace ran out", camera_id)


class _RobotFacing(detection_pb2_grpc.DetectObjectBoundaryServicer):
    def __init__(self, server: DrvsServer) -> None:
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
        slots: _Slots | None = None,
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
        slots: _Slots | None,
        stream: _FusedOnStream | None = None,
    ) -> detection_pb2.DetectionReply | None:
        self._s.door.check_server()  # first: a server past capacity spends nothing more on it
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
        return await self._s.submit(request, message, secret, robot, peer, allowed, slots)

    async def _fused(
        self,
        request: DetectionRequest,
        message: detection_pb2.DetectionRequest,
        robot: str,
        slots: _Slots | None,
        stream: _FusedOnStream | None,
    ) -> detection_pb2.DetectionReply | None:
        """A fused request: on a stream, its replies go on the stream's queue (a single shot's one
        reply when it is ready: None now); on DetectObjects (single shots only), awaited here."""
        single_shot = request.continuous.single_shot
        if stream is None:
            if not single_shot:
                raise InvalidArgument(FUSED_CONTINUOUS_UNARY)
            delivery = _CallDelivery()
            _, session = self._s.submit_fused(request, message, robot, delivery)
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
            reply, session = self._s.submit_fused(
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
        slots = _Slots(self._s.limits, robot)
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


class _CameraReports(detection_pb2_grpc.CallbackCoordinatesServicer):
    """Cameras' reports for fused requests (CallbackCoordinates, as a robot serves it): only cameras
    may call (a camera token or a camera certificate where those are configured, as for
    registration); each stream is a ReportIntake, which takes only the reports a key proves."""

    def __init__(self, server: DrvsServer) -> None:
        self._s = server

    async def ReportDetections(
        self,
        request_iterator: AsyncIterator[detection_pb2.DetectionReport],
        context: aio.ServicerContext[Any, Any],
    ) -> None:
        server = self._s
        try:
            who = camera_identity(context, server.tokens, server.security.require_client_cert, "ReportDetections")
            server._camera_owner(who, "ReportDetections")
        except DrvsError as exc:
            # Take the first message before refusing (see security._refusal).
            with contextlib.suppress(Exception):
                await asyncio.wait_for(anext(aiter(request_iterator)), 1.0)
            await context.abort(_grpc.status_of(exc), str(exc))
        view = server.view
        seen = view.report if view is not None else None
        await serve_report_stream(request_iterator, context, ReportIntake(server.fusion, context.peer()), seen)


class _Registration(registry_pb2_grpc.RegisterVisionServiceServicer):
    """Converts and delegates: protobuf and call context in, `DrvsServer`'s registration methods
    called, protobuf out."""

    def __init__(self, server: DrvsServer) -> None:
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
        if self._s.shared is not None:
            entry, secret = await self._s.register_camera_shared(registration, who, peer, token)
        else:
            entry, secret = self._s.register_camera(registration, who, peer, token)
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
        if self._s.shared is not None:
            await self._s.renew_camera_shared(message.camera_id, who, message.registration_secret)
        else:
            self._s.renew_camera(message.camera_id, who, message.registration_secret)
        return registry_pb2.HeartbeatReply(lease_ttl_s=self._s.registry.lease_ttl_s)

    @_grpc.servicer_method
    async def UpdatePose(
        self, message: registry_pb2.UpdatePoseRequest, context: aio.ServicerContext[Any, Any]
    ) -> registry_pb2.UpdatePoseReply:
        if not message.HasField("pose"):
            raise InvalidArgument("pose: missing")
        entry = self._s.update_pose(
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
        if self._s.shared is not None:
            await self._s.deregister_camera_shared(message.camera_id, who, message.registration_secret)
        else:
            self._s.deregister_camera(message.camera_id, who, message.registration_secret)
        return registry_pb2.DeregisterReply()

    @_grpc.servicer_method
    async def ListCameras(
        self, message: registry_pb2.ListCamerasRequest, context: aio.ServicerContext[Any, Any]
    ) -> registry_pb2.ListCamerasReply:
        region = region_from_pb(message.region) if message.HasField("region") else None
        entries, next_token = self._s.list_cameras(region, message.page_token, message.page_size, message.frame)
        return registry_pb2.ListCamerasReply(
            next_page_token=next_token,
            cameras=[self._s.camera_info(e) for e in entries],
        )

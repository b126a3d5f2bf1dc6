"""The DRVS server: routes robots' requests to the cameras that see the region.

`DrvsServer` starts, wires and stops the rooms that do the work, each a module of its own:
registration.py (cameras register, heartbeat, leave; leases swept; in memory or shared in etcd),
routing.py (which cameras a request goes to; what floor nobody sees), dispatch.py (limits,
admission, dispatch, fused requests), forwarding.py (the links to cameras), mobile.py (mobile
cameras' poses and pick-ups), listing.py (ListCameras) and servicers.py (the gRPC services)."""

from __future__ import annotations

import asyncio
import importlib
import logging
import time
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from grpc import aio

from drvs.core.errors import InvalidArgument, Unauthenticated
from drvs.core.net import format_address, host_of, is_loopback_host
from drvs.server.admission import Door
from drvs.server.claims import Claims
from drvs.server.config import (
    DEFAULT_LISTEN,
    WILDCARDS,
    ServerConfig,
)
from drvs.server.dispatch import Dispatcher
from drvs.server.forwarding import Forwarder
from drvs.server.fusion_session import FusionSessions
from drvs.server.listing import camera_info
from drvs.server.mobile import MobileCameras
from drvs.server.policy import CallbackPolicy, RequestLimits
from drvs.server.registration import EtcdBackend, MemoryBackend, RegistryBackend
from drvs.server.registry import CameraEntry, Registry
from drvs.server.routing import Routing
from drvs.server.servicers import add_servicers
from drvs.server.shared import SharedRegistry
from drvs.v1 import detection_pb2, registry_pb2
from drvs.wire import _grpc
from drvs.wire._service import Endpoint, Lifecycle
from drvs.wire.security import CAMERA, Security, TokenAuthority, TokenInterceptor

if TYPE_CHECKING:
    from drvs.server.liveview import ServerView

log = logging.getLogger("drvs.server")

SERVICE_NAMES = (
    detection_pb2.DESCRIPTOR.services_by_name["DetectObjectBoundary"].full_name,
    registry_pb2.DESCRIPTOR.services_by_name["RegisterVisionService"].full_name,
    detection_pb2.DESCRIPTOR.services_by_name["CallbackCoordinates"].full_name,
)
REGISTRATION_SERVICE = SERVICE_NAMES[1]


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
        #: Admission: past capacity requests are refused here, before anything is forwarded.
        self.door = Door(config.admission_target_s)
        self._sweeper: asyncio.Task[None] | None = None
        #: Fused requests in flight, whose cameras report here (fusion_session.py).
        self.fusion = FusionSessions()
        self._stopped = False
        #: The rooms (see the module's docstring), wired together.
        # After a start, cameras registered with a previous run may not be back yet for warm_up_s.
        self.routing = Routing(self.registry, config.warm_up)
        self.forwarder = Forwarder(
            self.security, self.forward_timeout_s, self.max_queued_forwards, self.door, self.routing
        )
        self.dispatcher = Dispatcher(
            registry=self.registry,
            routing=self.routing,
            forwarder=self.forwarder,
            limits=self.limits,
            door=self.door,
            callback_policy=self.callback_policy,
            fusion=self.fusion,
            report_address=lambda: self.report_address,
        )
        rooms = (self.registry, self.claims, self.routing, self.forwarder)
        self.registrations: RegistryBackend
        if config.registry != "memory":
            self.registrations = EtcdBackend(
                *rooms,
                owner=self.camera_owner,
                default_max_range_m=self.default_max_range_m,
                config=config,
                server_address=lambda: self.address,
                on_reachable=self._registry_reachable,
                on_moved=lambda entry: self.mobile.pick_up(entry),
            )
        else:
            self.registrations = MemoryBackend(
                *rooms, owner=self.camera_owner, default_max_range_m=self.default_max_range_m
            )
        self.mobile = MobileCameras(self.registry, self.routing, self.fusion, self.forwarder, self.registrations)
        #: The registry's etcd side when it is shared with other servers (--registry etcd://...).
        self.shared: SharedRegistry | None = self.registrations.shared
        #: The live view and recording (--foxglove, --record): see `show`.
        self.view: ServerView | None = None

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

    @property
    def warm_up_s(self) -> float:
        """After a start, cameras registered with a previous run may not be back yet for this long."""
        return self.routing.warm_up_s

    @property
    def _unreachable(self) -> set[str]:
        """Cameras skipped after a failed forward until they heartbeat (routing.py)."""
        return self.routing.unreachable

    def _add_servicers(self, server: aio.Server) -> None:
        add_servicers(server, self)

    async def start(self) -> None:
        # The fused path's assignment solver (scipy.optimize, about half of this package's import
        # time) is imported as the server starts, not with the package (drvs.server.fusion and
        # .tracking import it where they use it): a process that only uses the registry or the
        # config (the benchmarks' helper processes) never pays it, and a serving server never
        # stalls its event loop on it at its first fused request.
        importlib.import_module("scipy.optimize")
        await self.registrations.open()
        await self._endpoint.start()
        await self.registrations.serving()
        self.routing.started_at = time.monotonic()
        self._sweeper = asyncio.get_running_loop().create_task(self.registrations.sweep_leases())
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
            self.registrations.describe(),
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
        self.forwarder.stopped = True
        if self._sweeper is not None:
            self._sweeper.cancel()
        await self.door.loop.stop()
        self.fusion.end_all("the server is stopping")
        await self._endpoint.stop(grace)
        await self.forwarder.close()
        await self.registrations.close()
        if self.view is not None:
            await self.view.stop()
            if self.view.dropped:
                log.warning("live view: %d messages dropped (too large, too fast, or behind)", self.view.dropped)
        log.info("drvs-server stopped")

    async def wait_for_termination(self) -> None:
        await self._endpoint.wait_for_termination()

    def camera_owner(self, who: str, method: str) -> str:
        """`who`, the identity a call proved ("" anonymous: no camera token or camera certificate),
        or UNAUTHENTICATED where anonymity is not allowed."""
        if not who and not self.anonymous_cameras:
            raise Unauthenticated(
                f"{method}: this server serves {self.address}, beyond this host: a camera needs a camera "
                "token or a client certificate with the camera role (the server's --trust-network allows "
                "cameras without one)"
            )
        return who

    def camera_info(self, e: CameraEntry) -> registry_pb2.CameraInfo:
        """A camera as ListCameras describes it (listing.py)."""
        return camera_info(self.registry, e)

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

"""Registration: cameras register, heartbeat and leave, and their leases are swept.

Two backends behind one `RegistryBackend` Protocol: `MemoryBackend` (this server's registry is the
registry) and `EtcdBackend` (the registry shared in etcd with other servers, --registry
etcd://...). Servicers and the server call the Protocol; neither branches on which it is."""

from __future__ import annotations

import asyncio
import logging
import secrets
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Protocol

from drvs.core.errors import InvalidArgument, NotFound
from drvs.core.geometry import Homography
from drvs.core.model import DEFAULT_FRAME, Pose2, check_frame, check_id
from drvs.server.claims import Claims
from drvs.server.config import ServerConfig
from drvs.server.etcd import Endpoints, EtcdClient
from drvs.server.forwarding import Forwarder
from drvs.server.registry import CameraEntry, Registry
from drvs.server.routing import Routing
from drvs.server.shared import PoseRecord, Record, SharedRegistry, secret_digest
from drvs.wire import metrics

log = logging.getLogger("drvs.server")

#: How long a server sharing its registry in etcd waits for it at start before serving, seconds.
SHARED_SYNC_WAIT_S = 5.0
#: Longest secret a camera may hand over (it travels as call metadata on every forward).
MAX_SECRET_LENGTH = 256
#: The DEBUG line of every pose a mobile camera's field of view moves to (tests wait on it).
POSE_APPLIED = "camera %s at pose x=%.3f y=%.3f yaw=%.4f %s"

#: `who` (the identity a call proved, "" anonymous) and the method: the owner, or Unauthenticated.
OwnerCheck = Callable[[str, str], str]


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


class RegistryBackend(Protocol):
    """Where registrations are kept: this server's memory, or etcd shared with other servers."""

    #: The etcd side when the registry is shared, else None.
    shared: SharedRegistry | None

    def describe(self) -> str:
        """Where the registry is, for the start-up log line."""

    async def open(self) -> None:
        """Before the server serves: the registry as it stands read in."""

    async def serving(self) -> None:
        """Once the server serves."""

    async def close(self) -> None:
        """At the server's stop."""

    async def register(
        self, registration: CameraRegistration, who: str, peer: str, presented_token: str = ""
    ) -> tuple[CameraEntry, str]:
        """Register (or register again) a camera for identity `who` ("" anonymous): the id's claim is
        checked and granted, its lease starts, and the server forwards to it from now on presenting
        its forward secret (or `presented_token`, the token the registration carried). `peer`: the
        caller's IP, whose quota an anonymous caller's ids count against. Returns the camera's entry
        and the registration's secret, which its heartbeats and deregistration must carry."""

    async def renew(self, camera_id: str, who: str, registration_secret: str) -> None:
        """A heartbeat: the id's holder, with its registration's secret, renews the lease; a camera
        skipped after a failed forward is routed to again."""

    async def deregister(self, camera_id: str, who: str, registration_secret: str) -> None:
        """The id's holder leaves: out of routing, its id free at once, its link closed."""

    def check_holder(self, camera_id: str, who: str, registration_secret: str, method: str) -> None:
        """The caller holds `camera_id` (with its registration's secret), or the claim's error."""

    def admit_pose(self, camera_id: str) -> None:
        """A pose update may be taken now (ResourceExhausted past the pose write rate)."""

    def share_pose(self, camera_id: str, pose: Pose2, pose_time_unix: float) -> None:
        """A pose this server took, for the other servers that route the camera too."""

    async def sweep_leases(self) -> None:
        """Runs while the server does: cameras whose lease ran out leave routing."""


class _Backend:
    """What both backends share: the registry, the claims on ids, and what a camera leaving does."""

    shared: SharedRegistry | None = None

    def __init__(
        self,
        registry: Registry,
        claims: Claims,
        routing: Routing,
        forwarder: Forwarder,
        *,
        owner: OwnerCheck,
        default_max_range_m: float,
    ) -> None:
        self.registry = registry
        self.claims = claims
        self.routing = routing
        self.forwarder = forwarder
        self.owner = owner
        self.default_max_range_m = default_max_range_m

    async def open(self) -> None:
        pass

    async def serving(self) -> None:
        pass

    async def close(self) -> None:
        pass

    def _registrant(self, registration: CameraRegistration, who: str, peer: str) -> tuple[str, str, str]:
        """A registration's secrets and id checked: (camera id, owner, the quota its ids count against)."""
        for name in ("registration_secret", "forward_secret"):
            value = getattr(registration, name)
            if len(value) > MAX_SECRET_LENGTH or not (value.isascii() and value.isprintable()) or " " in value:
                raise InvalidArgument(f"{name}: at most {MAX_SECRET_LENGTH} printable ASCII characters, no spaces")
        camera_id = check_id(registration.camera_id, "camera_id")
        owner = self.owner(who, "Register")
        return camera_id, owner, owner or f"the anonymous caller at {peer}"

    def admit_pose(self, camera_id: str) -> None:
        pass

    def share_pose(self, camera_id: str, pose: Pose2, pose_time_unix: float) -> None:
        pass

    def forget(self, camera_id: str) -> None:
        """It left routing: forgotten by routing and its link closed."""
        self.routing.forget(camera_id)
        self.forwarder.forget(camera_id)

    async def sweep_leases(self) -> None:
        period = min(1.0, self.registry.lease_ttl_s / 4)
        while True:
            await asyncio.sleep(period)
            for entry in self.registry.expire():
                log.info("camera %s left routing: lease expired", entry.camera_id)
                self.forget(entry.camera_id)
                self.routing.remember_lost(entry, "its lease ran out without it deregistering")
                metrics.CAMERAS.set(len(self.registry))
            for camera_id in self.claims.expire():
                if camera_id not in self.registry:
                    log.info("camera id %s is free: its lease and grace ran out", camera_id)


class MemoryBackend(_Backend):
    """The registry in this server's memory: leases and claims kept here."""

    def describe(self) -> str:
        return "in memory"

    async def register(
        self, registration: CameraRegistration, who: str, peer: str, presented_token: str = ""
    ) -> tuple[CameraEntry, str]:
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
        self.forwarder.camera_tokens[entry.camera_id] = registration.forward_secret or presented_token
        self.routing.unreachable.discard(entry.camera_id)
        self.forwarder.link(entry)
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

    def check_holder(self, camera_id: str, who: str, registration_secret: str, method: str) -> None:
        self.claims.check(camera_id, self.owner(who, method), registration_secret)

    async def renew(self, camera_id: str, who: str, registration_secret: str) -> None:
        check_id(camera_id, "camera_id")
        self.check_holder(camera_id, who, registration_secret, "Heartbeat")
        self.registry.renew(camera_id)
        self.claims.renew(camera_id, self.registry.expires_at(camera_id))
        self.routing.unreachable.discard(camera_id)

    async def deregister(self, camera_id: str, who: str, registration_secret: str) -> None:
        check_id(camera_id, "camera_id")
        self.check_holder(camera_id, who, registration_secret, "Deregister")
        self.claims.release(camera_id)
        if camera_id in self.registry:
            self.registry.remove(camera_id)
        self.forget(camera_id)
        metrics.CAMERAS.set(len(self.registry))
        log.info("camera %s deregistered", camera_id)


class EtcdBackend(_Backend):
    """The registry shared in etcd (--registry etcd://...): every server routes every camera; a
    registration, heartbeat or deregistration may come through any of them. UNAVAILABLE while etcd
    cannot be reached; `on_reachable` is told each time that changes (the server's health)."""

    shared: SharedRegistry | None

    def __init__(
        self,
        registry: Registry,
        claims: Claims,
        routing: Routing,
        forwarder: Forwarder,
        *,
        owner: OwnerCheck,
        default_max_range_m: float,
        config: ServerConfig,
        server_address: Callable[[], str],
        on_reachable: Callable[[bool], Awaitable[None]],
        on_moved: Callable[[CameraEntry], None],
    ) -> None:
        super().__init__(registry, claims, routing, forwarder, owner=owner, default_max_range_m=default_max_range_m)
        self._server_address = server_address
        self._on_reachable = on_reachable
        self._on_moved = on_moved
        endpoints = Endpoints.parse(config.registry, "registry")
        self.shared = SharedRegistry(
            endpoints,
            self.apply,
            self.drop,
            lambda: [e.camera_id for e in self.registry.cameras()],
            on_reachable=on_reachable,
            apply_pose=self.apply_pose,
            client=EtcdClient(endpoints, credentials=config.etcd_credentials()),
            registration_rate=config.registration_rate,
            pose_write_rate=config.pose_write_rate,
        )

    def _shared(self) -> SharedRegistry:
        assert self.shared is not None
        return self.shared

    def describe(self) -> str:
        return f"shared in etcd {self._shared().endpoints}"

    async def open(self) -> None:
        shared = self._shared()
        await shared.start()
        try:  # the registry as etcd holds it before serving; if etcd does not answer, serve anyway
            await asyncio.wait_for(shared.synced.wait(), SHARED_SYNC_WAIT_S)
        except TimeoutError:
            log.warning("registry: etcd %s has not answered yet; serving with no camera", shared.endpoints)

    async def serving(self) -> None:
        if self._shared().trouble:
            await self._on_reachable(False)

    async def close(self) -> None:
        await self._shared().stop()

    async def register(
        self, registration: CameraRegistration, who: str, peer: str, presented_token: str = ""
    ) -> tuple[CameraEntry, str]:
        """The id's holder is read from etcd (another server may have registered it), the
        registration is checked as always, then stored by compare-and-put under a new etcd lease;
        every server (this one at once) routes to it."""
        shared = self._shared()
        camera_id, owner, quota = self._registrant(registration, who, peer)
        shared.registrations.check(quota)  # a caller over its rate costs no etcd read and no field of view
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
            server=self._server_address(),
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
            self.claims.unreserve(camera_id, quota)  # held from here on (apply), or failed
        shared.records[camera_id] = stored
        entry = self.apply(stored)
        if state is not None and (applied := self.registry.mobile_state(camera_id)) is not None:
            applied.max_speed_mps = state.max_speed_mps  # the speed its updates here are held to
        return entry, secret

    async def _held_record(self, camera_id: str, who: str, registration_secret: str, method: str) -> Record:
        """The id's record in etcd, once the caller is shown to hold it (as etcd records the holder)."""
        check_id(camera_id, "camera_id")
        owner = self.owner(who, method)
        record = await self._shared().get(camera_id)
        if record is None:
            raise NotFound(f"camera_id: {camera_id!r} is not registered")
        self.claims.adopt(camera_id, record.claim())
        self.claims.check(camera_id, owner, secret_digest(registration_secret))
        return record

    async def renew(self, camera_id: str, who: str, registration_secret: str) -> None:
        """A heartbeat through any server: the holder (as etcd records it) keeps the etcd lease alive."""
        record = await self._held_record(camera_id, who, registration_secret, "Heartbeat")
        if not await self._shared().renew(record):
            raise NotFound(f"camera_id: {camera_id!r}'s lease expired; register again")
        self.routing.unreachable.discard(camera_id)
        log.debug("camera %s: heartbeat; its lease in etcd renewed", camera_id)

    async def deregister(self, camera_id: str, who: str, registration_secret: str) -> None:
        """The holder leaves through any server: its key goes from etcd, and every server drops it."""
        record = await self._held_record(camera_id, who, registration_secret, "Deregister")
        await self._shared().delete(record)
        self._shared().records.pop(camera_id, None)
        self.drop(camera_id, "deregistered")

    def check_holder(self, camera_id: str, who: str, registration_secret: str, method: str) -> None:
        self.claims.check(camera_id, self.owner(who, method), secret_digest(registration_secret))

    def admit_pose(self, camera_id: str) -> None:
        self._shared().admit_pose(camera_id)  # each one a write etcd keeps until compacted

    def share_pose(self, camera_id: str, pose: Pose2, pose_time_unix: float) -> None:
        shared = self._shared()  # the other servers route it by this pose too
        shared.share_pose(camera_id, PoseRecord(pose.x, pose.y, pose.yaw, pose_time_unix, shared.origin))

    def apply(self, record: Record) -> CameraEntry:
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
        self.forwarder.camera_tokens[entry.camera_id] = record.forward_secret
        self.routing.unreachable.discard(entry.camera_id)
        self.routing.lost.pop(entry.camera_id, None)
        self.forwarder.link(entry)
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

    def apply_pose(self, camera_id: str, pose: PoseRecord) -> None:
        """A mobile camera's pose another server took: its field of view moves here too (the rate
        was checked where the update came in), and it may join this server's tracks."""
        entry = self.registry.update_pose(camera_id, Pose2(pose.x, pose.y, pose.yaw), pose.time_unix, check_rate=False)
        log.debug(POSE_APPLIED, camera_id, pose.x, pose.y, pose.yaw, "from the shared registry")
        self._on_moved(entry)

    def drop(self, camera_id: str, why: str, lapsed: bool = False) -> None:
        """A registration etcd no longer holds: out of routing here, its id free; `lapsed` (its
        lease ran out without it deregistering): remembered as lost, as `sweep_leases` does."""
        self.claims.release(camera_id)
        entry = self.registry.remove(camera_id) if camera_id in self.registry else None
        self.forget(camera_id)
        if lapsed and entry is not None:
            self.routing.remember_lost(entry, why)
        metrics.CAMERAS.set(len(self.registry))
        log.info("camera %s left routing: %s", camera_id, why)

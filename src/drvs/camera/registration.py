"""A camera node's registration with its server: soft state, kept alive by the camera.

The camera registers, heartbeats well within the lease the server grants, registers again when
the server no longer knows it (a restart) or another registration of its id replaced it, backs
off while the server is unreachable or refuses it, and deregisters when it stops.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time

import grpc
from grpc import aio

from drvs.core.backoff import Backoff
from drvs.core.errors import PermissionDenied
from drvs.core.mobile import PoseBuffer
from drvs.core.model import Pose2
from drvs.core.net import parse_address_list
from drvs.v1 import registry_pb2, registry_pb2_grpc
from drvs.wire import _grpc
from drvs.wire.channels import check_role, open_channel
from drvs.wire.convert import pose_to_pb
from drvs.wire.security import SERVER, Security

log = logging.getLogger("drvs.camera")

#: Seconds a Register call may take before the camera tries again.
REGISTER_TIMEOUT_S = 5.0
#: Seconds a Deregister call may take when the camera stops.
DEREGISTER_TIMEOUT_S = 1.0
#: First wait after a failed call, seconds; doubled after each failure up to the heartbeat interval.
INITIAL_BACKOFF_S = 0.2
#: Shortest heartbeat interval, seconds.
MIN_HEARTBEAT_S = 0.05
#: A conflict over the camera id lasts at least a lease: ask again at most this often, seconds.
CONFLICT_BACKOFF_S = 5.0


def details(exc: grpc.RpcError) -> str:
    """A failed call's status and message, for the log."""
    if isinstance(exc, aio.AioRpcError):
        return f"{exc.code().name} {exc.details()}"
    return str(exc)


class Registration:
    """Keeps one camera id registered with the server at `server_address`.

    `start(request)` opens the channel and starts the loop; `registered` is set once the first
    registration succeeded; `stop()` ends the loop, deregisters and closes the channel.
    `heartbeat_s`: the interval the operator asked for (None: a third of the lease), never more
    than half the lease."""

    def __init__(
        self, camera_id: str, server_address: str, security: Security, heartbeat_s: float | None = None
    ) -> None:
        self.camera_id = camera_id
        self.server_address = server_address
        self.security = security
        self.heartbeat_s = heartbeat_s
        self.registered = asyncio.Event()
        self._channel: aio.Channel | None = None
        self._stub: registry_pb2_grpc.RegisterVisionServiceStub | None = None
        self._task: asyncio.Task[None] | None = None
        #: The current registration's secret, from the server: heartbeats and deregistration carry it.
        self.secret = ""
        #: The server's answer to the latest registration (a mobile camera's pose lease, its
        #: minimum pose interval, and why it will not be routed, if so).
        self.reply = registry_pb2.RegisterReply()

    def heartbeat_interval(self, lease_ttl_s: float) -> float:
        """Seconds between heartbeats: the configured interval, but never so long that the lease
        runs out between beats."""
        interval = lease_ttl_s / 3 if self.heartbeat_s is None else min(self.heartbeat_s, lease_ttl_s / 2)
        return max(MIN_HEARTBEAT_S, interval)

    def start(self, request: registry_pb2.RegisterRequest, fov_m2: float = 0.0) -> None:
        """Open the channel to the server and keep `request` registered (`fov_m2`: for the log)."""
        # Every server given (a,b,...) on one channel (under TLS, one per server): it moves on from one that fails.
        self._channel = open_channel(self.security, parse_address_list(self.server_address, "server"))
        self._stub = registry_pb2_grpc.RegisterVisionServiceStub(self._channel)
        self._task = asyncio.get_running_loop().create_task(self.run(request, fov_m2))

    async def stop(self) -> None:
        """Stop heartbeating, deregister (if registered), close the channel; idempotent."""
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
        await self.deregister()
        channel, self._channel = self._channel, None
        if channel is not None:
            await channel.close()

    async def _register(self, request: registry_pb2.RegisterRequest, again: bool, fov_m2: float) -> float:
        """One registration; returns the heartbeat interval for the lease granted."""
        assert self._stub is not None
        # The previous registration's secret proves this is the same camera coming back.
        request.registration_secret = self.secret
        # Under TLS: no registration (nor its forward secret) for a certificate of another role.
        await check_role(self.security, parse_address_list(self.server_address, "server"), SERVER, "server")
        reply = await self._stub.Register(request, timeout=REGISTER_TIMEOUT_S, metadata=self.security.metadata())
        self.secret = reply.registration_secret
        self.reply = reply
        if reply.unroutable:
            log.warning("camera %s: the server will not route to it: %s", self.camera_id, reply.unroutable)
        log.info(
            "camera %s %s with %s: lease %.1f s, field of view %.1f m²",
            self.camera_id,
            "re-registered" if again else "registered",
            self.server_address,
            reply.lease_ttl_s,
            fov_m2,
        )
        self.registered.set()
        return self.heartbeat_interval(reply.lease_ttl_s)

    async def _heartbeat(self, timeout_s: float) -> float:
        """One heartbeat; returns the interval for the lease the server now grants."""
        assert self._stub is not None
        reply = await self._stub.Heartbeat(
            registry_pb2.HeartbeatRequest(camera_id=self.camera_id, registration_secret=self.secret),
            timeout=timeout_s,
            metadata=self.security.metadata(),
        )
        return self.heartbeat_interval(reply.lease_ttl_s)

    async def run(self, request: registry_pb2.RegisterRequest, fov_m2: float = 0.0) -> None:
        """Register with `request`, then heartbeat until cancelled (`fov_m2`: for the log only)."""
        interval = 1.0
        backoff = Backoff(INITIAL_BACKOFF_S, CONFLICT_BACKOFF_S)
        ever_registered = False
        registered = False
        while True:
            try:
                if not registered:
                    interval = await self._register(request, ever_registered, fov_m2)
                    registered = ever_registered = True
                else:
                    interval = await self._heartbeat(interval)
                    if backoff.failing:  # it had failed: say the lease is kept again
                        log.info("camera %s: heartbeats reach %s again", self.camera_id, self.server_address)
                backoff.reset()
                await asyncio.sleep(interval)
            except grpc.RpcError as exc:
                code = exc.code() if isinstance(exc, aio.AioRpcError) else grpc.StatusCode.UNKNOWN
                if code == grpc.StatusCode.NOT_FOUND:
                    log.info(
                        "camera %s: server does not know this camera (restarted?); registering again", self.camera_id
                    )
                    registered = False
                    continue
                if code == grpc.StatusCode.FAILED_PRECONDITION and registered:
                    log.warning(
                        "camera %s: the server says another registration replaced ours (%s); registering again",
                        self.camera_id,
                        details(exc),
                    )
                    registered = False
                    continue
                if code == grpc.StatusCode.PERMISSION_DENIED:
                    registered = False
                    log.error(
                        "camera %s: CONFLICT: the server gives camera id %s to another registration: %s; "
                        "retrying in %.1f s",
                        self.camera_id,
                        self.camera_id,
                        details(exc),
                        backoff.current,
                    )
                elif code in (grpc.StatusCode.INVALID_ARGUMENT, grpc.StatusCode.UNAUTHENTICATED):
                    registered = False
                    log.error("camera %s: server refused registration: %s", self.camera_id, details(exc))
                elif _grpc.refused_before_read(exc):
                    # Dropped or refused before the server read it (too busy to take it in): the
                    # server is there; tried again after the backoff.
                    log.warning("camera %s: server %s busy: %s", self.camera_id, self.server_address, details(exc))
                else:
                    log.warning(
                        "camera %s: server %s unreachable: %s", self.camera_id, self.server_address, details(exc)
                    )
                conflict = code == grpc.StatusCode.PERMISSION_DENIED
                await backoff.sleep(max(interval, CONFLICT_BACKOFF_S) if conflict else interval)
            except PermissionDenied as exc:  # the server's certificate is not a server's (check_role)
                log.error("camera %s: %s; retrying in %.1f s", self.camera_id, exc, backoff.current)
                await backoff.sleep(max(interval, CONFLICT_BACKOFF_S))

    async def update_pose(self, pose: Pose2, pose_time_unix: float, timeout_s: float) -> registry_pb2.UpdatePoseReply:
        """A mobile camera's pose, to the server (grpc.RpcError when it refuses or cannot be reached)."""
        assert self._stub is not None
        reply: registry_pb2.UpdatePoseReply = await self._stub.UpdatePose(
            registry_pb2.UpdatePoseRequest(
                camera_id=self.camera_id,
                registration_secret=self.secret,
                pose=pose_to_pb(pose),
                pose_time_unix=pose_time_unix,
            ),
            timeout=timeout_s,
            metadata=self.security.metadata(),
        )
        return reply

    async def deregister(self) -> None:
        """Leave routing at once (rather than when the lease runs out); only after a registration.
        A failure is logged: the lease then runs out by itself."""
        if not self.registered.is_set() or self._stub is None:
            return
        self.registered.clear()
        try:
            await self._stub.Deregister(
                registry_pb2.DeregisterRequest(camera_id=self.camera_id, registration_secret=self.secret),
                timeout=DEREGISTER_TIMEOUT_S,
                metadata=self.security.metadata(),
            )
            log.info("camera %s deregistered", self.camera_id)
        except grpc.RpcError as exc:
            log.warning("camera %s: deregistration failed: %s", self.camera_id, details(exc))


class PoseUpdates:
    """Keeps a mobile camera's field of view where its robot is: sends the newest pose from `poses`
    to the server when the robot moved `distance_m` or turned `angle_deg` since the last pose sent,
    or when that one is older than half the pose lease (a standing robot stays routed); only while
    the newest pose is itself fresh (within the lease of now), and at most `max_rate_hz` a second (and
    never sooner than the server's minimum interval). Without fresh poses it sends nothing, and the
    server stops routing to the camera when the lease runs out."""

    def __init__(
        self,
        registration: Registration,
        poses: PoseBuffer,
        *,
        distance_m: float = 0.1,
        angle_deg: float = 5.0,
        max_rate_hz: float = 5.0,
    ) -> None:
        self.registration = registration
        self.poses = poses
        self.distance_m = distance_m
        self.angle_rad = math.radians(angle_deg)
        self.max_rate_hz = max_rate_hz
        #: What was sent last: the pose, its time, when (time.monotonic()), and to which registration.
        self.sent: tuple[Pose2, float, float, str] | None = None
        self.updates = 0
        self._task: asyncio.Task[None] | None = None
        self._unimplemented_logged = False

    def start(self) -> None:
        self._task = asyncio.get_running_loop().create_task(self.run())

    async def stop(self) -> None:
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    def due(self, now_unix: float, now_mono: float) -> tuple[Pose2, float] | None:
        """The pose to send now, with its time, or None."""
        latest = self.poses.latest()
        reply = self.registration.reply
        lease = reply.pose_lease_s or 1.0
        if latest is None or not self.registration.registered.is_set() or now_unix - latest[0] > lease:
            return None
        t, pose = latest
        if self.sent is None or self.sent[3] != self.registration.secret:
            return pose, t
        last, _, sent_at, _ = self.sent
        moved = math.hypot(pose.x - last.x, pose.y - last.y) >= self.distance_m
        turned = abs(math.remainder(pose.yaw - last.yaw, 2 * math.pi)) >= self.angle_rad
        stale = now_mono - sent_at >= lease / 2
        return (pose, t) if moved or turned or stale else None

    async def run(self) -> None:
        while True:
            interval = max(1.0 / self.max_rate_hz, self.registration.reply.min_pose_interval_s)
            due = self.due(time.time(), time.monotonic())
            if due is not None:
                pose, t = due
                try:
                    await self.registration.update_pose(pose, t, timeout_s=max(1.0, interval))
                    self.sent = (pose, t, time.monotonic(), self.registration.secret)
                    self.updates += 1
                except grpc.RpcError as exc:
                    code = exc.code() if isinstance(exc, aio.AioRpcError) else grpc.StatusCode.UNKNOWN
                    if code == grpc.StatusCode.UNIMPLEMENTED:
                        if not self._unimplemented_logged:
                            log.error("camera %s: the server does not take poses (too old?)", self.camera_id)
                            self._unimplemented_logged = True
                        interval = max(interval, 5.0)
                    elif code != grpc.StatusCode.RESOURCE_EXHAUSTED:
                        # NOT_FOUND / FAILED_PRECONDITION: the registration loop registers again.
                        log.warning("camera %s: pose update refused: %s", self.camera_id, details(exc))
            await asyncio.sleep(interval)

    @property
    def camera_id(self) -> str:
        return self.registration.camera_id

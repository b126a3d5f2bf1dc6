"""The plumbing under DrvsClient: the channel and the request stream to the server, the report
listener, retries and the throttle, and the tables of open subscriptions and tracks that the
handles (drvs.robot.subscription, drvs.robot.track) and the listener (drvs.robot.listener) ask it
to change. DrvsClient (drvs.robot.client) adds the requests robot code makes."""

from __future__ import annotations

import asyncio
import ipaddress
import itertools
import logging
import secrets
from collections.abc import Awaitable, Callable
from types import TracebackType
from typing import Any, TypeVar

from grpc import aio

from drvs.core.errors import DrvsError, InvalidArgument
from drvs.core.model import DEFAULT_FRAME, check_frame, check_id
from drvs.core.net import dialable_address, format_address, host_of, local_ip_towards, parse_address, parse_address_list
from drvs.robot.handles import health_check
from drvs.robot.limits import DEFAULT_CONNECT_TIMEOUT_S
from drvs.robot.listener import Listener, ReportKeys
from drvs.robot.regions import _Regions
from drvs.robot.retry import RetryPolicy, asking, retrying
from drvs.robot.subscription import Subscription
from drvs.robot.throttle import DEFAULT_K, AdaptiveThrottle
from drvs.robot.track import Track
from drvs.v1 import detection_pb2, detection_pb2_grpc, registry_pb2_grpc
from drvs.wire import _grpc
from drvs.wire.channels import check_role, open_channel
from drvs.wire.convert import report_from_pb
from drvs.wire.report_auth import new_secret
from drvs.wire.request_stream import RequestStream
from drvs.wire.security import SERVER, Security

log = logging.getLogger("drvs.robot")

T = TypeVar("T")
_C = TypeVar("_C", bound="ClientConnection")


class ClientConnection:
    """A robot's connection to its server, without the requests (see DrvsClient, which documents
    the arguments): started by `start()` or `async with`, closed by `close()`."""

    def __init__(
        self,
        server: str,
        *,
        robot_id: str = "",
        listen: str | None = None,
        advertise: str | None = None,
        retry: RetryPolicy | None = None,
        security: Security | None = None,
        frame: str = DEFAULT_FRAME,
        throttle_k: float = DEFAULT_K,
    ) -> None:
        self.security = security or Security()
        #: The server, or several sharing one registry ("a:50051,b:50051"): one gRPC channel over
        #: them, which moves on from one that fails; with several, tracks resume through another.
        self.servers = parse_address_list(server, "server")
        self.server = server
        #: Several servers given, or a DNS name (which may stand for several): a track whose
        #: server's stream ends is sent again through the channel, which moves on to one that answers.
        self.fails_over = len(self.servers) > 1 or not _is_ip_literal(self.servers[0])
        #: Its requests' robot_id ("" for none): checked here, not first by the request that carries it.
        self.robot_id = check_id(robot_id, "robot_id", allow_empty=True)
        #: The floor plan this robot's regions are in ("building-a/floor-2"; "map" by default): its
        #: requests go only to cameras of this frame. Set it when the robot changes floors.
        self.frame = check_frame(frame)
        #: HOST:PORT the listener binds; "" until start() picks the default.
        self.listen = listen or ""
        if listen:
            parse_address(listen, "listen", allow_port_zero=True)
        self._advertise = advertise
        if advertise:
            parse_address(advertise, "advertise")
        if retry is not None and not isinstance(retry, RetryPolicy):
            raise InvalidArgument(f"retry: expected a RetryPolicy, got {type(retry).__name__}")
        self.retry = retry or RetryPolicy()
        #: The port the listener bound (0 until started).
        self.port = 0
        self._channel: aio.Channel | None = None
        self._listener: aio.Server | None = None
        self._listener_lock = asyncio.Lock()
        self._subscriptions: dict[str, Subscription] = {}
        self._tracks: dict[str, Track] = {}
        self.reports_received = 0
        #: Reports refused: not from a camera the request was dispatched to, or not on its stream.
        self.reports_rejected = 0
        # Proves reports (drvs.wire.report_auth): the server derives each camera's key from it, and a
        # camera's reports count only on the streams that presented its key.
        self._report_keys = ReportKeys(new_secret())
        self._closing = False
        self._open_at_close: list[str] = []
        self._report_streams: set[asyncio.Task[Any]] = set()
        # Request ids: a random prefix per client (a restarted robot never reuses a live id) and a
        # counter; short, because the id travels in the request, the reply and every report.
        self._id_prefix = secrets.token_urlsafe(3)  # 4 characters, 24 random bits
        self._id_counter = itertools.count(1)
        self._requests: RequestStream | None = None
        self._regions = _Regions()
        #: Holds back requests while the server refuses them for overload (drvs.robot.throttle).
        self.throttle = AdaptiveThrottle(throttle_k)

    @property
    def callback_address(self) -> str:
        """HOST:PORT cameras dial to deliver this robot's reports (`advertise`, or the listener's);
        "" while no listener runs (see `listening`)."""
        if self._advertise:
            return self._advertise
        if self._listener is None:
            return ""
        return dialable_address(self.listen, self.port, self.servers)

    @property
    def listening(self) -> bool:
        """True once the report listener runs (a per-camera request, `listen`/`advertise`, or
        start_listener()); a robot whose requests are all fused never opens it."""
        return self._listener is not None

    async def start(self) -> None:
        """Open the channel to the server (no check of the server: DrvsClient.connect does that),
        and the report listener when `listen` or `advertise` was given (otherwise it starts with the
        first per-camera request)."""
        self._channel = open_channel(self.security, self.servers)  # TLS: a channel per server
        self._detect = detection_pb2_grpc.DetectObjectBoundaryStub(self._channel)
        self._requests = RequestStream(self._detect, f"server {self.server}", metadata=self.security.metadata())
        self._registry = registry_pb2_grpc.RegisterVisionServiceStub(self._channel)
        if self.listen or self._advertise:
            await self.start_listener()

    async def start_listener(self) -> str:
        """Start the report listener cameras dial with the reports of per-camera requests, if it
        is not running, and return `callback_address`. Per-camera requests start it themselves."""
        self._require_started()
        async with self._listener_lock:
            if self._listener is None:
                if not self.listen:
                    # Resolving the servers' names may block: not on the event loop. Every server
                    # given is one way to the same cameras: the first with a route picks the interface.
                    self.listen = format_address(await asyncio.to_thread(local_ip_towards, self.servers), 0)
                listener = _grpc.new_server()
                detection_pb2_grpc.add_CallbackCoordinatesServicer_to_server(Listener(self), listener)
                self.port = self.security.bind(listener, self.listen)
                await listener.start()
                self._listener = listener
                log.debug("robot %r listening for reports on %s", self.robot_id, self.callback_address)
        return self.callback_address

    async def check_server(self, timeout_s: float = DEFAULT_CONNECT_TIMEOUT_S) -> None:
        """Ask the server's gRPC health service whether it serves, each attempt waiting at most
        `timeout_s` seconds, retried as `retry` allows. Raises Unavailable naming the server when it
        is not there, not serving, or silent; other refusals (Unauthenticated ...) as they come."""
        self._require_started()
        await check_role(self.security, self.servers, SERVER, "server")  # under TLS: a server's certificate
        assert self._channel is not None
        check = health_check(self._channel, self.security.metadata() or None, self.server, timeout_s)
        await self._retrying("the connection", check)

    async def _retrying(self, what: str, call: Callable[[], Awaitable[T]]) -> T:
        """`call()`, tried again after each Unavailable as `retry` allows."""
        return await retrying(self.retry, self.server, what, call)

    async def _asking(self, what: str, call: Callable[[], Awaitable[T]]) -> T:
        """A request to the server, through the client's throttle: refused here at once while the
        server refuses this robot for overload (see drvs.robot.throttle), else sent as `_retrying`
        sends it; the server's answer is counted."""
        return await asking(self.throttle, self.retry, self.server, what, call)

    # What the report listener (drvs.robot.listener) asks of the client: it edits nothing here itself.

    def _take_report(self, message: detection_pb2.DetectionReport, stream: object) -> bool | None:
        """Hand one report to its subscription: True when taken; False when its request is unknown
        or closed (the camera is told to stop it); None when refused: not proven its camera's on
        this stream (answered as an unknown request, so the sender learns nothing more)."""
        sub = self._subscriptions.get(message.request_id)
        if not self._report_keys.accepts(message, stream):
            self.reports_rejected += 1
            return None
        if sub is None or not sub._deliver(report_from_pb(message, sub.request.filter_def)):
            return False
        self.reports_received += 1
        return True

    def _stream_opened(self, task: asyncio.Task[Any] | None) -> None:
        if task is not None:
            self._report_streams.add(task)

    def _stream_ended(self, stream: object, task: asyncio.Task[Any] | None) -> None:
        """A report stream ended: cameras that reported only on it have none now, and the requests
        they had not finished are interrupted."""
        if task is not None:
            self._report_streams.discard(task)
        cameras = self._report_keys.forget(stream)
        if cameras:
            for sub in list(self._subscriptions.values()):
                sub._stream_ended(cameras)

    def _closing_control(self) -> detection_pb2.ReportControl | None:
        """What a report stream tells its camera while the robot closes: stop the requests still open."""
        if not self._open_at_close:
            return None
        return detection_pb2.ReportControl(cancelled_request_ids=self._open_at_close)

    def new_request_id(self) -> str:
        """A request id unique to this client (and, by its random prefix, across restarts)."""
        return f"{self._id_prefix}{next(self._id_counter):x}"

    def _cancel_at_server(self, request_id: str) -> None:
        if self._requests is not None:
            self._requests.cancel_soon(request_id)

    def _check_unused(self, request_id: str) -> None:
        if request_id in self._subscriptions or request_id in self._tracks:
            raise InvalidArgument(f"request_id: {request_id!r} is already in use")

    def _register(self, handle: Subscription | Track) -> None:
        """A subscription or track about to be sent: reports and snapshots for its id go to it."""
        self._check_unused(handle.request_id)
        if isinstance(handle, Subscription):
            self._subscriptions[handle.request_id] = handle
        else:
            self._tracks[handle.request_id] = handle

    def _forget(self, request_id: str) -> None:
        """A subscription or track closed: no longer this client's to deliver to or close."""
        self._subscriptions.pop(request_id, None)
        self._tracks.pop(request_id, None)

    def _release(self, request_id: str) -> None:
        if self._requests is not None:
            self._requests.release(request_id)

    async def close(self) -> None:
        """Close every open subscription (cameras are told to stop), the listener and the channel.
        Closing again does nothing."""
        self._closing = True
        # Requests still open: each report stream tells its camera to stop them before it ends,
        # so cameras do not go on dialling a robot that has gone.
        self._open_at_close = list(self._subscriptions)
        for sub in list(self._subscriptions.values()):
            sub.close()
        for track in list(self._tracks.values()):
            track.close()
        for task in list(self._report_streams):
            task.cancel()
        if self._requests is not None:
            requests, self._requests = self._requests, None
            await requests.flush_cancels()
            await requests.close()
        if self._listener is not None:
            await self._listener.stop(0.5)
            self._listener = None
        if self._channel is not None:
            await self._channel.close()
            self._channel = None

    async def __aenter__(self: _C) -> _C:
        await self.start()
        return self

    async def __aexit__(
        self, et: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.close()

    def _require_started(self) -> None:
        if self._channel is None:
            raise DrvsError("DrvsClient is not started; use `async with DrvsClient.connect(...)` or await start()")


def _is_ip_literal(address: str) -> bool:
    host = host_of(address).strip("[]")
    try:
        ipaddress.ip_address(host)
    except ValueError:
        return False
    return True

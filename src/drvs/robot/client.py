"""DrvsClient: robot code asks for objects and gets Python objects back.

    async with DrvsClient.connect("drvs.example:50051", robot_id="turtle-1") as drvs:
        result = await drvs.detect("hsv_014110130035225200", (0, 0, 5, 5))
        for d in result.detections:
            print(d.camera_id, d.centroid.x, d.centroid.y)

Timeouts, each in seconds and each meaning one thing:

- `connect_timeout_s` (DrvsClient.connect): how long one attempt to reach the server may take
  (its gRPC health check); past it the attempt fails with Unavailable.
- `rpc_timeout_s` (subscribe, detect, cameras): how long one attempt of one call may wait for the
  server's reply (the reply lists the cameras a request went to); past it DeadlineExceeded.
- `timeout_s` (subscribe, detect): how long after the server's reply, beyond the request's own
  `duration_s`, to wait for every camera's final report; a camera that has not finished by then is
  in `result.camera_errors` as DEADLINE_EXCEEDED. It never raises.

`retry=RetryPolicy(...)` applies to the first two, and only to Unavailable (the server is down,
restarting, or unreachable): nothing is sent again after the server has taken it.
"""

from __future__ import annotations

import asyncio
import ipaddress
import itertools
import logging
import secrets
import warnings
from collections.abc import Awaitable, Callable
from dataclasses import replace
from types import TracebackType
from typing import Any, Literal, TypeVar, overload

import grpc
from grpc import aio

from drvs import _grpc
from drvs.channels import check_role, open_channel
from drvs.convert import polygon_from_pb, report_from_pb, request_to_pb, snapshot_from_pb
from drvs.errors import (
    DrvsError,
    FailedPrecondition,
    InvalidArgument,
)
from drvs.model import (
    DEFAULT_FRAME,
    ContinuousMode,
    DetectionRequest,
    FusionOptions,
    Snapshot,
    check_frame,
)
from drvs.net import (
    dialable_address,
    format_address,
    host_of,
    local_ip_towards,
    parse_address,
    parse_address_list,
)
from drvs.report_auth import new_secret
from drvs.request_stream import RequestStream
from drvs.robot.handles import Connecting, health_check
from drvs.robot.limits import (
    DEFAULT_CONNECT_TIMEOUT_S,
    DEFAULT_RPC_TIMEOUT_S,
    DEFAULT_TIMEOUT_S,
    DEFAULT_TRACK_RATE_HZ,
    MAX_BACKOFF_S,
    MAX_QUEUED_REPORTS,
    MAX_QUEUED_SNAPSHOTS,
    check_queue,
    check_timeout,
    fusion_options,
    seconds,
)
from drvs.robot.listener import Listener, ReportKeys
from drvs.robot.regions import REGION_CACHE_SIZE, RegionLike, _Regions, as_region
from drvs.robot.results import CameraInfo, DetectionResult, camera_info_from_pb
from drvs.robot.retry import RetryPolicy, asking, retrying
from drvs.robot.subscription import Subscribing, Subscription, open_subscription
from drvs.robot.throttle import DEFAULT_K, AdaptiveThrottle
from drvs.robot.track import Track, Tracking, open_track
from drvs.security import SERVER, Security
from drvs.v1 import detection_pb2, detection_pb2_grpc, registry_pb2, registry_pb2_grpc

log = logging.getLogger("drvs.robot")

T = TypeVar("T")

# What robot code, tools and tests import from here (the parts now live in their own modules).
__all__ = [
    "DEFAULT_CONNECT_TIMEOUT_S",
    "DEFAULT_RPC_TIMEOUT_S",
    "DEFAULT_TIMEOUT_S",
    "DEFAULT_TRACK_RATE_HZ",
    "MAX_BACKOFF_S",
    "MAX_QUEUED_REPORTS",
    "MAX_QUEUED_SNAPSHOTS",
    "REGION_CACHE_SIZE",
    "CameraInfo",
    "Connecting",
    "DetectionResult",
    "DrvsClient",
    "RegionLike",
    "RetryPolicy",
    "Subscribing",
    "Subscription",
    "Track",
    "Tracking",
    "as_region",
]


class DrvsClient:
    """A robot's connection to a DRVS server: ask where objects are, get Python objects back.

    Connect with `DrvsClient.connect(server, ...)`, which checks that the server answers:

        async with DrvsClient.connect("drvs.example:50051", robot_id="turtle-1") as drvs:
            result = await drvs.detect("hsv_014110130035225200", (0, 0, 5, 5))

    - `server`: the server's HOST:PORT, several sharing one registry ("a:50051,b:50051", all IPv4 or
      all IPv6), or a DNS name standing for several: every call moves on from one that is down;
    - `robot_id`: this robot's name in the server's logs and limits (letters, digits, - _ . :);
    - `listen`: HOST:PORT the robot's report listener binds (port 0: any free port); default: the
      local address that reaches the server, port 0, chosen when the listener starts;
    - `advertise`: HOST:PORT cameras dial to deliver reports (behind NAT, a relay ...); default:
      the bound listener's address;

    The report listener is only for per-camera requests (subscribe, detect): it starts
    with the first of them (at start() when `listen` or `advertise` is given, or on
    `await start_listener()`). A robot whose requests are all fused (snapshot, track)
    dials out only and opens no port, so it works behind NAT.
    - `retry`: a RetryPolicy for calls the server could not take (default: no retry);
    - `throttle_k`: client-side throttling (drvs.robot.throttle): while the server refuses requests
      for overload (ResourceExhausted, with `retry_after_s`), the client itself refuses new ones
      at once so that it sends at most about `throttle_k` times what the server accepts (2, the
      SRE book's value; larger throttles later; math.inf: never, for tools that measure the server);
    - `security`: a drvs.security.Security with TLS files and this robot's token (default: plain).

    Constructing one does no network work (no name is resolved); `start()` (or `async with
    DrvsClient(...)`) opens the channel without checking the server, and a call
    to a server that is not there fails then, with Unavailable. Every error is a drvs.errors
    exception with `.code` (the gRPC status name) and `.camera_id`.

    Timeouts, in seconds, one meaning each: `connect_timeout_s` (connect) bounds one attempt to
    reach the server; `rpc_timeout_s` (subscribe, detect, cameras) bounds one attempt's wait for the
    server's reply; `timeout_s` (subscribe, detect) is how long, after that reply and beyond the
    request's `duration_s`, to wait for every camera's final report (never raises: a late camera
    is in `result.camera_errors`). `retry` repeats the first two after Unavailable.

    Counters: `reports_received` (reports handed to subscriptions) and `reports_rejected`
    (reports refused: not from a camera the request went to, or not on its stream).
    """

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
        self.robot_id = robot_id
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
        # Proves reports (drvs.report_auth): the server derives each camera's key from it, and a
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

    @classmethod
    def connect(
        cls,
        server: str,
        *,
        robot_id: str = "",
        listen: str | None = None,
        advertise: str | None = None,
        retry: RetryPolicy | None = None,
        security: Security | None = None,
        connect_timeout_s: float = DEFAULT_CONNECT_TIMEOUT_S,
        frame: str = DEFAULT_FRAME,
        throttle_k: float = DEFAULT_K,
    ) -> Connecting:
        """A client that has checked its server: `await DrvsClient.connect(...)` or
        `async with DrvsClient.connect(...) as drvs:` (closed on leaving the block).

        Starts the client, then asks the server's gRPC health service whether it serves, each
        attempt waiting at most `connect_timeout_s` seconds, and as many attempts as `retry`
        allows. A server that is not there, not serving, or not answering in time raises
        Unavailable naming its address (a refused credential: Unauthenticated). The other
        arguments are DrvsClient's; bad ones raise InvalidArgument at once.
        """
        timeout_s = seconds(connect_timeout_s, "connect_timeout_s", 3600.0)
        client = cls(
            server,
            robot_id=robot_id,
            listen=listen,
            advertise=advertise,
            retry=retry,
            security=security,
            frame=frame,
            throttle_k=throttle_k,
        )
        return Connecting(client, timeout_s)

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

    async def __aenter__(self) -> DrvsClient:
        await self.start()
        return self

    async def __aexit__(
        self, et: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.close()

    def _require_started(self) -> None:
        if self._channel is None:
            raise DrvsError("DrvsClient is not started; use `async with DrvsClient.connect(...)` or await start()")

    def subscribe(
        self,
        filter_def: str,
        region: RegionLike,
        *,
        rate_hz: float = 0.0,
        duration_s: float = 0.0,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        request_id: str | None = None,
        rpc_timeout_s: float = DEFAULT_RPC_TIMEOUT_S,
        outlines: bool = True,
        max_queued: int = MAX_QUEUED_REPORTS,
    ) -> Subscribing:
        """Send a request; its reports arrive on the Subscription as the cameras send them.

            async with drvs.subscribe(YELLOW, (0, 0, 5, 5), rate_hz=10, duration_s=2) as sub:
                async for report in sub:
                    ...

        (`sub = await drvs.subscribe(...)` works too; then `sub.close()` when done.)

        - `filter_def`: what to look for (e.g. "hsv_014110130035225200", "aruco_4x4_50_7", "people");
        - `region`: where, on the floor, in metres (RegionLike);
        - `rate_hz`, `duration_s`: continuous mode, reports a second for that many seconds (both 0:
          a single shot, one report per camera);
        - `timeout_s`: seconds to wait, after the server's reply and beyond `duration_s`, for every
          camera's final report; iteration ends then, and the cameras not finished are in
          `sub.result.camera_errors` as DEADLINE_EXCEEDED;
        - `rpc_timeout_s`: seconds one attempt waits for the server's reply (DeadlineExceeded);
        - `request_id`: an id of your own (default: a fresh one);
        - `outlines`: False asks for bounds, centroid and ground contact only (an empty outline);
        - `max_queued`: unread reports a continuous request keeps; beyond it the oldest are dropped
          and counted in `sub.dropped` (final reports are always kept).

        A bad argument raises InvalidArgument at once; nothing is sent until the returned object
        is awaited or entered, and a server that cannot be reached raises Unavailable then, after
        the attempts `retry` allows. Sending starts the report listener if it is not running.
        """
        self._require_started()
        check_timeout(timeout_s)
        seconds(rpc_timeout_s, "rpc_timeout_s", 3600.0)
        check_queue(max_queued, "reports")
        request, message = self._build(
            filter_def, region, ContinuousMode(float(rate_hz), float(duration_s)), outlines, request_id, None
        )
        message.report_secret = self._report_keys.secret
        return Subscribing(lambda: open_subscription(self, request, message, timeout_s, rpc_timeout_s, max_queued))

    def _build(
        self,
        filter_def: str,
        region: RegionLike,
        continuous: ContinuousMode,
        outlines: bool,
        request_id: str | None,
        fusion: FusionOptions | None,
    ) -> tuple[DetectionRequest, detection_pb2.DetectionRequest]:
        """A validated request and its message. A per-camera request's callback address is the
        listener's, filled in when it is sent if the listener is not running yet."""
        polygon, region_pb = self._regions.get(region)
        request = DetectionRequest(
            request_id=request_id or self.new_request_id(),
            robot_id=self.robot_id,
            filter_def=filter_def,
            region=polygon,
            callback_address=self.callback_address if fusion is None else "",
            continuous=continuous,
            omit_outlines=not outlines,
            fusion=fusion,
            frame=check_frame(self.frame),
        )
        # Every field but a callback address still to come (this client's own) is checked now.
        checked = request if request.callback_address or fusion else replace(request, fusion=FusionOptions())
        checked.validate(unknown_types=True)
        return request, request_to_pb(request, region=region_pb)

    @overload
    async def detect(
        self,
        filter_def: str,
        region: RegionLike,
        *,
        rate_hz: float = ...,
        duration_s: float = ...,
        timeout_s: float = ...,
        outlines: bool = ...,
        fuse: Literal[False] = ...,
        request_id: str | None = ...,
    ) -> DetectionResult: ...

    @overload
    async def detect(
        self,
        filter_def: str,
        region: RegionLike,
        *,
        timeout_s: float = ...,
        outlines: bool = ...,
        fuse: Literal[True],
        deadline_s: float | None = ...,
        request_id: str | None = ...,
    ) -> Snapshot: ...

    @overload
    async def detect(
        self,
        filter_def: str,
        region: RegionLike,
        *,
        rate_hz: float = ...,
        duration_s: float = ...,
        timeout_s: float = ...,
        outlines: bool = ...,
        fuse: bool,
        deadline_s: float | None = ...,
        request_id: str | None = ...,
    ) -> DetectionResult | Snapshot: ...

    async def detect(
        self,
        filter_def: str,
        region: RegionLike,
        *,
        rate_hz: float = 0.0,
        duration_s: float = 0.0,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        outlines: bool = True,
        fuse: bool = False,
        deadline_s: float | None = None,
        request_id: str | None = None,
    ) -> DetectionResult | Snapshot:
        """Send a request and collect every report until each camera is done or `timeout_s` seconds
        beyond `duration_s` have passed; the arguments are subscribe's. Camera failures do not
        raise: they are in `result.camera_errors` (or call `result.raise_for_errors()`).

        `fuse=True` is the deprecated spelling of `snapshot()` (it warns; removed in the next
        release): a fused single shot, answered with one Snapshot.
        """
        if fuse:
            warnings.warn(
                "detect(fuse=True) is deprecated: use snapshot(), which returns the Snapshot", DeprecationWarning, 2
            )
            if rate_hz or duration_s:
                raise InvalidArgument(
                    "fuse: detect(fuse=True) is a single shot (rate_hz and duration_s 0); "
                    "use track() for snapshots over time"
                )
            return await self.snapshot(
                filter_def, region, timeout_s=timeout_s, outlines=outlines, deadline_s=deadline_s, request_id=request_id
            )
        if deadline_s is not None:
            raise InvalidArgument("deadline_s: only for fused requests (fuse=True)")
        async with self.subscribe(
            filter_def,
            region,
            rate_hz=rate_hz,
            duration_s=duration_s,
            timeout_s=timeout_s,
            outlines=outlines,
            request_id=request_id,
        ) as sub:
            return await sub.collect()

    async def snapshot(
        self,
        filter_def: str,
        region: RegionLike,
        *,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        outlines: bool = True,
        deadline_s: float | None = None,
        request_id: str | None = None,
    ) -> Snapshot:
        """A fused single shot: the server gathers the cameras' reports itself and answers with one
        `drvs.model.Snapshot` (`time, objects, missing_cameras = snapshot`): each physical object
        once, as a `WorldObject`, however many cameras saw it. No listener is used (`track()` gives
        snapshots over time).

        - `filter_def`, `region`, `outlines`: what and where, as for subscribe;
        - `deadline_s`: the server answers with what it has this many seconds after it sent the
          request to the cameras, naming the cameras that did not report in time in
          `snapshot.missing_cameras` (DEADLINE_EXCEEDED); None or 0: the server's default (2 s);
          at most 30;
        - `timeout_s`: how long beyond `deadline_s` to wait for the server's answer; past it
          DeadlineExceeded;
        - `request_id`: an id of your own (default: a fresh one).

        A server that refuses the request raises its DrvsError (InvalidArgument ...).
        """
        self._require_started()
        check_timeout(timeout_s)
        fusion = fusion_options(deadline_s, None)
        _, message = self._build(filter_def, region, ContinuousMode(), outlines, request_id, fusion)
        self._check_unused(message.request_id)
        requests = self._requests
        assert requests is not None
        wait = fusion.single_shot_deadline_s + timeout_s
        reply = await self._asking(f"request {message.request_id}", lambda: requests.request(message, wait))
        if not reply.HasField("snapshot"):
            raise FailedPrecondition(
                f"server {self.server}: answered the fused request {message.request_id} without a snapshot "
                "(a server without fused delivery?)"
            )
        uncovered = [polygon_from_pb(p, "uncovered") for p in reply.uncovered]
        return snapshot_from_pb(reply.snapshot, message.request_id, uncovered)

    def track(
        self,
        filter_def: str,
        region: RegionLike,
        *,
        rate_hz: float = DEFAULT_TRACK_RATE_HZ,
        duration_s: float,
        drop_after_s: float | None = None,
        deadline_s: float | None = None,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        rpc_timeout_s: float = DEFAULT_RPC_TIMEOUT_S,
        outlines: bool = True,
        max_queued: int = MAX_QUEUED_SNAPSHOTS,
        request_id: str | None = None,
    ) -> Tracking:
        """Track objects: the server fuses the cameras' reports and sends a `drvs.model.Snapshot`
        `rate_hz` times a second for `duration_s` seconds, on the robot's own request stream (no
        listener: works behind NAT). Objects keep their `track_id` from snapshot to snapshot, also
        when they pass from one camera to another; each has a velocity (m/s) and an uncertainty (m).

            async for time, objects, missing in drvs.track(YELLOW, (0, 0, 5, 5), duration_s=5):
                ...

        - `filter_def`, `region`: what and where, as for subscribe;
        - `rate_hz`: snapshots a second (default 10, at most 100);
        - `duration_s`: for how long, seconds (at most 3600); the last snapshot has `final` set;
        - `drop_after_s`: a track no camera has seen for this long is dropped, seconds (None or 0:
          the server's default, 1 s; at most 60);
        - `deadline_s`: how late after its period a camera's report may still count, seconds (None
          or 0: one period; at most 30); a camera without a report in time is in that snapshot's
          `missing_cameras`;
        - `timeout_s`: seconds beyond `duration_s` and the deadline to wait for the final snapshot
          (past it the iteration raises DeadlineExceeded);
        - `rpc_timeout_s`: seconds one attempt waits for the server's first reply (DeadlineExceeded);
        - `outlines`: False leaves the objects' outlines out (bounds and centroid only);
        - `max_queued`: unread snapshots kept; beyond it the oldest are dropped and counted in
          `track.dropped` (the final one is always kept);
        - `request_id`: an id of your own (default: a fresh one).

        Returns a Tracking: iterate it, enter it (`async with ... as track`) or await it for the
        Track. A bad argument raises InvalidArgument at once; nothing is sent before that.
        """
        self._require_started()
        check_timeout(timeout_s)
        seconds(rpc_timeout_s, "rpc_timeout_s", 3600.0)
        check_queue(max_queued, "snapshots")
        for name, value in (("rate_hz", rate_hz), ("duration_s", duration_s)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
                raise InvalidArgument(f"{name}: {value!r} must be a number > 0 (a track runs at a rate for a time)")
        fusion = fusion_options(deadline_s, drop_after_s)
        request, message = self._build(
            filter_def, region, ContinuousMode(float(rate_hz), float(duration_s)), outlines, request_id, fusion
        )
        return Tracking(lambda: open_track(self, request, message, timeout_s, rpc_timeout_s, max_queued))

    async def cameras(
        self,
        region: RegionLike | None = None,
        *,
        frame: str | None = None,
        rpc_timeout_s: float = DEFAULT_RPC_TIMEOUT_S,
    ) -> list[CameraInfo]:
        """The cameras the server routes to in this client's `frame` (or in `frame`; "" every
        frame's), optionally only those that see `region`; each page of the answer waits at most
        `rpc_timeout_s` seconds per attempt."""
        self._require_started()
        msg = registry_pb2.ListCamerasRequest()
        wanted = self.frame if frame is None else frame
        if wanted:
            msg.frame = check_frame(wanted)
        if region is not None:
            msg.region.CopyFrom(self._regions.get(region)[1])
        found: list[CameraInfo] = []

        async def page() -> registry_pb2.ListCamerasReply:
            try:
                reply: registry_pb2.ListCamerasReply = await self._registry.ListCameras(
                    msg, timeout=rpc_timeout_s, metadata=self.security.metadata()
                )
            except grpc.RpcError as exc:
                raise _grpc.from_rpc_error(exc, f"server {self.server}") from None
            return reply

        while True:  # the server answers a page at a time: follow next_page_token to the end
            reply = await self._retrying("listing cameras", page)
            found.extend(camera_info_from_pb(c) for c in reply.cameras)
            if not reply.next_page_token or reply.next_page_token == msg.page_token:
                return found
            msg.page_token = reply.next_page_token


def _is_ip_literal(address: str) -> bool:
    host = host_of(address).strip("[]")
    try:
        ipaddress.ip_address(host)
    except ValueError:
        return False
    return True

"""DrvsClient: robot code asks for objects and gets Python objects back."""

from __future__ import annotations

import asyncio
import collections
import contextlib
import itertools
import logging
import secrets
from collections.abc import AsyncIterator, Sequence
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any, TypeAlias

import grpc
from grpc import aio
from shapely.geometry import Polygon

from drvs import _grpc
from drvs.convert import polygon_from_pb, region_to_pb, report_from_pb, request_to_pb
from drvs.errors import DrvsError, InvalidArgument, Unavailable
from drvs.geometry import box_region, polygon_region
from drvs.meter import CountingRelay
from drvs.model import ContinuousMode, Detection, DetectionReport, DetectionRequest
from drvs.net import dialable_address, format_address, host_of, local_ip_towards, parse_address
from drvs.report_auth import key_matches, new_secret
from drvs.request_stream import RequestStream
from drvs.security import Security
from drvs.v1 import detection_pb2, detection_pb2_grpc, geometry_pb2, registry_pb2, registry_pb2_grpc

log = logging.getLogger("drvs.robot")

#: How long to wait for every camera's final report beyond a request's own duration.
DEFAULT_TIMEOUT_S = 5.0
#: Reports buffered per request before the listener pushes back on cameras.
MAX_QUEUED_REPORTS = 1024
#: The longest wait between retries of a request the server could not take.
MAX_BACKOFF_S = 5.0
#: Regions a client keeps built and encoded, by the value robot code passed.
REGION_CACHE_SIZE = 256

RegionLike: TypeAlias = "Polygon | Sequence[float] | Sequence[Sequence[float]]"


def as_region(region: RegionLike) -> Polygon:
    """A shapely polygon, a box (x0, y0, x1, y1), or a list of [x, y] points."""
    if isinstance(region, Polygon):
        return polygon_region(list(region.exterior.coords), "region")
    items: list[Any] = list(region)
    if len(items) == 4 and all(isinstance(v, (int, float)) for v in items):
        return box_region(*items)
    if items and all(isinstance(p, Sequence) for p in items):
        return polygon_region(items, "region")
    raise InvalidArgument("region: expected a shapely Polygon, a box (x0, y0, x1, y1) or a list of [x, y] points")


class _Regions:
    """Robot code asks about the same few regions again and again: each is built, validated and
    encoded once. Building the polygon and its wire form was a tenth of a request's CPU at 30 Hz.
    Keyed by the values robot code passed (a shapely Polygon by identity: it is immutable)."""

    def __init__(self, size: int = REGION_CACHE_SIZE) -> None:
        self._size = size
        self._cache: collections.OrderedDict[Any, tuple[Any, Polygon, geometry_pb2.Region]] = collections.OrderedDict()

    @staticmethod
    def _key(region: RegionLike) -> Any:
        if isinstance(region, Polygon):
            return ("polygon", id(region))
        try:
            key = tuple(tuple(p) if isinstance(p, Sequence) else p for p in region)
            hash(key)
        except TypeError:
            return None
        return key

    def get(self, region: RegionLike) -> tuple[Polygon, geometry_pb2.Region]:
        key = self._key(region)
        hit = self._cache.get(key) if key is not None else None
        if hit is not None and (not isinstance(region, Polygon) or hit[0] is region):
            self._cache.move_to_end(key)
            return hit[1], hit[2]
        polygon = as_region(region)  # a bad region raises here, every time, and is not kept
        encoded = region_to_pb(polygon)
        if key is not None:
            self._cache[key] = (region, polygon, encoded)
            if len(self._cache) > self._size:
                self._cache.popitem(last=False)
        return polygon, encoded


@dataclass(frozen=True)
class CameraInfo:
    camera_id: str
    address: str
    field_of_view: Polygon
    detector_kinds: tuple[str, ...]
    lease_remaining_s: float


@dataclass(frozen=True)
class CameraError:
    """Why a camera's answer is missing from a result. `code` is a gRPC status name:
    UNAVAILABLE (could not be reached, skipped after a failure, gone without deregistering, or no
    fresh frame), DEADLINE_EXCEEDED (no final report within the timeout), RESOURCE_EXHAUSTED (busy)."""

    code: str
    message: str


@dataclass
class DetectionResult:
    """Everything one request brought back.

    Absence of detections means "nothing there" only where a camera looked: `complete` is False
    when any camera that sees the region did not answer (`missing_cameras`, each with its
    `camera_errors` entry), and `uncovered` holds the parts of the region nobody looked at because
    of that. `coverage_uncertain_s` > 0: the server restarted recently and may not know every
    camera yet, so parts of the region no dispatched camera sees are not known to be clear.
    """

    request_id: str
    camera_ids: tuple[str, ...]
    reports: list[DetectionReport] = field(default_factory=list)
    #: Cameras the server named in its reply as seeing the region but not asked.
    skipped: dict[str, CameraError] = field(default_factory=dict)
    #: Dispatched cameras whose report stream ended before their final report.
    interrupted: set[str] = field(default_factory=set)
    uncovered: list[Polygon] = field(default_factory=list)
    coverage_uncertain_s: float = 0.0

    @property
    def detections(self) -> list[Detection]:
        return [d for r in self.reports for d in r.detections]

    @property
    def finished_cameras(self) -> set[str]:
        return {r.camera_id for r in self.reports if r.final}

    @property
    def unfinished_cameras(self) -> set[str]:
        """Dispatched cameras that have sent no final report (yet)."""
        return set(self.camera_ids) - self.finished_cameras

    @property
    def camera_errors(self) -> dict[str, CameraError]:
        """Every camera whose answer is missing, and why."""
        errors = dict(self.skipped)
        for camera_id in self.unfinished_cameras:
            if camera_id in self.interrupted:
                errors[camera_id] = CameraError(
                    "UNAVAILABLE", f"camera {camera_id}: its report stream ended before its final report"
                )
            else:
                errors[camera_id] = CameraError("DEADLINE_EXCEEDED", f"camera {camera_id}: no final report in time")
        for r in self.reports:
            if r.final and r.error:
                errors[r.camera_id] = CameraError(r.error_code or "UNKNOWN", r.error)
        return errors

    @property
    def missing_cameras(self) -> set[str]:
        """Cameras that see the region but did not answer: not asked (skipped, gone), failed, or
        sent no final report before the timeout."""
        return set(self.camera_errors)

    @property
    def complete(self) -> bool:
        return not self.missing_cameras

    @property
    def errors(self) -> list[str]:
        return [r.error for r in self.reports if r.error]


class Subscription:
    """The reports of one request, as an async iterator that ends when every dispatched camera has
    sent its final report, or when the timeout passes."""

    def __init__(self, client: DrvsClient, request: DetectionRequest, timeout_s: float) -> None:
        self._client = client
        self.request = request
        self.request_id = request.request_id
        self.camera_ids: tuple[str, ...] = ()
        # A deque and one waiter future, not an asyncio.Queue with wait_for: at 30 requests a
        # second per robot, a task per report was a visible share of the robot's CPU.
        self._pending: collections.deque[DetectionReport] = collections.deque()
        self._wakeup: asyncio.Future[None] | None = None
        self._room = asyncio.Event()
        self._room.set()
        self._timer: asyncio.TimerHandle | None = None
        self._expired = False
        self._timeout_s = timeout_s
        self.closed = False
        self.result = DetectionResult(request.request_id, ())
        self._finals: set[str] = set()  # cameras whose final report arrived
        #: camera id -> when (loop time) its latest report arrived: a continuous request's camera
        #: that falls silent is a camera that stopped looking.
        self.last_report_at: dict[str, float] = {}

    def _dispatched(self, reply: detection_pb2.DetectionReply) -> None:
        self.camera_ids = tuple(reply.camera_ids)
        self.result.camera_ids = self.camera_ids
        self.result.skipped = {m.camera_id: CameraError(m.code, m.message) for m in reply.missing_cameras}
        self.result.uncovered = [polygon_from_pb(p, "uncovered") for p in reply.uncovered]
        self.result.coverage_uncertain_s = reply.coverage_uncertain_s
        loop = asyncio.get_running_loop()
        self._timer = loop.call_later(self.request.continuous.duration_s + self._timeout_s, self._expire)

    def _expire(self) -> None:
        self._expired = True
        self._wake()

    def _wake(self) -> None:
        if self._wakeup is not None and not self._wakeup.done():
            self._wakeup.set_result(None)

    def _stream_ended(self, cameras: set[str]) -> None:
        """The report stream of `cameras` ended: those this request went to that have not sent
        their final report are interrupted (a camera that reconnects presents its key again and
        reports on)."""
        for camera_id in cameras:
            if camera_id in self.camera_ids and camera_id not in self._finals:
                self.result.interrupted.add(camera_id)

    @property
    def interrupted(self) -> set[str]:
        """Dispatched cameras whose report stream ended before their final report, and that have not
        reported since: they stopped looking (crashed, or cut off)."""
        return self.result.interrupted

    async def _deliver(self, report: DetectionReport) -> bool:
        """Queue a report; waits while MAX_QUEUED_REPORTS are unread, so a slow robot pushes back
        on the camera instead of buffering without bound. False once the subscription is closed."""
        while len(self._pending) >= MAX_QUEUED_REPORTS and not self.closed:
            self._room.clear()
            await self._room.wait()
        if self.closed:
            return False
        self._pending.append(report)
        self.last_report_at[report.camera_id] = asyncio.get_running_loop().time()
        self.result.interrupted.discard(report.camera_id)
        if report.final:
            self._finals.add(report.camera_id)
        self._wake()
        return True

    async def _next(self) -> DetectionReport | None:
        while not self._pending:
            if self._expired or self.closed:
                return None
            self._wakeup = asyncio.get_running_loop().create_future()
            await self._wakeup
        report = self._pending.popleft()
        self._room.set()
        return report

    def __aiter__(self) -> AsyncIterator[DetectionReport]:
        return self._iterate()

    async def _iterate(self) -> AsyncIterator[DetectionReport]:
        try:
            while not self.closed and self.result.unfinished_cameras:
                report = await self._next()
                if report is None:
                    break
                if report.camera_id not in self.camera_ids:
                    self._client.reports_rejected += 1
                    log.warning(
                        "request %s: report from undispatched camera %s ignored",
                        self.request_id,
                        report.camera_id,
                    )
                    continue
                self.result.reports.append(report)
                yield report
        finally:
            self.close()

    async def collect(self) -> DetectionResult:
        async for _ in self:
            pass
        return self.result

    def close(self) -> None:
        """Stop listening: cameras still streaming for this request are told to stop, and the
        server frees the request's place among the robot's running continuous requests."""
        if not self.closed:
            self.closed = True
            if self.request.continuous.duration_s > 0 and not self._expired and self.result.unfinished_cameras:
                self._client._cancel_at_server(self.request_id)
            if self._timer is not None:
                self._timer.cancel()
            self._wake()
            self._room.set()
            self._client._subscriptions.pop(self.request_id, None)


class DrvsClient:
    """Connects to a DRVS server and runs the robot's CallbackCoordinates listener.

    The listener binds `listen` (default: the local address that reaches the server, port 0) and
    tells cameras to call `advertise` (default: the bound address).
    """

    def __init__(
        self,
        server: str,
        *,
        robot_id: str = "",
        listen: str | None = None,
        advertise: str | None = None,
        meter: bool = False,
        retries: int = 0,
        retry_backoff_s: float = 0.2,
        security: Security | None = None,
    ) -> None:
        self.security = security or Security()
        parse_address(server, "server")
        self.server = server
        self.robot_id = robot_id
        self.listen = listen or format_address(local_ip_towards(server), 0)
        parse_address(self.listen, "listen", allow_port_zero=True)
        self._advertise = advertise
        if advertise:
            parse_address(advertise, "advertise")
        self.port = 0
        self._channel: aio.Channel | None = None
        self._listener: aio.Server | None = None
        self._subscriptions: dict[str, Subscription] = {}
        self.reports_received = 0
        #: Reports refused: not from a camera the request was dispatched to, or not on its stream.
        self.reports_rejected = 0
        # Proves reports (drvs.report_auth): the server derives each camera's key from it.
        self._report_secret = new_secret()
        # camera id -> the report streams that presented its key: the only ones its reports count on
        # (its own, and the server's when it answered for the camera).
        self._camera_streams: dict[str, set[object]] = {}
        self._closing = False
        self._open_at_close: list[str] = []
        self._report_streams: set[asyncio.Task[Any]] = set()
        # Request ids: a random prefix per client (a restarted robot never reuses a live id) and a
        # counter; short, because the id travels in the request, the reply and every report.
        self._id_prefix = secrets.token_urlsafe(3)  # 4 characters, 24 random bits
        self._id_counter = itertools.count(1)
        self._requests: RequestStream | None = None
        # With meter=True, both of the robot's connections pass through counting relays, so
        # wire_bytes() reports the real bytes its sockets carried.
        self._meter = meter
        # A request the server could not take (Unavailable: down, restarting, unreachable) is sent
        # again up to `retries` times, after retry_backoff_s, doubling, at most MAX_BACKOFF_S.
        if retries < 0 or not (0 < retry_backoff_s <= MAX_BACKOFF_S):
            raise InvalidArgument(f"retries must be >= 0 and retry_backoff_s in (0, {MAX_BACKOFF_S:g}]")
        self.retries = retries
        self.retry_backoff_s = retry_backoff_s
        self._relays: list[CountingRelay] = []
        self._regions = _Regions()

    def wire_bytes(self) -> tuple[int, int]:
        """(received, sent) TCP payload bytes on the robot's sockets; needs meter=True."""
        if not self._relays:
            raise DrvsError("wire_bytes() needs DrvsClient(meter=True)")
        callback, server = self._relays
        return callback.to_target + server.from_target, callback.from_target + server.to_target

    def ethernet_bytes(self) -> tuple[int, int]:
        """(received, sent) bytes on the robot's connections as a 1500-byte-MTU Ethernet link carries
        them: payload plus Ethernet, IP and TCP headers of every segment, ACKs included (drvs.meter);
        needs meter=True."""
        if not self._relays:
            raise DrvsError("ethernet_bytes() needs DrvsClient(meter=True)")
        callback, server = self._relays
        wire = callback.wire() + server.wire()
        return wire.to_host, wire.from_host

    @property
    def callback_address(self) -> str:
        if self._meter and self._relays:
            return dialable_address(self.listen, self._relays[0].port, self.server)
        if self._advertise:
            return self._advertise
        return dialable_address(self.listen, self.port, self.server)

    async def start(self) -> None:
        listener = _grpc.new_server()
        detection_pb2_grpc.add_CallbackCoordinatesServicer_to_server(_Listener(self), listener)
        self.port = self.security.bind(listener, self.listen)
        await listener.start()
        self._listener = listener
        server_address = self.server
        if self._meter:
            callback_relay = CountingRelay(
                host_of(self.listen), self.port, listen_host=host_of(self.listen), side="target"
            )
            host, port = parse_address(self.server, "server")
            server_relay = CountingRelay(host, port)
            await callback_relay.start()
            await server_relay.start()
            self._relays = [callback_relay, server_relay]
            server_address = format_address("127.0.0.1", server_relay.port)
        self._channel = self.security.channel(server_address)
        self._detect = detection_pb2_grpc.DetectObjectBoundaryStub(self._channel)
        self._requests = RequestStream(self._detect, f"server {self.server}", metadata=self.security.metadata())
        self._registry = registry_pb2_grpc.RegisterVisionServiceStub(self._channel)
        log.debug("robot %r listening for reports on %s", self.robot_id, self.callback_address)

    def _accepts(self, message: detection_pb2.DetectionReport, stream: object) -> bool:
        """A camera's reports count only on a stream that presented its key."""
        camera_id = message.camera_id
        if message.report_key:
            if not key_matches(self._report_secret, camera_id, message.report_key):
                return False
            self._camera_streams.setdefault(camera_id, set()).add(stream)
            return True
        return stream in self._camera_streams.get(camera_id, ())

    def new_request_id(self) -> str:
        return f"{self._id_prefix}{next(self._id_counter):x}"

    def _cancel_at_server(self, request_id: str) -> None:
        if self._requests is not None:
            self._requests.cancel_soon(request_id)

    async def close(self) -> None:
        self._closing = True
        # Requests still open: each report stream tells its camera to stop them before it ends,
        # so cameras do not go on dialling a robot that has gone.
        self._open_at_close = list(self._subscriptions)
        for sub in list(self._subscriptions.values()):
            sub.close()
        for task in list(self._report_streams):
            task.cancel()
        if self._requests is not None:
            await self._requests.flush_cancels()
            await self._requests.close()
        if self._listener is not None:
            await self._listener.stop(0.5)
            self._listener = None
        if self._channel is not None:
            await self._channel.close()
            self._channel = None
        for relay in self._relays:
            await relay.close()

    async def __aenter__(self) -> DrvsClient:
        await self.start()
        return self

    async def __aexit__(
        self, et: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.close()

    def _require_started(self) -> None:
        if self._channel is None:
            raise DrvsError("DrvsClient is not started; use `async with DrvsClient(...)` or await start()")

    async def subscribe(
        self,
        filter_def: str,
        region: RegionLike,
        *,
        rate_hz: float = 0.0,
        duration_s: float = 0.0,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        request_id: str | None = None,
        rpc_timeout_s: float = 5.0,
        outlines: bool = True,
    ) -> Subscription:
        """Send a request; iterate the returned Subscription for its reports.

        outlines=False asks for bounds, centroid and ground contact only (an empty outline).
        """
        self._require_started()
        polygon, region_pb = self._regions.get(region)
        request = DetectionRequest(
            request_id=request_id or self.new_request_id(),
            robot_id=self.robot_id,
            filter_def=filter_def,
            region=polygon,
            callback_address=self.callback_address,
            continuous=ContinuousMode(float(rate_hz), float(duration_s)),
            omit_outlines=not outlines,
        )
        request.validate(unknown_types=True)
        if request.request_id in self._subscriptions:
            raise InvalidArgument(f"request_id: {request.request_id!r} is already in use")
        # Registered before sending: a camera may report before the server's reply arrives.
        sub = Subscription(self, request, timeout_s)
        self._subscriptions[request.request_id] = sub
        assert self._requests is not None
        message = request_to_pb(request, region=region_pb)
        message.report_secret = self._report_secret
        try:
            reply = await self._send(message, rpc_timeout_s)
        except BaseException:
            sub.close()
            raise
        sub._dispatched(reply)
        return sub

    async def _send(
        self, message: detection_pb2.DetectionRequest, rpc_timeout_s: float
    ) -> detection_pb2.DetectionReply:
        assert self._requests is not None
        backoff = self.retry_backoff_s
        for attempt in itertools.count():
            try:
                return await self._requests.request(message, rpc_timeout_s)
            except Unavailable:
                if attempt >= self.retries:
                    raise
                log.info(
                    "server %s unavailable; retrying request %s in %.1f s", self.server, message.request_id, backoff
                )
                await asyncio.sleep(backoff)
                backoff = min(backoff * 2, MAX_BACKOFF_S)
        raise AssertionError("unreachable")

    async def detect(
        self,
        filter_def: str,
        region: RegionLike,
        *,
        rate_hz: float = 0.0,
        duration_s: float = 0.0,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        outlines: bool = True,
    ) -> DetectionResult:
        """Send a request and collect every report until each camera is done or the timeout passes."""
        sub = await self.subscribe(
            filter_def, region, rate_hz=rate_hz, duration_s=duration_s, timeout_s=timeout_s, outlines=outlines
        )
        return await sub.collect()

    async def cameras(self, region: RegionLike | None = None, *, rpc_timeout_s: float = 5.0) -> list[CameraInfo]:
        """The cameras the server routes to (optionally only those that see `region`)."""
        self._require_started()
        msg = registry_pb2.ListCamerasRequest()
        if region is not None:
            msg.region.CopyFrom(self._regions.get(region)[1])
        found: list[CameraInfo] = []
        while True:  # the server answers a page at a time: follow next_page_token to the end
            try:
                reply = await self._registry.ListCameras(msg, timeout=rpc_timeout_s, metadata=self.security.metadata())
            except grpc.RpcError as exc:
                raise _grpc.from_rpc_error(exc, f"server {self.server}") from None
            found.extend(
                CameraInfo(
                    camera_id=c.camera_id,
                    address=c.address,
                    field_of_view=polygon_from_pb(c.field_of_view, "field_of_view"),
                    detector_kinds=tuple(c.detector_kinds),
                    lease_remaining_s=c.lease_remaining_s,
                )
                for c in reply.cameras
            )
            if not reply.next_page_token or reply.next_page_token == msg.page_token:
                return found
            msg.page_token = reply.next_page_token


class _Listener(detection_pb2_grpc.CallbackCoordinatesServicer):
    def __init__(self, client: DrvsClient) -> None:
        self._client = client

    async def ReportDetections(
        self,
        request_iterator: AsyncIterator[detection_pb2.DetectionReport],
        context: aio.ServicerContext[Any, Any],
    ) -> None:
        """One camera's stream of reports, for any of this robot's requests, for as long as it lasts.

        A closing robot cancels each stream's task and ends the stream itself (the camera sees a
        normal end) instead of leaving gRPC to cancel it.
        """
        client = self._client
        task = asyncio.current_task()
        assert task is not None
        client._report_streams.add(task)
        stream = object()  # this stream's identity, which a camera's key binds its reports to
        warned = False
        try:
            async for message in request_iterator:
                sub = client._subscriptions.get(message.request_id)
                if not client._accepts(message, stream):
                    client.reports_rejected += 1
                    if not warned:  # once per stream: a hostile peer does not flood the log
                        warned = True
                        log.warning(
                            "report for request %s in camera %r's name from %s rejected: no valid report key "
                            "for this stream (not a camera the server dispatched to, or not its stream)",
                            message.request_id,
                            message.camera_id[:40],
                            context.peer(),
                        )
                    sub = None  # answered as an unknown request: the sender learns nothing more
                if sub is None or not await sub._deliver(report_from_pb(message, sub.request.filter_def)):
                    # Unknown or closed request: tell the camera to stop sending its reports.
                    await context.write(detection_pb2.ReportControl(cancelled_request_ids=[message.request_id]))
                    continue
                client.reports_received += 1
        except asyncio.CancelledError:
            if not client._closing:
                raise
            # The robot is closing: stop what is still open, then end the stream normally, so the
            # camera sees it end, not fail.
            if client._open_at_close:
                with contextlib.suppress(Exception):
                    control = detection_pb2.ReportControl(cancelled_request_ids=client._open_at_close)
                    await asyncio.wait_for(context.write(control), 0.5)
        finally:
            client._report_streams.discard(task)
            cameras = set()  # cameras that reported only on this stream: now they have none
            for camera_id, streams in list(client._camera_streams.items()):
                if stream in streams:
                    streams.discard(stream)
                    if not streams:
                        del client._camera_streams[camera_id]
                        cameras.add(camera_id)
            if cameras:
                for sub in list(client._subscriptions.values()):
                    sub._stream_ended(cameras)

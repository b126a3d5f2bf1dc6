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

import warnings
from dataclasses import replace
from typing import Literal, overload

import grpc

from drvs.core.errors import (
    FailedPrecondition,
    InvalidArgument,
)
from drvs.core.model import (
    DEFAULT_FRAME,
    ContinuousMode,
    DetectionRequest,
    FusionOptions,
    Snapshot,
    check_frame,
)
from drvs.robot.connection import ClientConnection
from drvs.robot.handles import Connecting
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
from drvs.robot.regions import REGION_CACHE_SIZE, RegionLike, as_region
from drvs.robot.results import CameraInfo, DetectionResult, camera_info_from_pb
from drvs.robot.retry import RetryPolicy
from drvs.robot.subscription import Subscribing, Subscription, open_subscription
from drvs.robot.throttle import DEFAULT_K
from drvs.robot.track import Track, Tracking, open_track
from drvs.v1 import detection_pb2, registry_pb2
from drvs.wire import _grpc
from drvs.wire.convert import polygon_from_pb, request_to_pb, snapshot_from_pb
from drvs.wire.security import Security

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


class DrvsClient(ClientConnection):
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
    - `security`: a drvs.wire.security.Security with TLS files and this robot's token (default: plain).

    Constructing one does no network work (no name is resolved); `start()` (or `async with
    DrvsClient(...)`) opens the channel without checking the server, and a call
    to a server that is not there fails then, with Unavailable. Every error is a drvs.core.errors
    exception with `.code` (the gRPC status name) and `.camera_id`.

    Timeouts, in seconds, one meaning each: `connect_timeout_s` (connect) bounds one attempt to
    reach the server; `rpc_timeout_s` (subscribe, detect, cameras) bounds one attempt's wait for the
    server's reply; `timeout_s` (subscribe, detect) is how long, after that reply and beyond the
    request's `duration_s`, to wait for every camera's final report (never raises: a late camera
    is in `result.camera_errors`). `retry` repeats the first two after Unavailable.

    Counters: `reports_received` (reports handed to subscriptions) and `reports_rejected`
    (reports refused: not from a camera the request went to, or not on its stream).
    """

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
        `drvs.core.model.Snapshot` (`time, objects, errors = snapshot`): each physical object
        once, as a `WorldObject`, however many cameras saw it. No listener is used (`track()` gives
        snapshots over time).

        - `filter_def`, `region`, `outlines`: what and where, as for subscribe;
        - `deadline_s`: the server answers with what it has this many seconds after it sent the
          request to the cameras, naming the cameras that did not report in time in
          `snapshot.camera_errors` (DEADLINE_EXCEEDED); None or 0: the server's default (2 s);
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
        """Track objects: the server fuses the cameras' reports and sends a `drvs.core.model.Snapshot`
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
          `camera_errors`;
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

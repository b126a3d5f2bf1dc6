"""Fused requests in the server: the cameras report to the server, which merges what they see.

A robot's request with `fusion` set is forwarded to its cameras with `report_to_server`: each
camera sends its reports to the server (on a CallbackCoordinates.ReportDetections stream, as it
would to a robot), presenting the key the server made for that camera and request. A
`FusionSession` per request gathers them:

- a single shot (`SingleShot`) waits until every dispatched camera has sent its final report or
  failed, or until the request's deadline, then merges the reports (`drvs.server.fusion.fuse`) into one
  snapshot, delivered in the request's one reply;
- a continuous request (`Continuous`) makes a snapshot every period from the reports received since
  the last one, through a `drvs.server.tracking.Tracker` (stable track ids), the last one final. A mobile
  camera whose field of view enters its region while it runs is asked for the rest of it, and joins
  it (`Continuous.add_camera`; the server decides when, on the camera's pose update).

Cameras that failed, refused, or did not report in time are named in each snapshot's
missing_cameras; no camera holds up the others beyond the deadline. `ReportIntake` is one camera's
report stream: it takes a report only for a fused request in flight that was dispatched to that
camera, proven by that camera's key; anything else is dropped and counted, and the camera is told
to stop sending it (ReportControl), as a robot would. Everything is bounded: sessions in flight
(`FusionSessions`), the one newest report kept per camera and period, the (request, camera) pairs a
stream remembers as proven, the cancels waiting to be written.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import logging
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from typing import Any, Protocol

import grpc
import shapely
from shapely.geometry import Polygon

from drvs.core.errors import ResourceExhausted
from drvs.core.geometry import Homography
from drvs.core.model import CameraError, DetectionReport, DetectionRequest, Snapshot, WorldObject, errors_by_camera
from drvs.server.fusion import fuse
from drvs.server.tracking import Tracker
from drvs.v1 import detection_pb2
from drvs.wire import metrics
from drvs.wire.convert import report_from_pb, snapshot_to_pb
from drvs.wire.request_stream import refusal

log = logging.getLogger("drvs.server")

#: Fused requests in flight in one server at once (single shots waiting and continuous ones).
MAX_SESSIONS = 4096
#: (request, camera) pairs one report stream remembers as proven by their key.
MAX_VERIFIED = 4096
#: Request ids waiting to be written back to a camera as cancelled.
MAX_CANCELS = 4096
#: Detections of one report that fusion takes (the rest are dropped, and logged): merging costs
#: more than linearly in them.
MAX_DETECTIONS_PER_REPORT = 128
#: Up to this many detections in all, a snapshot is fused on the event loop (two cameras' 2 each
#: take about 1 ms, 8 each 3 ms, 128 each 33 ms on the 2-core test machine); more are fused in a
#: worker thread, so that the loop keeps serving.
INLINE_DETECTIONS = 16
#: Ended sessions remembered, so that a camera's report that comes after its request ended counts as
#: late, not as a forgery.
MAX_ENDED = 1024

FUSING_FAILED = "drvs-server: fusing the cameras' reports failed"

HomographyOf = Callable[[str], Homography | None]


class Delivery(Protocol):
    """Where a session's replies go: the robot's request stream, or a DetectObjects call."""

    def send(self, reply: detection_pb2.DetectionReply, last: bool) -> bool:
        """Queue `reply`; `last`: the session's last. False when it was not queued (the robot is not
        reading, or is gone)."""

    def abandon(self) -> None:
        """The session ends without a last reply (cancelled, or its stream ended)."""


class FusionSession:
    """One fused request in flight: which cameras it was dispatched to, their keys, what they
    reported, and where its replies go. `start(reply)` once dispatched; `end(why)` stops it early."""

    def __init__(
        self,
        request: DetectionRequest,
        cameras: Sequence[str],
        keys: dict[str, bytes],
        homography_of: HomographyOf,
        delivery: Delivery,
        on_end: Callable[[FusionSession], None],
        missing: Sequence[CameraError] = (),
        forward_id: str = "",
        secret: bytes = b"",
        forwarded: detection_pb2.DetectionRequest | None = None,
    ) -> None:
        assert request.fusion is not None
        self.request = request
        self.request_id = request.request_id
        #: The id the cameras know the request by (unique in the server: robots choose theirs).
        self.forward_id = forward_id or request.request_id
        #: The secret the cameras' keys are made from, and the message forwarded to them (without a
        #: key): a camera asked later (`Continuous.add_camera`) gets a copy, with its own key.
        self.secret = secret
        self.forwarded = forwarded
        self.options = request.fusion
        self.cameras = tuple(cameras)
        self.keys = keys
        self._homography_of = homography_of
        self._delivery = delivery
        self._on_end = on_end
        self._planned_missing = tuple(missing)
        #: camera id -> why it will not report (its forward failed, it refused, its report said so)
        self._failed: dict[str, CameraError] = {}
        #: cameras that sent their final report
        self._finished: set[str] = set()
        #: camera id -> the report stream its reports came on (told when the request ends early)
        self._streams: dict[str, ReportIntake] = {}
        self._reply = detection_pb2.DetectionReply(request_id=request.request_id)
        self._started = False
        self._settled = False
        self.ended = False
        self.outlines = not request.omit_outlines
        #: the robot reads geometry as millimetre integers (an older one asked without saying so)
        self.compact = request.fusion is not None and request.fusion.compact_geometry
        self._init()

    def _init(self) -> None:
        """The subclass's own state."""

    def accepts(self, camera_id: str, key: bytes) -> bool:
        """Is `key` the one made for `camera_id` for this request (so the camera was dispatched to)?"""
        expected = self.keys.get(camera_id)
        return expected is not None and hmac.compare_digest(expected, key)

    def start(self, reply: detection_pb2.DetectionReply) -> None:
        """Dispatched: `reply` is the answer to the request (cameras, missing, uncovered)."""
        self._reply = reply
        self._started = True

    def report(self, report: DetectionReport, stream: ReportIntake) -> None:
        """A report from a dispatched camera (its key checked)."""
        raise NotImplementedError

    def failed(self, camera_id: str, error: CameraError) -> None:
        """The camera will not report: its forward failed or it refused the request."""
        if self.ended or camera_id in self._failed or camera_id in self._finished:
            return
        self._failed[camera_id] = error
        self._changed()

    def stream_ended(self, stream: ReportIntake) -> None:
        for camera_id, known in list(self._streams.items()):
            if known is stream:
                del self._streams[camera_id]

    def end(self, why: str) -> None:
        """Stop now, without a last reply: the robot cancelled, its stream ended, the server stops.
        Cameras that have not finished are told to stop (on the streams they reported on)."""
        if self.ended:
            return
        log.debug("fused request %s ends: %s", self.request_id, why)
        self._close()

    def _changed(self) -> None:
        """A camera finished or failed."""

    def _deliver(self, reply: detection_pb2.DetectionReply, last: bool) -> bool:
        if self._settled:
            return False
        if last:
            self._settled = True
        sent = self._delivery.send(reply, last)
        (metrics.FUSION_SNAPSHOTS_SENT if sent else metrics.FUSION_SNAPSHOTS_DROPPED).inc()
        return sent

    def _close(self) -> None:
        if self.ended:
            return
        self.ended = True
        self._forget()
        for camera_id, stream in self._streams.items():
            if camera_id not in self._finished:
                stream.cancel(self.forward_id)
        self._streams.clear()
        if not self._settled:
            self._settled = True
            self._delivery.abandon()
        self._on_end(self)

    def _forget(self) -> None:
        """Drop what the session gathered: an ended one is remembered only by its keys."""

    def _missing(self, extra: Sequence[CameraError] = ()) -> tuple[CameraError, ...]:
        failed = [self._failed[c] for c in self.cameras if c in self._failed]
        return (*self._planned_missing, *failed, *extra)

    def _fuse(self, reports: Sequence[DetectionReport]) -> list[WorldObject]:
        return fuse(reports, self._homography_of)

    @staticmethod
    def _inline(reports: Sequence[DetectionReport]) -> bool:
        return sum(len(r.detections) for r in reports) <= INLINE_DETECTIONS


class SingleShot(FusionSession):
    """Waits for every dispatched camera's final report (or failure), or the deadline, then answers
    the request with one snapshot."""

    def _init(self) -> None:
        self._pending = set(self.cameras)
        self._reports: dict[str, DetectionReport] = {}
        self._timer: asyncio.TimerHandle | None = None
        self._finishing = False
        self._fusing: asyncio.Task[None] | None = None

    def start(self, reply: detection_pb2.DetectionReply) -> None:
        super().start(reply)
        loop = asyncio.get_running_loop()
        self._timer = loop.call_later(self.options.single_shot_deadline_s, self._deadline)
        # Not at once: the caller queues the reply's place first.
        loop.call_soon(self._changed)

    def report(self, report: DetectionReport, stream: ReportIntake) -> None:
        camera_id = report.camera_id
        if self.ended or camera_id not in self._pending:
            return
        self._streams[camera_id] = stream
        if not report.final:
            return
        self._pending.discard(camera_id)
        self._finished.add(camera_id)
        error = report.camera_error
        if error is not None:
            self._failed[camera_id] = error
        else:
            self._reports[camera_id] = report
        self._changed()

    def failed(self, camera_id: str, error: CameraError) -> None:
        self._pending.discard(camera_id)
        super().failed(camera_id, error)

    def _changed(self) -> None:
        if self._started and not self._pending and not self.ended:
            self._finish()

    def _deadline(self) -> None:
        if self.ended:
            return
        deadline = self.options.single_shot_deadline_s
        for camera_id in sorted(self._pending):
            self._failed[camera_id] = CameraError(
                "DEADLINE_EXCEEDED", f"camera {camera_id}: no report within the deadline of {deadline:g} s", camera_id
            )
        self._pending.clear()
        self._finish()

    def _finish(self) -> None:
        if self._finishing:
            return
        self._finishing = True
        if self._timer is not None:
            self._timer.cancel()
        reports = [self._reports[c] for c in self.cameras if c in self._reports]
        if self._inline(reports):
            objects: list[WorldObject] | None = None
            try:
                objects = self._fuse(reports)
            except Exception:
                log.exception("fused request %s: fusing %d reports failed", self.request_id, len(reports))
            self._answer(reports, objects)
        else:
            self._fusing = asyncio.get_running_loop().create_task(self._fuse_aside(reports))

    async def _fuse_aside(self, reports: list[DetectionReport]) -> None:
        objects: list[WorldObject] | None = None
        try:
            objects = await asyncio.to_thread(self._fuse, reports)
        except Exception:
            log.exception("fused request %s: fusing %d reports failed", self.request_id, len(reports))
        self._fusing = None
        if not self.ended:
            self._answer(reports, objects)

    def _answer(self, reports: list[DetectionReport], objects: list[WorldObject] | None) -> None:
        """The one reply: the dispatch's, with its snapshot (None objects: fusing failed)."""
        reply = self._reply
        if objects is None:
            self._deliver(refusal(self.request_id, grpc.StatusCode.INTERNAL, FUSING_FAILED), last=True)
            self._close()
            return
        try:
            snapshot = Snapshot(
                time=max((r.capture_time for r in reports), default=0.0) or time.time(),
                objects=tuple(objects),
                camera_errors=errors_by_camera(self._missing()),
                camera_ids=tuple(sorted(r.camera_id for r in reports)),
                sequence=0,
                final=True,
                request_id=self.request_id,
            )
            snapshot_to_pb(snapshot, self.outlines, into=reply.snapshot, compact=self.compact)  # in place: no copy
        except Exception:
            log.exception("fused request %s: making its snapshot failed", self.request_id)
            reply = refusal(self.request_id, grpc.StatusCode.INTERNAL, FUSING_FAILED)
        self._deliver(reply, last=True)
        self._close()

    def _close(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
        fusing, self._fusing = self._fusing, None
        _cancel_unless_current(fusing)
        super()._close()

    def _forget(self) -> None:
        self._reports.clear()


class Continuous(FusionSession):
    """A snapshot every period of the request's rate from the reports received since the last one,
    through a Tracker; the last one final. A camera silent for longer than a period and the deadline
    grace is missing from the snapshots until it reports again."""

    def _init(self) -> None:
        mode = self.request.continuous
        self.period = 1.0 / mode.rate_hz
        #: How late after its period a report may still count (default one period).
        self.grace = self.options.deadline_s or self.period
        self.count = len(mode.report_times())
        self.tracker = Tracker(drop_after_s=self.options.track_drop_after_s)
        self._fresh: dict[str, DetectionReport] = {}  # the newest report per camera since the last snapshot
        self._heard: dict[str, float] = {}  # camera id -> when its last report came (loop time)
        self._t0 = 0.0
        self._task: asyncio.Task[None] | None = None
        self._done = asyncio.Event()  # every camera finished or failed
        #: Mobile cameras whose field of view is off the region now: their reports count no more
        #: until a pose brings it back over the region (they keep their forward, so they may).
        self.away: set[str] = set()

    def start(self, reply: detection_pb2.DetectionReply) -> None:
        super().start(reply)
        self._t0 = asyncio.get_running_loop().time()
        self._task = asyncio.get_running_loop().create_task(self._run())
        self._changed()

    def remaining_s(self) -> float:
        """Seconds from now until the cameras' last report is due (0 before the start or once it ended)."""
        if not self._started or self.ended:
            return 0.0
        due = self._t0 + (self.count - 1) * self.period
        return max(0.0, due - asyncio.get_running_loop().time())

    def add_camera(self, camera_id: str, key: bytes) -> None:
        """A camera asked after the dispatch (a mobile camera whose field of view entered the region),
        with the key made for it: its reports are taken from now on and merged into the snapshots;
        it counts as heard now, so it is not named missing before a period and the grace pass, and
        the session waits for its final report (or the grace) as for the others'."""
        if self.ended or camera_id in self.keys:
            return
        self.cameras = (*self.cameras, camera_id)
        self.keys[camera_id] = key
        self._heard[camera_id] = asyncio.get_running_loop().time()
        self._done.clear()

    def remove_camera(self, camera_id: str) -> bool:
        """A mobile camera whose field of view left the region: its reports count no more (they are
        taken and dropped: none is merged, none names it in a snapshot, nothing waits for it) until
        `rejoin`. True when it was one of this request's cameras."""
        if self.ended or camera_id not in self.keys or camera_id in self.away:
            return False
        self.cameras = tuple(c for c in self.cameras if c != camera_id)
        self.away.add(camera_id)
        self._fresh.pop(camera_id, None)
        self._heard.pop(camera_id, None)
        self._changed()
        return True

    def rejoin(self, camera_id: str) -> bool:
        """A camera that was away is over the region again: its reports count from now on, as when
        it joined. False when it was not away, or its forward has ended meanwhile."""
        if self.ended or camera_id not in self.away or camera_id in self._finished:
            return False
        self.away.discard(camera_id)
        self.cameras = (*self.cameras, camera_id)
        self._heard[camera_id] = asyncio.get_running_loop().time()
        self._done.clear()
        return True

    def report(self, report: DetectionReport, stream: ReportIntake) -> None:
        camera_id = report.camera_id
        if self.ended or camera_id in self._finished:
            return
        if camera_id in self.away:
            if report.final:
                self._finished.add(camera_id)  # its forward ended: it cannot come back to this one
                self._changed()
            return
        self._streams[camera_id] = stream
        self._failed.pop(camera_id, None)  # its forward timed out, but it reports after all
        self._fresh[camera_id] = report
        self._heard[camera_id] = asyncio.get_running_loop().time()
        if report.final:
            self._finished.add(camera_id)
            self._changed()

    def _changed(self) -> None:
        # (a camera that is away may come back: the request runs its course, snapshots going on)
        if self.away <= self._finished and all(c in self._finished or c in self._failed for c in self.cameras):
            self._done.set()

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        try:
            for k in range(self.count):
                last = k == self.count - 1
                if not last:
                    # Half a period after the cameras' k-th look: their reports are in by then.
                    delay = self._t0 + (k + 0.5) * self.period - loop.time()
                    if delay > 0 and not self._done.is_set():
                        await asyncio.sleep(delay)
                else:
                    # The last: every camera's final report, or the deadline grace after it was due.
                    due = self._t0 + k * self.period + max(self.grace, self.period / 2)
                    if not self._done.is_set():
                        with contextlib.suppress(TimeoutError):
                            await asyncio.wait_for(self._done.wait(), max(0.0, due - loop.time()))
                last = last or self._done.is_set()
                await self._snapshot(k, last)
                if last:
                    break
        except asyncio.CancelledError:
            raise
        except Exception:
            log.exception("fused request %s: making a snapshot failed", self.request_id)
            self._deliver(refusal(self.request_id, grpc.StatusCode.INTERNAL, FUSING_FAILED), True)
        self._task = None
        self._close()

    async def _snapshot(self, sequence: int, final: bool) -> None:
        now = asyncio.get_running_loop().time()
        wall = time.time()
        fresh, self._fresh = self._fresh, {}
        merged = [fresh[c] for c in self.cameras if c in fresh and not fresh[c].error]
        late: list[CameraError] = []
        for camera_id in self.cameras:
            if camera_id in self._failed:
                continue
            report = fresh.get(camera_id)
            if report is not None:
                if report.camera_error is not None:
                    late.append(report.camera_error)
                continue
            if camera_id in self._finished:
                continue
            silent = now - self._heard.get(camera_id, self._t0)
            if silent > self.period + self.grace or final:
                late.append(
                    CameraError(
                        "DEADLINE_EXCEEDED",
                        f"camera {camera_id}: no report for {silent:.1f} s (one is due every {self.period:g} s, "
                        f"at most {self.grace:g} s late)",
                        camera_id,
                    )
                )
        if self._inline(merged):
            tracks = self._track(merged, wall)
        else:
            tracks = await asyncio.to_thread(self._track, merged, wall)
        snapshot = Snapshot(
            time=wall,
            objects=tuple(tracks),
            camera_errors=errors_by_camera(self._missing(late)),
            camera_ids=tuple(sorted(r.camera_id for r in merged)),
            sequence=sequence,
            final=final,
            request_id=self.request_id,
        )
        reply = detection_pb2.DetectionReply(request_id=self.request_id)
        snapshot_to_pb(snapshot, self.outlines, into=reply.snapshot, compact=self.compact)  # in place: no copy
        self._deliver(reply, last=final)

    def _track(self, reports: Sequence[DetectionReport], at: float) -> list[WorldObject]:
        return self.tracker.update(self._fuse(reports), at)

    def _close(self) -> None:
        task, self._task = self._task, None
        _cancel_unless_current(task)
        super()._close()

    def _forget(self) -> None:
        self._fresh.clear()


class FusionSessions:
    """The fused requests in flight in one server, by the id they were forwarded with (unique in the
    server); the key a report presents proves the camera was dispatched the request."""

    def __init__(self, max_sessions: int = MAX_SESSIONS) -> None:
        self.max_sessions = max_sessions
        self._by_id: dict[str, list[FusionSession]] = {}
        self._ended: OrderedDict[FusionSession, None] = OrderedDict()
        #: The continuous ones in flight, in the order they came (a mobile camera may join them).
        self._continuous: dict[Continuous, None] = {}
        self.count = 0

    def check_room(self) -> None:
        if self.count >= self.max_sessions:
            raise ResourceExhausted(
                f"fusion: {self.count} fused requests already in flight on this server "
                f"(limit {self.max_sessions}); try again later"
            )

    def add(self, session: FusionSession) -> None:
        self._by_id.setdefault(session.forward_id, []).append(session)
        if isinstance(session, Continuous):
            self._continuous[session] = None
        self.count += 1
        metrics.FUSION_SESSIONS.set(self.count)

    def remove(self, session: FusionSession) -> None:
        sessions = self._by_id.get(session.forward_id)
        if sessions is None or session not in sessions:
            return
        sessions.remove(session)
        if not sessions:
            del self._by_id[session.forward_id]
        if isinstance(session, Continuous):
            self._continuous.pop(session, None)
        self._ended[session] = None
        while len(self._ended) > MAX_ENDED:
            self._ended.popitem(last=False)
        self.count -= 1
        metrics.FUSION_SESSIONS.set(self.count)

    def continuous(self) -> list[Continuous]:
        """The continuous fused requests in flight (a list: the caller may start or end some)."""
        return list(self._continuous)

    def leave(self, camera_id: str, fov: Polygon) -> list[Continuous]:
        """Take a mobile camera that moved off the continuous requests whose region its field of
        view `fov` (empty: it sees no floor) no longer meets with positive area; the requests it left."""
        left = []
        for session in self.continuous():
            if camera_id not in session.keys or camera_id in session.away:
                continue
            off = fov.is_empty or not shapely.relate_pattern(fov, session.request.region, "T********")
            if off and session.remove_camera(camera_id):
                left.append(session)
        return left

    def find(self, request_id: str, camera_id: str, key: bytes) -> FusionSession | None:
        """The session in flight forwarded as `request_id` whose key for `camera_id` is `key`."""
        for session in self._by_id.get(request_id, ()):
            if session.accepts(camera_id, key):
                return session
        return None

    def find_ended(self, request_id: str, camera_id: str, key: bytes) -> FusionSession | None:
        """A recently ended session whose key for `camera_id` is `key`: its report is late."""
        for session in reversed(self._ended):
            if session.forward_id == request_id and session.accepts(camera_id, key):
                return session
        return None

    def end_all(self, why: str) -> None:
        for sessions in list(self._by_id.values()):
            for session in list(sessions):
                session.end(why)


class ReportIntake:
    """One camera's report stream to the server. A report counts only for a fused request in
    flight that was dispatched to the camera it names, on a stream that presented that camera's key
    for that request (with this report or an earlier one); anything else is dropped, counted
    (drvs_fusion_reports_total{outcome="rejected"}) and answered with a cancel, as a robot answers
    a report it does not want."""

    def __init__(self, sessions: FusionSessions, peer: str) -> None:
        self._sessions = sessions
        self._peer = peer
        self._verified: OrderedDict[tuple[str, str], FusionSession] = OrderedDict()
        self._cancels: OrderedDict[str, None] = OrderedDict()
        self._wake = asyncio.Event()
        self._input_ended = False
        self._warned = False
        self.rejected = 0

    def receive(self, message: detection_pb2.DetectionReport) -> bool:
        """Whether the report counted (False: dropped, and the camera told to cancel)."""
        pair = (message.request_id, message.camera_id)
        session: FusionSession | None = None
        if message.report_key:
            key = message.report_key
            session = self._sessions.find(message.request_id, message.camera_id, key)
            session = session or self._sessions.find_ended(message.request_id, message.camera_id, key)
            if session is not None:
                self._verified[pair] = session
                while len(self._verified) > MAX_VERIFIED:
                    self._verified.popitem(last=False)
        else:
            session = self._verified.get(pair)
        if session is None or session.ended or message.camera_id not in session.keys:
            self._verified.pop(pair, None)
            self._reject(message, known=session is not None)
            return False
        # A mobile camera off the region now: its reports are dropped, but it is not told to stop.
        if isinstance(session, Continuous) and message.camera_id in session.away:
            if message.final:
                session.report(report_from_pb(message, session.request.filter_def), self)  # (its forward ended)
            return False
        metrics.FUSION_REPORTS_ACCEPTED.inc()
        if len(message.detections) > MAX_DETECTIONS_PER_REPORT:
            log.warning(
                "fused request %s: camera %s reported %d detections; fusing the first %d",
                session.request_id,
                message.camera_id,
                len(message.detections),
                MAX_DETECTIONS_PER_REPORT,
            )
            del message.detections[MAX_DETECTIONS_PER_REPORT:]
        session.report(report_from_pb(message, session.request.filter_def), self)
        return True

    def _reject(self, message: detection_pb2.DetectionReport, known: bool) -> None:
        if known:
            metrics.FUSION_REPORTS_LATE.inc()  # its request ended: a late report, not a forgery
        else:
            self.rejected += 1
            metrics.FUSION_REPORTS_REJECTED.inc()
            if not self._warned:  # once per stream: a hostile peer does not flood the log
                self._warned = True
                log.warning(
                    "report for request %s in camera %r's name from %s rejected: no fused request in flight "
                    "dispatched to that camera with the key it presented on this stream",
                    message.request_id[:40],
                    message.camera_id[:40],
                    self._peer,
                )
        self.cancel(message.request_id)

    def cancel(self, request_id: str) -> None:
        """Tell the camera to stop sending `request_id`'s reports."""
        self._cancels[request_id] = None
        while len(self._cancels) > MAX_CANCELS:
            self._cancels.popitem(last=False)
        self._wake.set()

    def input_ended(self) -> None:
        self._input_ended = True
        self._wake.set()

    async def next_control(self) -> detection_pb2.ReportControl | None:
        """The next ReportControl to write, or None once the camera closed its side."""
        while not self._cancels:
            if self._input_ended:
                return None
            self._wake.clear()
            await self._wake.wait()
        cancelled, self._cancels = list(self._cancels), OrderedDict()
        return detection_pb2.ReportControl(cancelled_request_ids=cancelled)

    def end(self) -> None:
        self._input_ended = True
        for session in set(self._verified.values()):
            session.stream_ended(self)
        self._verified.clear()


def _cancel_unless_current(task: asyncio.Task[Any] | None) -> None:
    """Cancel a session's task when it closes, unless the task is the one closing it (it is ending)."""
    if task is not None and task is not asyncio.current_task():
        task.cancel()

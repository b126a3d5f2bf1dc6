"""Subscription: the reports of one per-camera request (DrvsClient.subscribe, detect), as the
robot's listener hands them over; Subscribing, what subscribe returns."""

from __future__ import annotations

import asyncio
import collections
import logging
from collections.abc import AsyncIterator
from dataclasses import replace
from typing import TYPE_CHECKING

from drvs.core.model import CameraError, DetectionReport, DetectionRequest
from drvs.core.net import parse_address
from drvs.robot.handles import _Delivery, _Sending
from drvs.robot.limits import MAX_QUEUED_REPORTS
from drvs.robot.results import DetectionResult
from drvs.v1 import detection_pb2
from drvs.wire.convert import polygon_from_pb

if TYPE_CHECKING:
    from drvs.robot.connection import ClientConnection

log = logging.getLogger("drvs.robot")


class Subscription(_Delivery):
    """The reports of one request, as an async iterator that ends when every dispatched camera has
    sent its final report, or `timeout_s` seconds after the request's duration has passed.

    Use it as an async context manager (`async with drvs.subscribe(...) as sub:`): leaving the block
    closes it, and cameras still reporting for it are told to stop. `result` (a DetectionResult)
    gathers the reports read so far; `camera_ids` names the cameras the request went to.

    Unread reports never hold back anything else: the robot's listener hands each report over
    without waiting. A continuous request keeps the newest `max_queued` unread reports and drops
    the oldest beyond that, counting them in `dropped`; each camera's final report is always kept.
    A single-shot request gets one report per camera, its final one, and keeps them all: its queue
    is bounded by the number of cameras the server dispatched to (a second report from the same
    camera is dropped and counted).
    """

    def __init__(
        self,
        client: ClientConnection,
        request: DetectionRequest,
        timeout_s: float,
        max_queued: int = MAX_QUEUED_REPORTS,
    ) -> None:
        self._client = client
        self.request = request
        self.request_id = request.request_id
        self.camera_ids: tuple[str, ...] = ()
        # A deque and one waiter future, not an asyncio.Queue with wait_for: at 30 requests a
        # second per robot, a task per report was a visible share of the robot's CPU.
        self._pending: collections.deque[DetectionReport] = collections.deque()
        self._max_queued = max_queued
        self._wakeup: asyncio.Future[None] | None = None
        self._timer: asyncio.TimerHandle | None = None
        self._expired = False
        self._timeout_s = timeout_s
        self.closed = False
        self.result = DetectionResult(request.request_id, ())
        self._finals: set[str] = set()  # cameras whose final report arrived
        #: camera id -> when (loop time, seconds) its latest report arrived: a continuous request's
        #: camera that falls silent is a camera that stopped looking.
        self.last_report_at: dict[str, float] = {}

    @property
    def dropped(self) -> int:
        """Reports dropped unread: the oldest of a continuous request's beyond `max_queued`, and
        any second report of a camera that had already sent its final one."""
        return self.result.dropped

    def _dispatched(self, reply: detection_pb2.DetectionReply) -> None:
        self.camera_ids = tuple(reply.camera_ids)
        self.result.camera_ids = self.camera_ids
        self.result.skipped = {m.camera_id: CameraError(m.code, m.message, m.camera_id) for m in reply.missing_cameras}
        self.result.uncovered = [polygon_from_pb(p, "uncovered") for p in reply.uncovered]
        self.result.coverage_uncertain_s = reply.coverage_uncertain_s
        loop = asyncio.get_running_loop()
        self._timer = loop.call_later(self.request.continuous.duration_s + self._timeout_s, self._expire)

    def _expire(self) -> None:
        self._expired = True
        self._wake()

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

    def _deliver(self, report: DetectionReport) -> bool:
        """Queue a report without waiting (one camera's stream carries the reports of every request
        to this robot: waiting here would hold all of them back). False once the subscription is
        closed."""
        if self.closed:
            return False
        if report.camera_id in self._finals:
            self.result.dropped += 1  # the camera already finished: nothing more is due from it
            return True
        self.last_report_at[report.camera_id] = asyncio.get_running_loop().time()
        self.result.interrupted.discard(report.camera_id)
        if report.final:
            self._finals.add(report.camera_id)
        elif len(self._pending) >= self._max_queued:
            self._drop_oldest()
        self._pending.append(report)
        self._wake()
        return True

    def _drop_oldest(self) -> None:
        """Drop the oldest unread report that is not a final one (finals, one a camera, are kept)."""
        for i, old in enumerate(self._pending):
            if not old.final:
                del self._pending[i]
                self.result.dropped += 1
                return

    async def _next(self) -> DetectionReport | None:
        while not self._pending:
            if self._expired or self.closed:
                return None
            self._wakeup = asyncio.get_running_loop().create_future()
            await self._wakeup
        return self._pending.popleft()

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
        """Read every report to the end (see the class) and return the result."""
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
            self._client._forget(self.request_id)


class Subscribing(_Sending[Subscription]):
    """What DrvsClient.subscribe returns: `await` it for the Subscription, or use it as an async
    context manager (`async with drvs.subscribe(...) as sub:`), which closes the subscription on
    leaving the block. The request is sent when it is awaited or entered, not before."""


async def open_subscription(
    client: ClientConnection,
    request: DetectionRequest,
    message: detection_pb2.DetectionRequest,
    timeout_s: float,
    rpc_timeout_s: float,
    max_queued: int,
) -> Subscription:
    """Send a per-camera request (DrvsClient.subscribe): its Subscription, once the server replied."""
    if not request.callback_address:
        callback = await client.start_listener()
        parse_address(callback, "callback_address")
        request = replace(request, callback_address=callback)
        message.callback_address = callback
    sub = Subscription(client, request, timeout_s, max_queued)
    # Registered before sending: a camera may report before the server's reply arrives.
    client._register(sub)
    requests = client._requests
    assert requests is not None
    try:
        reply = await client._asking(f"request {message.request_id}", lambda: requests.request(message, rpc_timeout_s))
    except BaseException:
        sub.close()
        raise
    sub._dispatched(reply)
    return sub

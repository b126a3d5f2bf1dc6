"""Sending detection reports to robots' CallbackCoordinates listeners.

One long-lived stream per robot address carries the reports of every request to that robot, so
a report costs one message on an open stream, not a call. The robot answers on the same stream
with the requests it no longer wants.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import grpc
from grpc import aio

from drvs.core.errors import ResourceExhausted, Unavailable
from drvs.core.model import MAX_ID_LENGTH, DetectionReport
from drvs.v1 import detection_pb2, detection_pb2_grpc
from drvs.wire import metrics
from drvs.wire.convert import report_to_pb
from drvs.wire.security import Security

log = logging.getLogger(__name__)

#: Robot links kept at once; the least recently used idle one is closed past this.
MAX_LINKS = 64
#: A link unused this long is closed (the robot may have gone for good).
IDLE_CLOSE_S = 30.0
#: A write that cannot complete in this time (the robot stopped reading) breaks the link.
WRITE_TIMEOUT_S = 5.0
STALLED = f"robot did not take a report within {WRITE_TIMEOUT_S:g} s"
#: After a stall, requests reporting to that address are refused this long, and its reports are not
#: dialled again: a listener that stopped reading would otherwise hold every request sent its way
#: for WRITE_TIMEOUT_S, one stall after another.
STALL_COOLDOWN_S = 5.0
#: Stalled addresses remembered at once (the oldest is forgotten past this).
MAX_STALLED = 4096
#: Cancelled request ids remembered per link.
MAX_CANCELLED = 4096
#: Cameras whose report key a link remembers having presented (past this it starts over).
MAX_KEYED = 4096


class RobotLink:
    """The open report stream to one robot."""

    def __init__(
        self,
        address: str,
        security: Security,
        metadata: tuple[tuple[str, str], ...] = (),
        on_stall: Callable[[str], None] | None = None,
    ) -> None:
        self.address = address
        self._on_stall = on_stall
        self._channel = security.channel(address)
        self._call: Any = detection_pb2_grpc.CallbackCoordinatesStub(self._channel).ReportDetections(
            metadata=metadata or None
        )
        self._write_lock = asyncio.Lock()
        self._cancelled: OrderedDict[str, None] = OrderedDict()
        self._presented: dict[str, bytes] = {}  # camera id -> the report key presented on this link
        self._reader = asyncio.get_running_loop().create_task(self._read_controls())
        self.broken: str | None = None
        self.last_used = asyncio.get_running_loop().time()
        self.sending = 0

    def cancelled(self, request_id: str) -> bool:
        return request_id in self._cancelled

    async def _read_controls(self) -> None:
        try:
            async for control in self._call:
                for request_id in control.cancelled_request_ids:
                    if len(request_id) > MAX_ID_LENGTH:
                        continue  # no request of ours has such an id: nothing to hold
                    self._cancelled[request_id] = None
                    while len(self._cancelled) > MAX_CANCELLED:
                        self._cancelled.popitem(last=False)
            self.broken = "the robot closed the stream"
        except grpc.RpcError as exc:
            self.broken = _details(exc)
        except asyncio.CancelledError:
            self.broken = "closed"
            raise

    async def send(self, report: DetectionReport, outlines: bool = True, key: bytes = b"") -> bool:
        """Send one report; False when the robot no longer wants this request's reports. `key`: the
        camera's report key for this robot, presented with the camera's first report on this link."""
        if self.cancelled(report.request_id):
            return False
        if self.broken:
            raise Unavailable(f"callback {self.address}: {self.broken}")
        self.sending += 1
        loop = asyncio.get_running_loop()
        try:
            message = report_to_pb(report, outlines)
            if key:
                self._present_key(message, key)
            async with self._write_lock:
                # A timer, not asyncio.wait_for: that would cost a task for every report.
                stall = loop.call_later(WRITE_TIMEOUT_S, self._stalled)
                try:
                    await self._call.write(message)
                finally:
                    stall.cancel()
            metrics.REPORT_BYTES.inc(message.ByteSize())
        except asyncio.CancelledError:
            if self.broken != STALLED:
                raise  # our own task was cancelled
            raise Unavailable(f"callback {self.address}: {self.broken}") from None
        except (grpc.RpcError, asyncio.InvalidStateError) as exc:
            await asyncio.sleep(0)  # let the reader record why the stream ended
            self.broken = self.broken or _details(exc)
            raise Unavailable(f"callback {self.address}: {self.broken}") from None
        finally:
            self.sending -= 1
            self.last_used = loop.time()
        return True

    def _present_key(self, message: detection_pb2.DetectionReport, key: bytes) -> None:
        """The robot takes a camera's reports on the stream that presented its key: once per link,
        not on every report (a new link, after a break, presents it again)."""
        camera_id = message.camera_id
        if self._presented.get(camera_id) == key:
            return
        if len(self._presented) >= MAX_KEYED:
            self._presented.clear()
        self._presented[camera_id] = key
        message.report_key = key

    def _stalled(self) -> None:
        """The robot has not taken a report for WRITE_TIMEOUT_S: break the link (the pending write
        ends with CancelledError, which send turns into Unavailable)."""
        self.broken = STALLED
        self._call.cancel()
        if self._on_stall is not None:
            self._on_stall(self.address)

    async def close(self) -> None:
        with contextlib.suppress(Exception):
            if not self._call.done():
                await asyncio.wait_for(self._call.done_writing(), 1.0)
        self._call.cancel()
        self._reader.cancel()
        await asyncio.gather(self._reader, return_exceptions=True)
        await self._channel.close()


def _details(exc: BaseException) -> str:
    if isinstance(exc, aio.AioRpcError):
        return f"{exc.code().name} {exc.details()}"
    return str(exc) or type(exc).__name__


class CallbackSender:
    """Keeps one RobotLink per robot address: bounded in number, idle ones closed. `metadata`: sent
    on every stream (a camera's token, when it reports to its server rather than to robots)."""

    def __init__(
        self,
        max_links: int = MAX_LINKS,
        idle_close_s: float = IDLE_CLOSE_S,
        security: Security | None = None,
        metadata: tuple[tuple[str, str], ...] = (),
    ) -> None:
        self._security = security or Security()
        self._metadata = metadata
        self._max = max_links
        self._idle_close_s = idle_close_s
        self._links: OrderedDict[str, RobotLink] = OrderedDict()
        self._closing: set[asyncio.Task[None]] = set()
        self._stalled: OrderedDict[str, float] = OrderedDict()  # address -> refused until (loop time)

    def _stall(self, address: str) -> None:
        self._stalled[address] = asyncio.get_running_loop().time() + STALL_COOLDOWN_S
        self._stalled.move_to_end(address)
        while len(self._stalled) > MAX_STALLED:
            self._stalled.popitem(last=False)

    def stalled_for(self, address: str) -> float:
        """Seconds `address` is still refused for having stalled (0: it is not)."""
        until = self._stalled.get(address)
        if until is None:
            return 0.0
        left = until - asyncio.get_running_loop().time()
        if left <= 0:
            del self._stalled[address]
            return 0.0
        return left

    def check(self, address: str) -> None:
        """ResourceExhausted if a request reporting to `address` must be refused now: its listener
        stalled lately (see STALL_COOLDOWN_S). No retry hint: it is that robot's doing, not load."""
        if address and (left := self.stalled_for(address)):
            raise ResourceExhausted(
                f"callback_address {address}: it took no report within {WRITE_TIMEOUT_S:g} s; requests "
                f"reporting to it are refused for another {left:.1f} s"
            )

    def link(self, address: str) -> RobotLink:
        link = self._links.get(address)
        if link is None or link.broken:
            old = link
            link = RobotLink(address, self._security, self._metadata, self._stall)
            if old is not None:
                # What the robot cancelled stays cancelled: a robot that said stop and then closed
                # its stream is not dialled again for those requests.
                link._cancelled = old._cancelled
                self._close_later(old)
            self._links[address] = link
        self._links.move_to_end(address)
        self._evict()
        return link

    async def send(self, address: str, report: DetectionReport, outlines: bool = True, key: bytes = b"") -> bool:
        known = self._links.get(address)
        if known is not None and known.cancelled(report.request_id):
            return False  # not even a new connection for a request the robot stopped
        if self.stalled_for(address):
            raise Unavailable(f"callback {address}: {STALLED}; not dialled again yet")
        return await self.link(address).send(report, outlines, key)

    def _evict(self) -> None:
        now = asyncio.get_running_loop().time()
        for address, link in list(self._links.items()):
            too_many = len(self._links) > self._max
            idle = now - link.last_used > self._idle_close_s
            if (too_many or idle) and not link.sending:
                del self._links[address]
                self._close_later(link)

    def _close_later(self, link: RobotLink) -> None:
        task = asyncio.get_running_loop().create_task(link.close())
        self._closing.add(task)
        task.add_done_callback(self._closing.discard)

    async def close(self) -> None:
        links, self._links = list(self._links.values()), OrderedDict()
        await asyncio.gather(*(link.close() for link in links), *self._closing, return_exceptions=True)

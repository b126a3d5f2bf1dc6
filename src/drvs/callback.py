"""Sending detection reports into a robot's CallbackCoordinates listener."""

from __future__ import annotations

import asyncio
import logging
from collections import OrderedDict
from types import TracebackType
from typing import Any

import grpc
from grpc import aio

from drvs import _grpc
from drvs.convert import report_to_pb
from drvs.errors import Unavailable
from drvs.model import DetectionReport
from drvs.v1 import detection_pb2_grpc

log = logging.getLogger(__name__)

#: Channels to robots are kept for reuse; the least recently used idle ones are closed past this.
MAX_CACHED_CHANNELS = 64


class ReportStream:
    """One client-streaming call carrying the reports of one request to one robot."""

    def __init__(self, call: Any, address: str, release: Any) -> None:
        self._call = call
        self._address = address
        self._release = release
        self.sent = 0
        self.cancelled = False

    async def send(self, report: DetectionReport) -> bool:
        """Send one report; False when the robot no longer wants them (the stream ended)."""
        if self.cancelled or self._call.done():
            await self._check_finished()
            return False
        try:
            await self._call.write(report_to_pb(report))
        except asyncio.InvalidStateError:
            await self._check_finished()
            return False
        except grpc.RpcError as exc:
            raise _grpc.from_rpc_error(exc, f"callback {self._address}") from None
        self.sent += 1
        return True

    async def _check_finished(self) -> None:
        try:
            ack = await self._call
        except grpc.RpcError as exc:
            raise _grpc.from_rpc_error(exc, f"callback {self._address}") from None
        self.cancelled = True
        if not ack.cancelled:
            raise Unavailable(f"callback {self._address}: stream ended early")

    async def close(self) -> None:
        try:
            if not self._call.done():
                await self._call.done_writing()
            ack = await self._call
            self.cancelled = self.cancelled or ack.cancelled
        except grpc.RpcError as exc:
            raise _grpc.from_rpc_error(exc, f"callback {self._address}") from None
        finally:
            self._release()

    def abort(self) -> None:
        self._call.cancel()
        self._release()

    async def __aenter__(self) -> ReportStream:
        return self

    async def __aexit__(
        self, et: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if et is None:
            await self.close()
        else:
            self.abort()


class CallbackSender:
    """Reuses one channel per robot callback address; bounded, least recently used idle ones closed."""

    def __init__(self, max_channels: int = MAX_CACHED_CHANNELS) -> None:
        self._max = max_channels
        self._channels: OrderedDict[str, aio.Channel] = OrderedDict()
        self._in_use: dict[str, int] = {}

    def open(self, address: str, timeout_s: float) -> ReportStream:
        channel = self._channels.get(address)
        if channel is None:
            channel = _grpc.insecure_channel(address)
            self._channels[address] = channel
        self._channels.move_to_end(address)
        self._in_use[address] = self._in_use.get(address, 0) + 1
        stub = detection_pb2_grpc.CallbackCoordinatesStub(channel)
        call = stub.ReportDetections(timeout=timeout_s, wait_for_ready=False)
        released = False

        def release() -> None:
            nonlocal released
            if not released:
                released = True
                self._in_use[address] -= 1
                if self._in_use[address] == 0:
                    del self._in_use[address]
                self._evict()

        return ReportStream(call, address, release)

    async def send_one(self, address: str, report: DetectionReport, timeout_s: float) -> None:
        async with self.open(address, timeout_s) as stream:
            await stream.send(report)

    def _evict(self) -> None:
        while len(self._channels) > self._max:
            idle = next((a for a in self._channels if a not in self._in_use), None)
            if idle is None:
                return
            channel = self._channels.pop(idle)
            asyncio.get_running_loop().create_task(channel.close())

    async def close(self) -> None:
        channels, self._channels = list(self._channels.values()), OrderedDict()
        await asyncio.gather(*(c.close() for c in channels), return_exceptions=True)

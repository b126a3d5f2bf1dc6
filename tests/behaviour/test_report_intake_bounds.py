"""Report intake holds nothing a sender sizes: a report whose request or camera id is longer than
an id may be ends its stream with INVALID_ARGUMENT naming the id's length, on the server's
fused-report intake and on a robot's listener alike, and the receiver's memory stays bounded."""

from __future__ import annotations

import asyncio
import contextlib
from pathlib import Path

import grpc
from grpc import aio

from drvs.core.model import MAX_ID_LENGTH
from drvs.robot import DrvsClient
from drvs.tools.launch import start_server
from drvs.v1 import detection_pb2, detection_pb2_grpc

#: The ids of the issue's flood: 1 MB each.
HUGE = 1 << 20
REPORTS = 300


def _rss_bytes(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise AssertionError(f"no VmRSS for {pid}")


async def _refusal(address: str, field: str) -> tuple[str, str]:
    """One report stream with one report whose `field` is 1 MB, then done: the (code, details) it ends with."""
    async with aio.insecure_channel(address) as channel:
        call = detection_pb2_grpc.CallbackCoordinatesStub(channel).ReportDetections()
        report = detection_pb2.DetectionReport(request_id="r1", camera_id="cam1", sequence=0, final=True)
        setattr(report, field, "x" * HUGE)
        with contextlib.suppress(aio.AioRpcError, asyncio.InvalidStateError):
            await call.write(report)
            await call.done_writing()
            async for _control in call:
                pass  # a stream that reads (its status comes after what was written to it)
        return (await call.code()).name, await call.details()


async def _flood(address: str, pid: int | None = None) -> tuple[int, int]:
    """One report stream that writes REPORTS reports, each with a 1 MB id (request ids and camera
    ids in turn), and reads nothing: how many writes went through before the stream was ended, and
    `pid`'s memory growth (bytes) from before the first report to after the last write."""
    before = _rss_bytes(pid) if pid is not None else 0
    written = 0
    async with aio.insecure_channel(address) as channel:
        call = detection_pb2_grpc.CallbackCoordinatesStub(channel).ReportDetections()
        with contextlib.suppress(aio.AioRpcError, asyncio.InvalidStateError):
            for index in range(REPORTS):
                report = detection_pb2.DetectionReport(request_id=f"r{index}", camera_id="cam1", sequence=0)
                setattr(report, "request_id" if index % 2 == 0 else "camera_id", f"{index:08d}".ljust(HUGE, "x"))
                await call.write(report)
                written += 1
        grown = _rss_bytes(pid) - before if pid is not None else 0
        call.cancel()
        return written, grown


async def _check_refusals(address: str) -> None:
    for field in ("request_id", "camera_id"):
        code, details = await _refusal(address, field)
        assert code == grpc.StatusCode.INVALID_ARGUMENT.name, (code, details)
        assert details == f"{field}: {HUGE} characters, longer than {MAX_ID_LENGTH}; this report stream is closed"


async def test_the_server_refuses_reports_with_oversized_ids_and_holds_nothing() -> None:
    server, address = await start_server()
    try:
        await _check_refusals(address)
        written, grown = await _flood(address, server.pid)
        # Ended by the server, at once (a write or two may be on the wire by then), not read to the end.
        assert written < REPORTS // 10, written
        assert grown < 50 << 20, f"the server's memory grew {grown >> 20} MB on {REPORTS} reports with 1 MB ids"
    finally:
        await server.stop()


async def test_a_robots_listener_refuses_reports_with_oversized_ids() -> None:
    server, address = await start_server()
    try:
        async with DrvsClient(address, robot_id="r", listen="127.0.0.1:0") as robot:
            callback = await robot.start_listener()
            await _check_refusals(callback)
            written, _ = await _flood(callback)
            assert written < REPORTS // 10, written
            assert robot.reports_received == 0
    finally:
        await server.stop()

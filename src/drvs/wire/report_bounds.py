"""Bounds on what a report stream's sender can make its receiver (the server's fused-report intake,
a robot's listener) hold: ids no longer than any id the receiver hands out, and a stream whose
sender stops reading its controls (the cancels the receiver answers with) is dropped instead of
queueing them. `serve_report_stream` serves the server's fused-report intake so; a robot's
listener (robot/client.py) checks the same bounds."""

from __future__ import annotations

import asyncio
import logging
import sys
from collections.abc import AsyncIterator, Callable
from typing import Any, Protocol

import grpc
from grpc import aio

from drvs.core.model import MAX_ID_LENGTH
from drvs.v1 import detection_pb2

log = logging.getLogger("drvs.server")

#: How long a receiver waits for a report stream's sender to take one control message (a cancel)
#: before it drops the stream: a sender that writes reports but reads nothing would otherwise
#: make the receiver hold every cancel it owes.
CONTROL_WRITE_TIMEOUT_S = 5.0


def oversized_id(message: detection_pb2.DetectionReport) -> str:
    """Why a report is refused (INVALID_ARGUMENT), "" when it is not: a request or camera id longer
    than any id a request or a camera may have. Nothing the receiver holds is keyed by such an id,
    and an answer would echo it. (A message, not an exception: an exception's traceback would keep
    the report, and its megabytes, alive until the garbage collector finds the cycle.)"""
    for name, value in (("request_id", message.request_id), ("camera_id", message.camera_id)):
        if len(value) > MAX_ID_LENGTH:
            return f"{name}: {len(value)} characters, longer than {MAX_ID_LENGTH}; this report stream is closed"
    return ""


#: Why a stream whose sender does not read is dropped (RESOURCE_EXHAUSTED).
NOT_READING = (
    f"ReportDetections: the sender has not read this stream's controls for {CONTROL_WRITE_TIMEOUT_S:g} s; "
    "the stream is dropped"
)


async def write_control(context: aio.ServicerContext[Any, Any], control: detection_pb2.ReportControl) -> bool:
    """Write one control to a report stream's sender: False when it has not taken it within
    CONTROL_WRITE_TIMEOUT_S (it does not read; drop the stream with NOT_READING)."""
    try:
        if sys.version_info >= (3, 11):
            async with asyncio.timeout(CONTROL_WRITE_TIMEOUT_S):  # the write stays in this task, in order
                await context.write(control)
        else:
            await asyncio.wait_for(context.write(control), CONTROL_WRITE_TIMEOUT_S)
    except (TimeoutError, asyncio.TimeoutError):  # one class from 3.11 on
        return False
    return True


class Intake(Protocol):
    """What serve_report_stream hands a stream's reports to (server.fusion_session.ReportIntake)."""

    def receive(self, message: detection_pb2.DetectionReport) -> bool: ...
    def input_ended(self) -> None: ...
    async def next_control(self) -> detection_pb2.ReportControl | None: ...
    def end(self) -> None: ...


async def serve_report_stream(
    requests: AsyncIterator[detection_pb2.DetectionReport],
    context: aio.ServicerContext[Any, Any],
    intake: Intake,
    seen: Callable[[detection_pb2.DetectionReport], None] | None = None,
) -> None:
    """One camera's report stream to the server: each report, once its ids are checked, to `intake`
    and, when the intake counted it, to `seen` (the live view and recording); the intake's controls
    back, until the camera ends its side. A report with an oversized id ends the stream
    (INVALID_ARGUMENT), as does a camera that does not read its controls (RESOURCE_EXHAUSTED);
    neither leaves anything held."""

    async def read() -> str:
        try:
            async for message in requests:
                if refusal := oversized_id(message):
                    return refusal  # the stream ends: nothing holds the report
                if intake.receive(message) and seen is not None:  # seen (recorded) only once it passed
                    seen(message)
            return ""
        finally:
            intake.input_ended()

    reader = asyncio.get_running_loop().create_task(read())
    refusal = (grpc.StatusCode.OK, "")
    try:
        while (control := await intake.next_control()) is not None:
            if not await write_control(context, control):
                refusal = (grpc.StatusCode.RESOURCE_EXHAUSTED, NOT_READING)
                break
        else:
            [ended] = await asyncio.gather(reader, return_exceptions=True)
            if isinstance(ended, str) and ended:
                refusal = (grpc.StatusCode.INVALID_ARGUMENT, ended)
    finally:
        reader.cancel()
        await asyncio.gather(reader, return_exceptions=True)
        intake.end()
    if refusal[1]:
        log.warning("report stream from %s closed: %s", context.peer(), refusal[1])
        await context.abort(*refusal)

"""The robot's report listener: the CallbackCoordinates service cameras dial to stream the reports
of per-camera requests, and the record of which stream may carry which camera's reports.

It edits none of the client's state: it asks the client (a ReportSink) to take each report, and
tells it when a stream opens and ends."""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator
from typing import Any, Protocol

import grpc
from grpc import aio

from drvs.v1 import detection_pb2, detection_pb2_grpc
from drvs.wire.report_auth import key_matches
from drvs.wire.report_bounds import NOT_READING, oversized_id, write_control

log = logging.getLogger("drvs.robot")


class ReportSink(Protocol):
    """What the listener asks of the client (DrvsClient implements it)."""

    @property
    def _closing(self) -> bool: ...

    def _take_report(self, message: detection_pb2.DetectionReport, stream: object) -> bool | None: ...

    def _stream_opened(self, task: asyncio.Task[Any] | None) -> None: ...

    def _stream_ended(self, stream: object, task: asyncio.Task[Any] | None) -> None: ...

    def _closing_control(self) -> detection_pb2.ReportControl | None: ...


class ReportKeys:
    """Which report streams may carry which camera's reports: those that presented the camera's
    key (drvs.wire.report_auth), derived by the server from this robot's `secret`: its own stream, and
    the server's when it answered for the camera."""

    def __init__(self, secret: bytes) -> None:
        self.secret = secret
        # camera id -> the report streams that presented its key
        self._camera_streams: dict[str, set[object]] = {}

    def accepts(self, message: detection_pb2.DetectionReport, stream: object) -> bool:
        """A camera's reports count only on a stream that presented its key."""
        camera_id = message.camera_id
        if message.report_key:
            if not key_matches(self.secret, camera_id, message.report_key):
                return False
            self._camera_streams.setdefault(camera_id, set()).add(stream)
            return True
        return stream in self._camera_streams.get(camera_id, ())

    def forget(self, stream: object) -> set[str]:
        """`stream` ended: the cameras that now have no stream their reports count on."""
        cameras = set()
        for camera_id, streams in list(self._camera_streams.items()):
            if stream in streams:
                streams.discard(stream)
                if not streams:
                    del self._camera_streams[camera_id]
                    cameras.add(camera_id)
        return cameras


class _ReportStream:
    """One camera's report stream as the client sees it: which reports count, and where they go."""

    def __init__(self, client: ReportSink, peer: str) -> None:
        self._client = client
        self._peer = peer
        self._warned = False
        self._task = asyncio.current_task()
        client._stream_opened(self._task)

    def receive(self, message: detection_pb2.DetectionReport) -> detection_pb2.ReportControl | None:
        """Hand one report to its subscription; a control message to send back when the camera
        should stop sending this request's reports (unknown, closed, or not proven its)."""
        taken = self._client._take_report(message, self)
        if taken is None and not self._warned:  # once per stream: a hostile peer does not flood the log
            self._warned = True
            log.warning(
                "report for request %s in camera %r's name from %s rejected: no valid report key "
                "for this stream (not a camera the server dispatched to, or not its stream)",
                message.request_id,
                message.camera_id[:40],
                self._peer,
            )
        if not taken:
            return detection_pb2.ReportControl(cancelled_request_ids=[message.request_id])
        return None

    @property
    def closing(self) -> bool:
        """The robot is closing (its stream tasks are cancelled on purpose)."""
        return self._client._closing

    def closing_control(self) -> detection_pb2.ReportControl | None:
        """What to tell the camera when the robot closes: stop the requests still open."""
        return self._client._closing_control()

    def end(self) -> None:
        """The stream ended: the client forgets it (see DrvsClient._stream_ended)."""
        self._client._stream_ended(self, self._task)


class Listener(detection_pb2_grpc.CallbackCoordinatesServicer):
    """The robot's CallbackCoordinates service: reads each camera's stream and delegates to the client."""

    def __init__(self, client: ReportSink) -> None:
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
        stream = _ReportStream(self._client, context.peer())
        refusal = (grpc.StatusCode.OK, "")
        try:
            async for message in request_iterator:
                if why := oversized_id(message):  # before anything holds or echoes it
                    refusal = (grpc.StatusCode.INVALID_ARGUMENT, why)
                    break
                control = stream.receive(message)
                if control is not None and not await write_control(context, control):
                    refusal = (grpc.StatusCode.RESOURCE_EXHAUSTED, NOT_READING)
                    break
        except asyncio.CancelledError:
            if not stream.closing:
                raise
            control = stream.closing_control()
            if control is not None:
                with contextlib.suppress(Exception):
                    await asyncio.wait_for(context.write(control), 0.5)
        finally:
            stream.end()
        if refusal[1]:
            await context.abort(*refusal)

"""Fake cameras: DetectObjectBoundary servers that accept what they are sent at once and do no
detection. The benchmarks' ack servers and bare cameras and the tests' stand-in cameras are all one
base, AckingCamera; each fake overrides the hook it needs and keeps what it records."""

from __future__ import annotations

from collections.abc import AsyncIterator, Sequence
from typing import Any

from grpc import aio

from drvs.v1 import detection_pb2, detection_pb2_grpc

_Context = aio.ServicerContext[Any, Any]
_Requests = AsyncIterator[detection_pb2.DetectionRequest]
_Batches = AsyncIterator[detection_pb2.DetectionRequests]
_Reply = detection_pb2.DetectionReply
_Replies = detection_pb2.DetectionReplies


class AckingCamera(detection_pb2_grpc.DetectObjectBoundaryServicer):
    """Accepts every request at once on DetectBatches, DetectStream and DetectObjects, with a reply
    naming `camera_id` (no camera when it is empty). No validation, no detection, no reports.

    Hooks for a fake that records or waits: `batch` sees each DetectBatches batch as it arrives,
    before any of its requests is accepted; `accept` makes each request's reply; `replied` runs after
    a stream's reply to the request was sent."""

    def __init__(self, camera_id: str = "") -> None:
        self.camera_id = camera_id

    async def batch(self, requests: Sequence[detection_pb2.DetectionRequest]) -> None:
        """Called with each batch's requests as the batch arrives."""

    async def accept(self, request: detection_pb2.DetectionRequest) -> detection_pb2.DetectionReply:
        """The reply to one request: accepted, by this camera."""
        return detection_pb2.DetectionReply(
            request_id=request.request_id, camera_ids=[self.camera_id] if self.camera_id else []
        )

    async def replied(self, request: detection_pb2.DetectionRequest) -> None:
        """Called after the reply to `request` was sent on a stream."""

    async def DetectObjects(self, request: detection_pb2.DetectionRequest, context: _Context) -> _Reply:
        return await self.accept(request)

    async def DetectStream(self, request_iterator: _Requests, context: _Context) -> AsyncIterator[_Reply]:
        async for request in request_iterator:
            yield await self.accept(request)
            await self.replied(request)

    async def DetectBatches(self, request_iterator: _Batches, context: _Context) -> AsyncIterator[_Replies]:
        async for batch in request_iterator:
            await self.batch(batch.requests)
            yield detection_pb2.DetectionReplies(replies=[await self.accept(request) for request in batch.requests])
            for request in batch.requests:
                await self.replied(request)


async def serve_camera(
    camera: detection_pb2_grpc.DetectObjectBoundaryServicer,
    listen: str = "127.0.0.1:0",
    options: Sequence[tuple[str, Any]] = (),
) -> tuple[aio.Server, str]:
    """A started grpc.aio server with `camera` on `listen` (port 0: any free port), and its address."""
    server = aio.server(options=list(options))
    detection_pb2_grpc.add_DetectObjectBoundaryServicer_to_server(camera, server)
    port = server.add_insecure_port(listen)
    await server.start()
    return server, f"{listen.rsplit(':', 1)[0]}:{port}"

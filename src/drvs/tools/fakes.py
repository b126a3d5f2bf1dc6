"""Fake cameras: DetectObjectBoundary servers that accept what they are sent at once and do no
detection. The benchmarks' ack servers and bare cameras (the floors DRVS is measured against) and the
tests' stand-in cameras (tests/fakes) are all one base, AckingCamera; each fake overrides the hook it
needs and keeps what it records."""

from __future__ import annotations

from collections.abc import AsyncIterator, Sequence
from typing import Any

from grpc import aio

from drvs.core.geometry import homography_from_pose
from drvs.v1 import detection_pb2, detection_pb2_grpc, registry_pb2

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


def register_message(
    camera_id: str = "cam1", x: float = 0.0, address: str = "127.0.0.1:9"
) -> registry_pb2.RegisterRequest:
    """A fake camera's registration: 3 m up at (x, 0), looking along +y, pitched 40° down, 60° wide,
    640×480, seeing 6 m of floor (about x-3.8..x+3.8, y 1.5..6) with the hsv detector."""
    h = homography_from_pose((x, 0.0, 3.0), 90.0, 40.0, 60.0, (640, 480))
    return registry_pb2.RegisterRequest(
        camera_id=camera_id,
        address=address,
        homography=registry_pb2.Homography(m=h.to_list()),
        image_width=640,
        image_height=480,
        max_range_m=6.0,
        detector_kinds=["hsv"],
    )

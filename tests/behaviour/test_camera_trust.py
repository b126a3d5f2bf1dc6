"""Whom a camera node trusts, with a real drvs-server process and a real camera node: the forward
secret it hands its server opens no frames (only its token does), and a fused request's reports,
which carry the camera's token, go only to a server the camera knows, not to whatever address a
forward names."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from typing import Any

import grpc
import numpy as np
import pytest
from grpc import aio

from drvs.camera import CameraNode, PushSource
from drvs.core.geometry import homography_from_pose
from drvs.tools.launch import start_server
from drvs.v1 import detection_pb2, detection_pb2_grpc, geometry_pb2, stream_pb2, stream_pb2_grpc
from drvs.wire import _grpc
from drvs.wire.security import Security
from tests.helpers import YELLOW, wait_until

TOKEN = "camera-token-0123456789abcdef"
SIZE = (320, 240)


def bearer(token: str) -> tuple[tuple[str, str], ...]:
    return (("authorization", f"Bearer {token}"),)


class Listener(detection_pb2_grpc.CallbackCoordinatesServicer):
    """Somewhere reports can go: remembers every report and the credential that came with it."""

    def __init__(self) -> None:
        self.reports: asyncio.Queue[tuple[str, str]] = asyncio.Queue()  # (request id, authorization)

    async def ReportDetections(self, request_iterator: AsyncIterator[Any], context: Any) -> None:
        authorization = dict(context.invocation_metadata() or ()).get("authorization", "")
        async for report in request_iterator:
            self.reports.put_nowait((report.request_id, authorization))


async def _listening(host: str) -> tuple[aio.Server, Listener, str]:
    server = _grpc.new_server()
    listener = Listener()
    detection_pb2_grpc.add_CallbackCoordinatesServicer_to_server(listener, server)
    port = server.add_insecure_port(f"{host}:0")
    await server.start()
    return server, listener, f"{host}:{port}"


async def _camera(server: str, **options: Any) -> CameraNode:
    source = PushSource("a still frame")
    source.push(np.zeros((SIZE[1], SIZE[0], 3), dtype=np.uint8))
    h = homography_from_pose((0.0, 0.0, 3.0), 90.0, 40.0, 60.0, SIZE)
    node = CameraNode("cam1", source, h, server, security=Security(token=TOKEN), **options)
    await node.start()
    return node


def _fused_forward(request_id: str, report_address: str) -> detection_pb2.DetectionRequests:
    """A fused request as a server forwards it, its reports to go to `report_address`."""
    box = geometry_pb2.Box(x_lower=-5, y_lower=0, x_upper=5, y_upper=10)
    return detection_pb2.DetectionRequests(
        requests=[
            detection_pb2.DetectionRequest(
                request_id=request_id,
                robot_id="r",
                filter_def=YELLOW,
                region=geometry_pb2.Region(box=box),
                report_to_server=True,
                report_address=report_address,
            )
        ]
    )


async def _forward(node: CameraNode, message: detection_pb2.DetectionRequests) -> detection_pb2.DetectionReply:
    """Send one batch to the camera with the secret it gave its server; its one reply."""
    async with aio.insecure_channel(f"127.0.0.1:{node.port}") as channel:
        call = detection_pb2_grpc.DetectObjectBoundaryStub(channel).DetectBatches(metadata=bearer(node.forward_secret))
        await call.write(message)
        replies = await call.read()
        call.cancel()
    assert isinstance(replies, detection_pb2.DetectionReplies)
    (reply,) = replies.replies
    return reply


async def test_the_forward_secret_opens_no_frames_the_token_does() -> None:
    server, address = await start_server()
    try:
        node = await _camera(address, serve_frames=True)
        try:
            await asyncio.wait_for(node.registered.wait(), 10)
            async with aio.insecure_channel(f"127.0.0.1:{node.port}") as channel:
                frames = stream_pb2_grpc.FrameStreamStub(channel)
                ask = stream_pb2.StreamFramesRequest(encoding=stream_pb2.FRAME_ENCODING_JPEG)
                with pytest.raises(aio.AioRpcError) as err:
                    await frames.StreamFrames(ask, metadata=bearer(node.forward_secret)).read()
                assert err.value.code() == grpc.StatusCode.UNAUTHENTICATED
                assert "frame streams need this camera's token" in (err.value.details() or "")
                call = frames.StreamFrames(ask, metadata=bearer(TOKEN))
                frame = await asyncio.wait_for(call.read(), 10)
                assert isinstance(frame, stream_pb2.VideoFrame) and frame.camera_id == "cam1" and frame.data
                call.cancel()
        finally:
            await node.stop()
    finally:
        await server.stop()


async def test_reports_go_only_to_a_server_the_camera_knows(caplog: pytest.LogCaptureFixture) -> None:
    """A forward naming a third party's report address is refused (PERMISSION_DENIED, logged): no
    report and no token reach it. A name that does not resolve to the servers' addresses is
    refused once resolved, before anything is sent. Another port on the server's host (where a
    `--workers` worker takes its reports) gets them, with the token."""
    server, address = await start_server()
    stranger, stranger_reports, stranger_address = await _listening("127.0.0.2")
    worker, worker_reports, worker_address = await _listening("127.0.0.1")
    try:
        node = await _camera(address)
        try:
            await asyncio.wait_for(node.registered.wait(), 10)
            reply = await _forward(node, _fused_forward("stolen", stranger_address))
            assert reply.error.code == "PERMISSION_DENIED", reply
            assert reply.error.message.startswith(f"report_address: {stranger_address!r} is not one of this camera's")
            reply = await _forward(node, _fused_forward("unresolved", "elsewhere.invalid:50051"))
            assert not reply.HasField("error"), reply  # a name: decided once resolved, off the event loop
            refused = "reports were to go to elsewhere.invalid:50051"
            await wait_until(lambda: refused in caplog.text, "the unresolved name refused", 10)
            reply = await _forward(node, _fused_forward("worker", worker_address))
            assert not reply.HasField("error"), reply
            request_id, authorization = await asyncio.wait_for(worker_reports.reports.get(), 10)
            assert (request_id, authorization) == ("worker", f"Bearer {TOKEN}")
            # The refusal was synchronous: nothing was started for the third party, so nothing can reach it later.
            assert stranger_reports.reports.empty()
        finally:
            await node.stop()
    finally:
        await stranger.stop(None)
        await worker.stop(None)
        await server.stop()

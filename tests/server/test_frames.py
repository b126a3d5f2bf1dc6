"""Floors and buildings: a camera registers in a named frame ("building-a/floor-2", default "map"),
a request names its frame, and routing stays within it, so two floors whose plans overlap in x, y
never answer for each other. A real drvs-server process, real sockets."""

from __future__ import annotations

import json
from collections.abc import AsyncIterator

import grpc
import pytest
import pytest_asyncio
from grpc import aio
from shapely.geometry import box

from drvs import DrvsClient
from drvs.tools.launch import ManagedProcess, start_server
from drvs.v1 import detection_pb2_grpc, registry_pb2, registry_pb2_grpc
from tests.helpers import detect_message, register_message

FLOOR_1 = "building-a/floor-1"
FLOOR_2 = "building-a/floor-2"


@pytest_asyncio.fixture
async def server() -> AsyncIterator[str]:
    """A server with three cameras over the same patch of floor plan: one on each floor of
    building A and one in the default frame (the map)."""
    proc: ManagedProcess
    proc, address = await start_server()
    try:
        async with aio.insecure_channel(address) as channel:
            stub = registry_pb2_grpc.RegisterVisionServiceStub(channel)
            for camera_id, frame in (("f1-cam", FLOOR_1), ("f2-cam", FLOOR_2), ("map-cam", "")):
                message = register_message(camera_id)
                message.frame = frame
                await stub.Register(message)
        yield address
    finally:
        await proc.stop()


async def test_a_request_is_routed_within_its_frame_only(server: str) -> None:
    async with aio.insecure_channel(server) as channel:
        stub = detection_pb2_grpc.DetectObjectBoundaryStub(channel)
        for frame, expected in ((FLOOR_1, ["f1-cam"]), (FLOOR_2, ["f2-cam"]), ("", ["map-cam"]), ("map", ["map-cam"])):
            reply = await stub.DetectObjects(detect_message(request_id=f"r-{len(frame)}", frame=frame))
            # (Asked, or named missing: a fake camera's address answers nothing, so after its first
            # forward fails the server skips it, and says so.)
            routed = list(reply.camera_ids) + [m.camera_id for m in reply.missing_cameras]
            assert routed == expected, frame
        # A frame nobody registered in: nobody is asked (the region is unseen there).
        reply = await stub.DetectObjects(detect_message(request_id="r-b", frame="building-b/floor-1"))
        assert list(reply.camera_ids) == [] and list(reply.missing_cameras) == []
        with pytest.raises(aio.AioRpcError) as err:
            await stub.DetectObjects(detect_message(request_id="r-bad", frame="floor 1"))
        assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert (err.value.details() or "").startswith("frame: 'floor 1' is not ids joined by '/'")


async def test_listing_cameras_by_frame(server: str) -> None:
    async with aio.insecure_channel(server) as channel:
        stub = registry_pb2_grpc.RegisterVisionServiceStub(channel)
        every = await stub.ListCameras(registry_pb2.ListCamerasRequest())
        assert {(c.camera_id, c.frame) for c in every.cameras} == {
            ("f1-cam", FLOOR_1),
            ("f2-cam", FLOOR_2),
            ("map-cam", "map"),
        }
        floor = await stub.ListCameras(registry_pb2.ListCamerasRequest(frame=FLOOR_2))
        assert [c.camera_id for c in floor.cameras] == ["f2-cam"]
    # The robot client: its frame for its requests and its listing; "" lists every frame.
    async with DrvsClient.connect(server, robot_id="lift-bot", frame=FLOOR_1) as drvs:
        assert [c.camera_id for c in await drvs.cameras(box(-1, 0, 1, 5))] == ["f1-cam"]
        assert {c.frame for c in await drvs.cameras(frame="")} == {FLOOR_1, FLOOR_2, "map"}
        drvs.frame = FLOOR_2  # it took the lift
        assert [c.camera_id for c in await drvs.cameras()] == ["f2-cam"]


async def test_registering_in_a_malformed_frame_is_refused(server: str) -> None:
    async with aio.insecure_channel(server) as channel:
        message = register_message("bad-cam")
        message.frame = "a//b"
        with pytest.raises(aio.AioRpcError) as err:
            await registry_pb2_grpc.RegisterVisionServiceStub(channel).Register(message)
        assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert (err.value.details() or "").startswith("frame: 'a//b' is not ids joined by '/'")


async def test_drvs_robot_cameras_shows_and_filters_by_frame(server: str) -> None:
    proc = await ManagedProcess.entry_point(
        "robot", "drvs-robot", "cameras", "--server", server, "--json", "--frame", FLOOR_1
    ).start()
    assert await proc.wait(timeout=30) == 0, proc.output()
    lines = [json.loads(line) for line in proc.lines if line.startswith("{")]
    assert [(c["camera_id"], c["frame"]) for c in lines] == [("f1-cam", FLOOR_1)]

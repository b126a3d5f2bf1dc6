"""A camera's requests, shared fairly: a caller whose listener never reads its reports cannot hold
the camera's every request slot and starve the other robots (real server, camera and listeners).

Without shares, a few hundred single shots reporting to a listener that never reads fill the
camera's MAX_ACTIVE_REQUESTS slots (each waits up to the report write timeout), and every other
robot is answered `busy`; the server, told its camera is full, then sheds everyone's requests."""

from __future__ import annotations

import asyncio
import contextlib
import re
from collections.abc import AsyncIterator
from typing import Any

import pytest
from grpc import aio

from drvs.robot import DrvsClient
from drvs.sim.scene import RecordedCamera
from drvs.tools.launch import start_server
from drvs.v1 import detection_pb2, detection_pb2_grpc, geometry_pb2
from tests.fakes import start_recorded_camera
from tests.helpers import CAM1_REGION, YELLOW, serving


class _NeverReads(detection_pb2_grpc.CallbackCoordinatesServicer):
    """A robot's callback listener that accepts report streams and never reads them: once HTTP/2's
    flow-control windows are full, every report written to it waits for the write timeout."""

    def __init__(self) -> None:
        self.stop = asyncio.Event()

    async def ReportDetections(
        self,
        request_iterator: AsyncIterator[detection_pb2.DetectionReport],
        context: aio.ServicerContext[Any, Any],
    ) -> None:
        await self.stop.wait()


@contextlib.asynccontextmanager
async def silent_listener() -> AsyncIterator[str]:
    """A real listener that never reads (see _NeverReads): its address."""
    listener = _NeverReads()
    try:
        async with serving(listener, detection_pb2_grpc.add_CallbackCoordinatesServicer_to_server) as address:
            yield address
    finally:
        listener.stop.set()


def _request(i: int, callback: str) -> detection_pb2.DetectionRequest:
    x0, y0, x1, y1 = CAM1_REGION
    corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    region = geometry_pb2.Region(
        polygon=geometry_pb2.Polygon(points=[geometry_pb2.Point2(x=x, y=y) for x, y in corners])
    )
    return detection_pb2.DetectionRequest(
        request_id=f"stalled{i}", robot_id="abuser", filter_def=YELLOW, region=region, callback_address=callback
    )


@pytest.mark.slow
async def test_a_listener_that_never_reads_holds_only_its_share_of_a_camera(
    recorded: dict[str, RecordedCamera],
) -> None:
    """An abuser on its own connection sends more single shots than the camera has slots, all
    reporting to a listener that never reads. It is refused past its share, by name; then, once its
    listener has stalled, at once. A robot asking meanwhile is answered every time, by the camera."""
    # The server's own limits out of the way: the camera's shares are what is tested. Its door too:
    # the abuser's flood makes the link's queue stand, and a robot the door has not yet measured is
    # admitted only the link's share (96 % once made the robot's detect below fail).
    server, address = await start_server(
        "--rate-limit", "100000", "--max-forward-bytes", "1000000000", "--admission-target", "0"
    )
    camera = await start_recorded_camera("cam1", recorded["cam1"], address)
    try:
        async with silent_listener() as stalled, aio.insecure_channel(address) as channel:
            call = detection_pb2_grpc.DetectObjectBoundaryStub(channel).DetectStream()
            sent = 0

            async def ask_until(pattern: str) -> str:
                """The abuser's requests, one after another, until the server logs a camera's refusal
                matching `pattern` (the server logs why a camera did not accept a request)."""
                nonlocal sent
                regex = re.compile(pattern)
                while sent < 50_000:
                    mark = len(server.lines)
                    await call.write(_request(sent, stalled))
                    sent += 1
                    reply = await call.read()
                    if reply.HasField("error"):  # the server's door: its link to the camera is full for now
                        assert reply.error.code == "RESOURCE_EXHAUSTED", reply.error
                        await asyncio.sleep(reply.error.retry_after_s)
                    for line in server.lines[mark:]:
                        if found := regex.search(line):
                            return found.group(0)
                raise AssertionError(f"no camera refusal matching {pattern!r} after {sent} requests")

            # Until the camera refuses one: without shares, for having no room left at all.
            refusal = await ask_until(
                r"requests active here \(its share: \d+\)|reports pending here|requests active; try later"
            )
            assert "its share" in refusal or "pending" in refusal, refusal
            async with DrvsClient(address, robot_id="robot", listen="127.0.0.1:0") as robot:
                for _ in range(5):
                    result = await robot.detect(YELLOW, CAM1_REGION)
                    assert result.complete and not result.missing_cameras, result
            # Once its listener has stalled (the report write timeout), it is refused at once.
            await ask_until(r"it took no report within")
            async with DrvsClient(address, robot_id="robot", listen="127.0.0.1:0") as robot:
                result = await robot.detect(YELLOW, CAM1_REGION)
                assert result.complete and not result.missing_cameras, result
            call.cancel()
    finally:
        await camera.stop()
        await server.stop()


async def test_shares_shrink_as_holders_arrive_and_always_leave_room() -> None:
    """The share is the camera's slots over one more than the holders present (at least MIN_SHARE),
    so a newcomer finds room; continuous requests keep their own cap; done jobs give back."""
    from drvs.camera.shares import MIN_SHARE, Shares
    from drvs.core.errors import ResourceExhausted

    shares = Shares("cam", max_continuous=1, max_active=64)
    never = asyncio.get_running_loop().create_future()
    jobs = []

    def hold(robot: str, callback: str, continuous: bool = False) -> None:
        shares.check(robot, callback, continuous)
        job = asyncio.ensure_future(never)
        jobs.append(job)
        shares.hold(job, robot, callback, continuous)

    for _ in range(32):  # alone: 64 // 2
        hold("a", "a:1")
    with pytest.raises(ResourceExhausted, match=r"cam: a already has 32 requests active here \(its share: 32\)"):
        hold("a", "a:1")
    for _ in range(21):  # two holders: 64 // 3
        hold("b", "b:1")
    with pytest.raises(ResourceExhausted, match=r"b already has 21 requests active here \(its share: 21\)"):
        hold("b", "b:1")
    # The share never falls below MIN_SHARE, however many hold some.
    for k in range(5):
        hold(f"x{k}", f"x{k}:1")
    assert shares._robots.share(64) == MIN_SHARE
    # One robot's requests to another's callback count against that callback's share too.
    with pytest.raises(ResourceExhausted, match=r"callback_address a:1 already has 32 requests' reports pending"):
        hold("c", "a:1")
    hold("c", "c:1", continuous=True)
    with pytest.raises(ResourceExhausted, match=r"continuous: 1 continuous requests already running for c"):
        hold("c", "c:1", continuous=True)
    assert shares.active == 32 + 21 + 5 + 1
    never.cancel()
    await asyncio.gather(*jobs, return_exceptions=True)
    assert shares.active == 0 and shares.continuous() == {}
    hold("a", "a:1")

"""Cheap exhaustion, closed (issue 14): bounded regions and caches, bounded amplification, lazy
continuous schedules, per-robot caps on server and camera with their slots released, a camera that
stops reading cut off, server-wide connection limits, metrics on loopback, monotonic frame age.
Real server and camera processes wherever the behaviour is theirs."""

from __future__ import annotations

import asyncio
import math
import re
import sys
import time
import tracemalloc
from pathlib import Path

import grpc
import numpy as np
import pytest
from drvs_bench.amplification import measure
from grpc import aio

from drvs.camera.node import CameraNode
from drvs.core.errors import DrvsError, InvalidArgument, ResourceExhausted, Unavailable
from drvs.core.geometry import MAX_REGION_VERTICES, homography_from_pose, polygon_region
from drvs.core.model import ContinuousMode
from drvs.detectors import Frame
from drvs.robot import DrvsClient, RetryPolicy
from drvs.robot.client import Subscription
from drvs.server.policy import RequestLimits
from drvs.sim.scene import RecordedCamera
from drvs.tools.launch import ManagedProcess, start_server
from drvs.v1 import detection_pb2, detection_pb2_grpc, geometry_pb2, registry_pb2, registry_pb2_grpc
from drvs.wire import _grpc, convert
from drvs.wire.convert import MAX_REGION_BYTES, RegionCache, region_to_pb
from tests.fakes import server_process, start_recorded_camera
from tests.helpers import CAM1_REGION, YELLOW

ROLES = Path(__file__).parents[1] / "fakes" / "fault_roles.py"


def rss_bytes(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise AssertionError(f"no VmRSS for {pid}")


def circle(cx: float, cy: float, r: float, n: int) -> list[tuple[float, float]]:
    return [(cx + r * math.cos(2 * math.pi * i / n), cy + r * math.sin(2 * math.pi * i / n)) for i in range(n)]


def polygon_pb(points: list[tuple[float, float]]) -> geometry_pb2.Region:
    return geometry_pb2.Region(polygon=geometry_pb2.Polygon(points=[geometry_pb2.Point2(x=x, y=y) for x, y in points]))


def request(request_id: str, region: geometry_pb2.Region | None) -> detection_pb2.DetectionRequest:
    msg = detection_pb2.DetectionRequest(
        request_id=request_id, robot_id="r", filter_def=YELLOW, callback_address="127.0.0.1:9"
    )
    if region is not None:
        msg.region.CopyFrom(region)
    return msg


async def stream_replies(
    address: str, messages: list[detection_pb2.DetectionRequest]
) -> list[detection_pb2.DetectionReply]:
    """Send `messages` on one DetectStream, exactly as given (nothing elided by us); their replies."""
    async with aio.insecure_channel(address) as channel:
        call = detection_pb2_grpc.DetectObjectBoundaryStub(channel).DetectStream()
        replies = []
        for message in messages:
            await call.write(message)
            replies.append(await call.read())
        await call.done_writing()
        return replies


# --- regions -----------------------------------------------------------------------------------


async def test_regions_are_capped_in_points_and_bytes_and_a_refused_one_is_not_kept() -> None:
    server, address = await start_server()
    try:
        too_many = polygon_pb(circle(0, 4, 2, MAX_REGION_VERTICES + 1))
        padded = geometry_pb2.Region(box=geometry_pb2.Box(x_lower=0, y_lower=0, x_upper=1, y_upper=1))
        # Unknown fields ride along in a message; 30 kB of them in the region.
        padded.MergeFromString(b"\xfa\x3f" + _varint(30_000) + b"x" * 30_000)  # field 1023, length-delimited
        largest = polygon_pb(circle(0, 4, 2, MAX_REGION_VERTICES))
        replies = await stream_replies(
            address,
            [
                request("q1", too_many),
                request("q2", padded),
                request("q3", None),  # "the same region as before": the refused one was not kept
                request("q4", largest),
                request("q5", None),  # the same 1000-point region again
            ],
        )
        errors = [(r.error.code, r.error.message) for r in replies]
        assert errors[0] == ("INVALID_ARGUMENT", "region.polygon: 1001 points; at most 1000, simplify the region")
        assert errors[1][0] == "INVALID_ARGUMENT"
        assert re.fullmatch(rf"region: \d+ bytes encoded; at most {MAX_REGION_BYTES}", errors[1][1]), errors[1]
        assert errors[2] == ("INVALID_ARGUMENT", "region: missing; give a box or a polygon")
        assert errors[3] == errors[4] == ("", "")
        # ListCameras takes the same regions.
        async with aio.insecure_channel(address) as channel:
            with pytest.raises(aio.AioRpcError) as err:
                await registry_pb2_grpc.RegisterVisionServiceStub(channel).ListCameras(
                    registry_pb2.ListCamerasRequest(region=too_many), timeout=5
                )
            assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
            assert (err.value.details() or "").startswith("region.polygon: 1001 points")
    finally:
        await server.stop()
    # The client library says the same before sending anything.
    with pytest.raises(InvalidArgument, match="more than 1000 points"):
        polygon_region(circle(0, 4, 2, MAX_REGION_VERTICES + 1))


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        byte, n = n & 0x7F, n >> 7
        out.append(byte | (0x80 if n else 0))
        if not n:
            return bytes(out)


def test_the_region_cache_keeps_within_its_byte_budget() -> None:
    cache = RegionCache(size=1000, budget_bytes=1_000_000)
    big = [region_to_pb(polygon_region(circle(i, 0, 0.5, 1000))).SerializeToString() for i in range(20)]
    for data in big:
        cache.get(data, "region")
    assert cache.bytes <= 1_000_000 and len(cache) < 20
    assert cache.bytes == sum(RegionCache.cost(d) for d, _ in cache._entries)
    # The most recent regions are the ones kept, and a hit hands out the same (prepared) polygon.
    assert cache.get(big[-1], "region") is cache.get(big[-1], "region")
    # The server's cache by default: 1024 entries, 8 MB at most.
    assert convert.REGIONS.budget_bytes == 8 * 1024 * 1024 and convert.REGIONS.size == 1024


# --- amplification -----------------------------------------------------------------------------


async def test_forwarded_bytes_per_robot_are_bounded() -> None:
    """A robot sends one 1000-point region and then asks about it 150 times a second, each time in a
    few bytes; four cameras see it. What the cameras receive is bounded by the robot's forwarding
    budget (here 200 kB/s, burst 400 kB), not by what the robot's few bytes stand for (about 80 kB
    a request, 12 MB a second). `python -m drvs_bench.amplification` prints the same figures."""
    budget = 200_000
    result = await measure(["--max-forward-bytes", str(budget)], cameras=4, seconds=2.0, rate_hz=150)
    wanted = result["requests_sent"] * 4 * 20_000  # what the robot asked to be forwarded, at least
    bound = 2 * budget + budget * result["seconds"]
    # Socket bytes also carry HTTP/2 framing and the cameras' replies' acknowledgements: 10 % slack.
    assert result["camera_bytes_received"] <= 1.1 * bound + 100_000, result
    assert wanted > 10 * bound, result
    assert result["requests_refused"] > 0 and result["refusals"] == ["forwarded bytes"], result
    assert result["requests_forwarded"] >= 2 * budget / (4 * 21_000), result


def test_request_limits_count_forwarded_bytes_and_release_slots() -> None:
    now = [0.0]
    limits = RequestLimits(rate_hz=1000, burst=1000, max_active=2, clock=lambda: now[0], forward_bytes_per_s=100)
    limits.admit("a", 0, 150)
    with pytest.raises(ResourceExhausted, match=r"^forwarded bytes: this request goes to cameras as 100 bytes"):
        limits.admit("a", 0, 100)  # 50 left of the burst of 200
    limits.admit("b", 0, 200)  # another robot has a budget of its own
    now[0] = 0.5
    limits.admit("a", 0, 100)  # refilled at 100 bytes a second
    one = limits.admit("a", 10.0)
    two = limits.admit("a", 10.0)
    with pytest.raises(ResourceExhausted, match="continuous"):
        limits.admit("a", 10.0)
    limits.release("a", one)
    assert limits.active("a") == 1
    three = limits.admit("a", 10.0)
    limits.release("a", two)
    limits.release("a", three)
    limits.release("a", three)  # twice is harmless
    assert limits.active("a") == 0


# --- continuous requests -----------------------------------------------------------------------


def test_report_times_are_computed_lazily() -> None:
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        times = ContinuousMode(100.0, 3600.0).report_times()
        grown = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert grown < 1024, f"{grown} bytes for one schedule"  # a list of 360 001 floats is about 14 MB
    assert len(times) == 360_001 and times[-1] == pytest.approx(3600.0) and times[1] == pytest.approx(0.01)
    assert times[:3] == [0.0, 0.01, 0.02] and list(ContinuousMode().report_times()) == [0.0]
    with pytest.raises(IndexError):
        times[360_001]


async def _error_of_first_report(robot: DrvsClient, *, camera: str = "cam1") -> tuple[Subscription, str]:
    sub = await robot.subscribe(YELLOW, CAM1_REGION, rate_hz=1.0, duration_s=60.0, timeout_s=5.0)
    assert sub.camera_ids == (camera,)
    async for report in sub:
        return sub, report.error
    raise AssertionError("no report")


@pytest.mark.slow
async def test_continuous_caps_per_robot_on_server_and_camera_and_their_slots_come_back(
    recorded: dict[str, RecordedCamera],
) -> None:
    """Server cap 2, camera cap 1 (per robot). The camera refuses a robot's second continuous
    request; the server then frees that request's slot, since no camera runs it. A cancelled
    request frees the camera's slot. And the server refuses the third that is really running."""
    server, address = await start_server("--max-continuous", "2")
    camera = await start_recorded_camera(
        "cam1", recorded["cam1"], address, "--max-continuous", "1", "--log-level", "DEBUG"
    )
    try:
        async with DrvsClient(address, robot_id="r", listen="127.0.0.1:0") as robot:
            first, error = await _error_of_first_report(robot)
            assert error == ""
            for _ in range(3):  # without the server freeing the slots, the second of these is refused
                _, error = await _error_of_first_report(robot)
                assert "RESOURCE_EXHAUSTED camera cam1: continuous: 1 continuous requests already running" in error
            # A region no camera sees holds no slot either.
            for _ in range(3):
                nowhere = await robot.subscribe(YELLOW, (100, 100, 101, 101), rate_hz=1, duration_s=60)
                assert nowhere.camera_ids == ()
            # Cancel the running one: the camera stops it at its next report and frees its slot.
            mark = len(camera.lines)
            first.close()
            await camera.wait_for_line(r"cancelled by the robot", timeout=10, start=mark)
            _, error = await _error_of_first_report(robot)
            assert error == ""
            # The server heard of the cancel too (on the robot's request stream, before any later
            # request): one running there now, of its limit of two, so the next is the camera's to
            # refuse (without the cancel the server would refuse it: two of two).
            _, error = await _error_of_first_report(robot)
            assert "RESOURCE_EXHAUSTED camera cam1: continuous: 1 continuous requests already running" in error
    finally:
        await camera.stop()
        await server.stop()


async def test_a_cancelled_continuous_request_frees_its_place_at_the_server(
    recorded: dict[str, RecordedCamera],
) -> None:
    """Server cap 1 per robot. While one continuous request runs a second is refused; once the robot
    stops listening to the first (the server hears it on the robot's request stream) a new one runs.
    Without the cancel reaching the server, the slot would last the request's 60 s."""
    server, address = await start_server("--max-continuous", "1")
    camera = await start_recorded_camera("cam1", recorded["cam1"], address)
    try:
        async with DrvsClient(address, robot_id="r", listen="127.0.0.1:0") as robot:
            first, error = await _error_of_first_report(robot)
            assert error == ""
            with pytest.raises(ResourceExhausted, match=r"continuous: 1 continuous requests already running"):
                await robot.subscribe(YELLOW, CAM1_REGION, rate_hz=1.0, duration_s=60.0)
            first.close()
            second, error = await _error_of_first_report(robot)
            assert error == ""
            with pytest.raises(ResourceExhausted, match=r"continuous: 1 continuous requests already running"):
                await robot.subscribe(YELLOW, CAM1_REGION, rate_hz=1.0, duration_s=60.0)
            second.close()
    finally:
        await camera.stop()
        await server.stop()


# --- a camera that stops reading -----------------------------------------------------------------


@pytest.mark.slow
async def test_a_camera_that_heartbeats_but_never_reads_is_cut_off_and_costs_the_server_no_memory(
    recorded: dict[str, RecordedCamera],
) -> None:
    """A hostile camera process registers, heartbeats every 50 ms (so the server keeps trying it)
    and never reads the request stream the server opens to it, while eight robot tasks ask about a
    900-point region it sees, as fast as they can. The server cuts each of its streams off after the
    forward timeout, its memory stays flat (before the fix it grew about 3 MB a second here, every
    unanswered request kept), and the real camera goes on serving."""
    server, address = await start_server(
        "--rate-limit", "5000", "--max-forward-bytes", "1e10", "--forward-timeout", "0.5"
    )  # fmt: skip
    stalled = ManagedProcess(
        "stalled", [sys.executable, str(ROLES), "stalled-camera", "--server", address, "--heartbeat", "0.05"]
    )
    camera: ManagedProcess | None = None
    try:
        await stalled.start()
        await stalled.wait_for_line(r"^REGISTERED stalled", timeout=30)
        camera = await start_recorded_camera("cam1", recorded["cam1"], address)
        region = circle(40.0, 4.5, 3.0, 900)  # inside the stalled camera's view (x 34..46), not cam1's
        loop = asyncio.get_running_loop()
        sent = 0
        refused = 0
        # No client-side throttling: the flood is to reach the server, whatever it answers.
        async with DrvsClient(address, robot_id="flood", listen="127.0.0.1:0", throttle_k=math.inf) as robot:

            async def flood(seconds: float) -> None:
                nonlocal sent, refused
                end = loop.time() + seconds
                while loop.time() < end:
                    try:
                        sub = await robot.subscribe(YELLOW, region, timeout_s=0.1)
                    except ResourceExhausted as exc:
                        # The server's door sheds what the stalled camera cannot take, at once.
                        assert exc.retry_after_s > 0, exc
                        refused += 1
                    else:
                        sub.close()
                    sent += 1

            await asyncio.gather(*(flood(2.0) for _ in range(8)))  # warm up: allocator, caches, channels
            rss0, sent0 = rss_bytes(server.pid), sent
            await asyncio.gather(*(flood(8.0) for _ in range(8)))
            rss1 = rss_bytes(server.pid)
        # Every stream it was given was cut off and replaced.
        await stalled.wait_for_line(r"^STREAM 1 CLOSED$", timeout=5)
        assert sum("OPENED" in line for line in stalled.lines) >= 3, stalled.output()
        assert any("no reply within 0.5 s; closing its request stream" in line for line in server.lines)
        assert sent - sent0 > 1000, f"only {sent - sent0} requests: the flood did not run"
        assert rss1 - rss0 < 10 * 2**20, f"server RSS grew {(rss1 - rss0) / 2**20:.1f} MB over {sent - sent0} requests"
        # The real camera serves as before.
        async with DrvsClient(address, robot_id="good", listen="127.0.0.1:0") as good:
            result = await good.detect(YELLOW, CAM1_REGION, timeout_s=10)
            assert result.complete and not result.errors and len(result.detections) == 2
        assert server.returncode is None
    finally:
        if camera is not None:
            await camera.stop()
        await stalled.stop()
        await server.stop()


# --- server-wide connection limits, metrics -------------------------------------------------------


BOX = geometry_pb2.Region(box=geometry_pb2.Box(x_lower=0, y_lower=0, x_upper=1, y_upper=1))


@pytest.mark.slow
async def test_streams_per_connection_are_capped_and_idle_connections_closed() -> None:
    async with (
        server_process("--max-streams-per-connection", "2", "--max-connection-idle", "1") as address,
        aio.insecure_channel(address) as channel,
    ):
        stub = detection_pb2_grpc.DetectObjectBoundaryStub(channel)
        calls = []
        for i in range(2):
            calls.append(stub.DetectStream())
            await calls[i].write(request(f"s{i}", BOX))
            assert (await calls[i].read()).request_id == f"s{i}"
        # A third stream on the same connection waits for one of the two to end.
        calls.append(stub.DetectStream())

        async def third_answer() -> detection_pb2.DetectionReply:
            await calls[2].write(request("s2", BOX))
            reply: detection_pb2.DetectionReply = await calls[2].read()
            return reply

        third = asyncio.get_running_loop().create_task(third_answer())
        done, _ = await asyncio.wait({third}, timeout=1.0)
        assert not done, "a third stream ran beside two on one connection"
        await calls[0].done_writing()
        assert await calls[0].code() == grpc.StatusCode.OK
        assert (await asyncio.wait_for(third, 10)).request_id == "s2"
        for call in calls[1:]:
            await call.done_writing()
            assert await call.code() == grpc.StatusCode.OK
        # No call open: the server closes the connection after a second.
        assert channel.get_state() == grpc.ChannelConnectivity.READY
        await asyncio.wait_for(channel.wait_for_state_change(grpc.ChannelConnectivity.READY), 10)
        assert channel.get_state() != grpc.ChannelConnectivity.READY


async def unary_burst(address: str, connections: int, calls: int) -> tuple[dict[str, int], list[Exception]]:
    """`calls` unary DetectObjects at once, spread over `connections` connections of their own (a
    plain stub, as a client without DrvsClient): the count of each status, and the domain errors
    DrvsClient's mapping (from_rpc_error) makes of the failures."""
    own = [("grpc.use_local_subchannel_pool", 1)]
    channels = [aio.insecure_channel(address, options=own) for _ in range(connections)]
    codes: dict[str, int] = {}
    mapped: list[Exception] = []

    async def one(stub: detection_pb2_grpc.DetectObjectBoundaryStub, i: int) -> None:
        try:
            await stub.DetectObjects(request(f"b{i}", BOX), timeout=60)
            code = "OK"
        except grpc.RpcError as exc:
            code = exc.code().name
            mapped.append(_grpc.from_rpc_error(exc, f"request b{i}"))
        codes[code] = codes.get(code, 0) + 1

    try:
        for channel in channels:
            await channel.channel_ready()
        stubs = [detection_pb2_grpc.DetectObjectBoundaryStub(c) for c in channels]
        await asyncio.gather(*(one(stubs[i % connections], i) for i in range(calls)))
    finally:
        for channel in channels:
            await channel.close()
    return codes, mapped


@pytest.mark.slow
async def test_calls_past_the_pending_limit_are_dropped_at_once_and_read_as_refusals() -> None:
    # 400 unary calls at once on 20 connections: far more than the server takes in at a time (a few
    # passes of its event loop each), so they queue in gRPC's core. With --max-pending-calls 1 the
    # core drops what would queue beyond it (CANCELLED), and DrvsClient's mapping reads that as a
    # refusal with a retry hint, not an unknown failure; with 0 (no limit) every call waits its turn.
    async with server_process("--max-pending-calls", "1", "--rate-limit", "1e6") as address:
        codes, mapped = await unary_burst(address, 20, 400)
    assert codes.get("CANCELLED", 0) > 0, codes
    assert set(codes) <= {"OK", "CANCELLED"}, codes
    assert codes["OK"] > 0, codes
    assert all(isinstance(e, ResourceExhausted) and e.retry_after_s > 0 for e in mapped), mapped[:3]
    assert "dropped before it was taken in" in str(mapped[0])
    async with server_process("--max-pending-calls", "0", "--rate-limit", "1e6") as address:
        codes, mapped = await unary_burst(address, 20, 400)
    assert codes == {"OK": 400}, (codes, mapped[:3])


def test_a_refused_stream_and_a_dropped_call_read_as_refusals_and_other_failures_do_not() -> None:
    def failed(code: grpc.StatusCode, details: str) -> aio.AioRpcError:
        return aio.AioRpcError(code, aio.Metadata(), aio.Metadata(), details)

    refused = _grpc.from_rpc_error(
        failed(grpc.StatusCode.UNAVAILABLE, "Stream removed (RST_STREAM (Received RST_STREAM with error code 7))"), "s"
    )
    assert isinstance(refused, ResourceExhausted) and refused.retry_after_s == _grpc.REFUSED_RETRY_S
    assert "REFUSED_STREAM" in str(refused)
    dropped = _grpc.from_rpc_error(failed(grpc.StatusCode.CANCELLED, "CANCELLED"), "s")
    assert isinstance(dropped, ResourceExhausted) and dropped.retry_after_s == _grpc.REFUSED_RETRY_S
    # A server that went away is still Unavailable, and a call cancelled here is no refusal.
    assert type(_grpc.from_rpc_error(failed(grpc.StatusCode.UNAVAILABLE, "Socket closed"), "s")) is Unavailable
    local = _grpc.from_rpc_error(failed(grpc.StatusCode.CANCELLED, "Locally cancelled by application!"), "s")
    assert type(local) is DrvsError
    # What a camera's registration logs as "busy" rather than "unreachable": these two only.
    refused_stream = "Stream removed (RST_STREAM (Received RST_STREAM with error code 7))"
    assert _grpc.refused_before_read(failed(grpc.StatusCode.UNAVAILABLE, refused_stream))
    assert _grpc.refused_before_read(failed(grpc.StatusCode.CANCELLED, "CANCELLED"))
    assert not _grpc.refused_before_read(failed(grpc.StatusCode.UNAVAILABLE, "Socket closed"))
    assert not _grpc.refused_before_read(failed(grpc.StatusCode.CANCELLED, "Locally cancelled by application!"))


@pytest.mark.slow
async def test_old_connections_are_ended_and_clients_reconnect() -> None:
    server, address = await start_server("--max-connection-age", "1", "--max-connection-age-grace", "0.5")
    try:
        async with aio.insecure_channel(address) as channel:
            stub = detection_pb2_grpc.DetectObjectBoundaryStub(channel)
            call = stub.DetectStream()
            await call.write(request("s0", BOX))
            assert (await call.read()).request_id == "s0"
            # Past its age (1 s) and grace (0.5 s) the connection's calls are ended.
            assert await asyncio.wait_for(call.code(), 10) == grpc.StatusCode.UNAVAILABLE
            # The client reconnects for the next one.
            again = stub.DetectStream()
            await again.write(request("s1", BOX))
            assert (await again.read()).request_id == "s1"
            again.cancel()
        # DrvsClient reopens its request stream by itself.
        async with DrvsClient(address, robot_id="r", listen="127.0.0.1:0", retry=RetryPolicy.retries(2)) as robot:
            loop = asyncio.get_running_loop()
            end = loop.time() + 3.0
            while loop.time() < end:  # across two connection lifetimes, 50 requests a second
                assert (await robot.detect(YELLOW, (0, 0, 1, 1), timeout_s=1)).complete
                await asyncio.sleep(0.02)
    finally:
        await server.stop()


def metrics_line(proc: ManagedProcess) -> str:
    return next(line for line in proc.lines if "metrics on http://" in line)


async def test_metrics_listen_on_loopback_unless_told_otherwise() -> None:
    runs = [
        (("--metrics-port", "0"), "127.0.0.1"),
        (("--metrics-port", "127.0.0.1:0"), "127.0.0.1"),
        (("--metrics-port", "0", "--metrics-host", "0.0.0.0"), "0.0.0.0"),
    ]
    for args, host in runs:
        server, _ = await start_server(*args)
        try:
            await server.wait_for_line(r"metrics on http://")
            assert re.search(rf"metrics on http://{re.escape(host)}:\d+/metrics", metrics_line(server))
        finally:
            await server.stop()


# --- frame freshness -----------------------------------------------------------------------------


class _OneFrame:
    """A frame source holding one frame (the FrameSource protocol)."""

    description = "one frame"

    def __init__(self, frame: Frame) -> None:
        self.frame = frame

    def start(self) -> None:
        pass

    def stop(self) -> None:
        pass

    def latest(self) -> Frame | None:
        return self.frame

    async def wait_first_frame(self, timeout_s: float) -> Frame:
        return self.frame


def test_frame_age_is_measured_on_the_monotonic_clock() -> None:
    """A wall clock that steps (NTP, an operator) neither makes a stale frame fresh nor a fresh one stale."""
    image = np.zeros((4, 4, 3), dtype=np.uint8)
    h = homography_from_pose((0.0, 0.0, 3.0), 90.0, 40.0, 60.0, (640, 480))

    def node(frame: Frame) -> CameraNode:
        return CameraNode("cam", _OneFrame(frame), h, "127.0.0.1:9", max_frame_age_s=2.0)

    # Captured just now, though the wall clock then read a day ago (or a day ahead).
    assert node(Frame(image, time.time() - 86_400, 1, captured_at=time.monotonic())).frame_is_fresh()
    assert node(Frame(image, time.time() + 86_400, 1, captured_at=time.monotonic())).frame_is_fresh()
    # Captured 10 s ago by the monotonic clock, though its wall-clock stamp says now.
    assert not node(Frame(image, time.time(), 1, captured_at=time.monotonic() - 10)).frame_is_fresh()

"""Property-based, against a real drvs-server process: hostile but well-formed inputs on Register and
DetectStream (huge and degenerate polygons, extreme homographies, NaN and infinity, repeated ids,
from several identities) never crash the server or hide an internal error, are refused with a
message naming the field, keep its memory bounded, and no identity can touch another's camera or
requests.

Identities: camera credentials `alice` (owns camera `a-cam`, a real gRPC server that accepts every
request) and `mallory`; robot credentials `ralph` (asks about a-cam's floor after every example)
and `mallet` (sends the hostile requests)."""

from __future__ import annotations

import asyncio
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import grpc
import pytest
from grpc import aio
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drvs.core.geometry import homography_from_pose
from drvs.tools.launch import ManagedProcess, start_server
from drvs.v1 import detection_pb2, detection_pb2_grpc, geometry_pb2, registry_pb2, registry_pb2_grpc
from tests.fakes import AckingCamera, serve_camera

YELLOW = "hsv_014110130035225200"
TOKENS = {
    "alice": "alice-camera-token-0123456789",
    "mallory": "mallory-camera-token-0123456789",
    "ralph": "ralph-robot-token-0123456789",
    "mallet": "mallet-robot-token-0123456789",
}
GOOD_H = homography_from_pose((0.0, 0.0, 3.0), 90.0, 40.0, 60.0, (640, 480)).to_list()
#: a-cam sees about x -3.8..3.8, y 1.5..7.5.
A_CAM_REGION = geometry_pb2.Region(box=geometry_pb2.Box(x_lower=-1, y_lower=3, x_upper=1, y_upper=5))
ALLOWED = {
    grpc.StatusCode.OK,
    grpc.StatusCode.INVALID_ARGUMENT,
    grpc.StatusCode.PERMISSION_DENIED,
    grpc.StatusCode.RESOURCE_EXHAUSTED,
    grpc.StatusCode.NOT_FOUND,
    grpc.StatusCode.FAILED_PRECONDITION,  # a heartbeat without the current registration's secret
}
FIELDS = ("request_id", "robot_id", "filter_def", "region", "callback_address", "continuous", "camera_id",
          "address", "homography", "field_of_view", "detector_kinds", "rate", "forwarded bytes", "max_range_m",
          "registration_secret", "registrations")  # fmt: skip


def meta(name: str) -> tuple[tuple[str, str], ...]:
    return (("authorization", f"Bearer {TOKENS[name]}"),)


@dataclass
class World:
    loop: asyncio.AbstractEventLoop
    server: ManagedProcess
    address: str
    channel: aio.Channel
    a_cam: registry_pb2.CameraInfo
    ralph: aio.StreamStreamCall[detection_pb2.DetectionRequest, detection_pb2.DetectionReply]
    rss0: int
    asked: int = 0


def rss_bytes(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise AssertionError(f"no VmRSS for {pid}")


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> Iterator[World]:
    directory = tmp_path_factory.mktemp("tokens")
    cameras, robots = directory / "cameras.txt", directory / "robots.txt"
    cameras.write_text(f"alice {TOKENS['alice']}\nmallory {TOKENS['mallory']}\n")
    robots.write_text(f"ralph {TOKENS['ralph']}\nmallet {TOKENS['mallet']}\n")
    loop = asyncio.new_event_loop()
    held: dict[str, object] = {}

    async def setup() -> World:
        server, address = await start_server(
            "--camera-tokens", str(cameras), "--robot-tokens", str(robots), "--lease-ttl", "3600"
        )
        held["server"] = server
        accepting, accepting_address = await serve_camera(AckingCamera("a-cam"))
        held["accepting"] = accepting
        channel = aio.insecure_channel(address)
        held["channel"] = channel
        await registry_pb2_grpc.RegisterVisionServiceStub(channel).Register(
            registry_pb2.RegisterRequest(
                camera_id="a-cam",
                address=accepting_address,
                homography=registry_pb2.Homography(m=GOOD_H),
                image_width=640,
                image_height=480,
                max_range_m=6.0,
                detector_kinds=["hsv"],
            ),
            metadata=meta("alice"),
            timeout=5,
        )
        listed = await registry_pb2_grpc.RegisterVisionServiceStub(channel).ListCameras(
            registry_pb2.ListCamerasRequest(), metadata=meta("ralph"), timeout=5
        )
        ralph = detection_pb2_grpc.DetectObjectBoundaryStub(channel).DetectStream(metadata=meta("ralph"))
        held["ralph"] = ralph
        return World(loop, server, address, channel, listed.cameras[0], ralph, rss_bytes(server.pid))

    async def teardown() -> None:
        if "ralph" in held:
            held["ralph"].cancel()  # type: ignore[attr-defined]
        if "channel" in held:
            await held["channel"].close()  # type: ignore[attr-defined]
        if "accepting" in held:
            await held["accepting"].stop(0)  # type: ignore[attr-defined]
        if "server" in held:
            await held["server"].stop()  # type: ignore[attr-defined]

    try:
        w = loop.run_until_complete(setup())
        yield w
        # Memory stayed bounded over every example (huge polygons included).
        grown = rss_bytes(w.server.pid) - w.rss0
        assert grown < 100 * 2**20, f"server RSS grew {grown / 2**20:.0f} MB"
        assert w.server.returncode is None, w.server.output()[-2000:]
        assert not any("Traceback" in line or "internal error" in line for line in w.server.lines), w.server.output()[
            -3000:
        ]
    finally:
        loop.run_until_complete(teardown())
        loop.close()


def check_unharmed(w: World) -> None:
    """alice's camera is as she registered it, and ralph's requests go to it as before."""

    async def go() -> None:
        stub = registry_pb2_grpc.RegisterVisionServiceStub(w.channel)
        listed = await stub.ListCameras(registry_pb2.ListCamerasRequest(), metadata=meta("ralph"), timeout=5)
        a = [c for c in listed.cameras if c.camera_id == "a-cam"]
        assert len(a) == 1 and a[0].address == w.a_cam.address and a[0].field_of_view == w.a_cam.field_of_view
        w.asked += 1
        message = detection_pb2.DetectionRequest(
            request_id=f"ralph-{w.asked}", robot_id="ralph", filter_def=YELLOW, callback_address="127.0.0.1:9"
        )
        message.region.CopyFrom(A_CAM_REGION)
        await w.ralph.write(message)
        reply = await asyncio.wait_for(w.ralph.read(), 10)
        assert isinstance(reply, detection_pb2.DetectionReply), reply
        assert reply.request_id == message.request_id and not reply.HasField("error"), reply
        assert "a-cam" in reply.camera_ids, reply

    w.loop.run_until_complete(go())


def check_status(code: grpc.StatusCode, details: str) -> None:
    assert code in ALLOWED, (code, details)
    if code != grpc.StatusCode.OK:
        assert details and any(details.startswith(f) or f"{f}:" in details for f in FIELDS), (code, details)


# --- strategies ----------------------------------------------------------------------------------

extreme = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=64),
    st.sampled_from([0.0, -0.0, 1e-300, -1e-300, 1e300, -1e300, 1e6, -1e6, 1e6 + 1, math.nan, math.inf, -math.inf]),
)
coordinate = st.one_of(st.floats(-50, 50, allow_nan=False), extreme)


@st.composite
def polygons(draw: st.DrawFn) -> geometry_pb2.Region:
    kind = draw(st.sampled_from(["circle", "points", "collinear", "bowtie", "repeated"]))
    if kind == "circle":  # up to three times the point limit, around a-cam's floor or anywhere
        n = draw(st.sampled_from([3, 4, 999, 1000, 1001, 3000]))
        cx, cy = draw(st.sampled_from([(0.0, 4.5), (40.0, 4.5), (1e5, -1e5)]))
        r = draw(st.sampled_from([1e-6, 1.0, 1e4]))
        pts = [(cx + r * math.cos(2 * math.pi * i / n), cy + r * math.sin(2 * math.pi * i / n)) for i in range(n)]
    elif kind == "points":
        pts = draw(st.lists(st.tuples(coordinate, coordinate), max_size=12))
    elif kind == "collinear":
        pts = [(float(i), 2.0 * i) for i in range(draw(st.integers(3, 50)))]
    elif kind == "bowtie":
        pts = [(0.0, 0.0), (2.0, 2.0), (2.0, 0.0), (0.0, 2.0)]
    else:
        pts = [(1.0, 1.0)] * draw(st.integers(3, 2000))
    return geometry_pb2.Region(polygon=geometry_pb2.Polygon(points=[geometry_pb2.Point2(x=x, y=y) for x, y in pts]))


boxes = st.builds(
    lambda a, b, c, d: geometry_pb2.Region(box=geometry_pb2.Box(x_lower=a, y_lower=b, x_upper=c, y_upper=d)),
    coordinate,
    coordinate,
    coordinate,
    coordinate,
)
regions = st.one_of(st.none(), polygons(), boxes, st.just(A_CAM_REGION))


@st.composite
def detection_requests(draw: st.DrawFn) -> detection_pb2.DetectionRequest:
    msg = detection_pb2.DetectionRequest(
        # ralph's own ids, repeated: another identity's requests are its own business
        request_id=draw(st.sampled_from(["ralph-1", "ralph-2", "m", "x" * 129, "bad id"])),
        robot_id=draw(st.sampled_from(["", "ralph", "mallet"])),
        filter_def=draw(st.sampled_from(["", YELLOW, "hsv_999999999999999999"])),
        callback_address=draw(st.sampled_from(["", "127.0.0.1:9", "10.1.2.3:9", "localhost:65536"])),
    )
    region = draw(regions)
    if region is not None:
        msg.region.CopyFrom(region)
    if draw(st.booleans()):
        msg.continuous.rate_hz = draw(st.one_of(st.sampled_from([0.0, 1.0, 100.0, 101.0]), extreme))
        msg.continuous.duration_s = draw(st.one_of(st.sampled_from([0.0, 1.0, 3600.0, 3601.0]), extreme))
    return msg


homographies = st.one_of(
    st.just(GOOD_H),
    st.lists(extreme, min_size=9, max_size=9),
    st.lists(st.floats(-1e3, 1e3, allow_nan=False), min_size=9, max_size=9),
    st.builds(lambda s: [v * s for v in GOOD_H], st.sampled_from([1e-300, 1e-30, 1e30, 1e300])),
    st.just([1.0, 0, 0, 0, 1e-17, 0, 0, 0, 1.0]),  # nearly singular
)
registrations = st.builds(
    lambda cid, h, w, ht, r, kinds: registry_pb2.RegisterRequest(
        camera_id=cid,
        address="127.0.0.1:9",
        homography=registry_pb2.Homography(m=h),
        image_width=w,
        image_height=ht,
        max_range_m=r,
        detector_kinds=kinds,
    ),
    st.sampled_from(["a-cam", "m-cam", "m-cam-2", "", "x" * 200]),
    homographies,
    st.sampled_from([0, 1, 640, 100_000, 100_001]),
    st.sampled_from([0, 1, 480, 100_000]),
    st.one_of(st.sampled_from([0.0, 6.0, 10_000.0, 10_001.0]), extreme),
    st.sampled_from([["hsv"], [], ["bad kind"], ["hsv"] * 100]),
)
camera_calls = st.sampled_from(["heartbeat", "deregister"])


# --- properties ----------------------------------------------------------------------------------

SETTINGS = settings(
    max_examples=120, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow]
)


@pytest.mark.slow
@SETTINGS
@given(messages=st.lists(detection_requests(), min_size=1, max_size=6))
def test_hostile_detect_streams_are_answered_cleanly_and_touch_nobody_else(
    world: World, messages: list[detection_pb2.DetectionRequest]
) -> None:
    async def go() -> None:
        call = detection_pb2_grpc.DetectObjectBoundaryStub(world.channel).DetectStream(metadata=meta("mallet"))
        try:
            for message in messages:
                await call.write(message)
                reply = await asyncio.wait_for(call.read(), 10)
                assert reply is not aio.EOF, await call.details()
                code = grpc.StatusCode[reply.error.code] if reply.HasField("error") else grpc.StatusCode.OK
                check_status(code, reply.error.message)
        finally:
            call.cancel()

    world.loop.run_until_complete(go())
    check_unharmed(world)


@SETTINGS
@given(registration=registrations, then=camera_calls)
def test_hostile_registrations_are_answered_cleanly_and_touch_nobody_else(
    world: World, registration: registry_pb2.RegisterRequest, then: str
) -> None:
    async def go() -> None:
        stub = registry_pb2_grpc.RegisterVisionServiceStub(world.channel)
        try:
            await stub.Register(registration, metadata=meta("mallory"), timeout=10)
            code, details = grpc.StatusCode.OK, ""
        except aio.AioRpcError as exc:
            code, details = exc.code(), exc.details() or ""
        check_status(code, details)
        if registration.camera_id == "a-cam":
            assert code == grpc.StatusCode.PERMISSION_DENIED, (code, details)
        # mallory's renewals and removals of alice's camera are refused too.
        for cid in ("a-cam", registration.camera_id or "m-cam"):
            try:
                if then == "heartbeat":
                    await stub.Heartbeat(registry_pb2.HeartbeatRequest(camera_id=cid), metadata=meta("mallory"))
                else:
                    await stub.Deregister(registry_pb2.DeregisterRequest(camera_id=cid), metadata=meta("mallory"))
                code, details = grpc.StatusCode.OK, ""
            except aio.AioRpcError as exc:
                code, details = exc.code(), exc.details() or ""
            check_status(code, details)
            if cid == "a-cam":
                assert code == grpc.StatusCode.PERMISSION_DENIED, (code, details)

    world.loop.run_until_complete(go())
    check_unharmed(world)

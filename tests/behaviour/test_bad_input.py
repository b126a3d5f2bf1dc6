"""Property-based: whatever a client sends, the server answers INVALID_ARGUMENT naming a field (or
accepts it), never crashes or hides an internal error, and bad registrations change nothing."""

from __future__ import annotations

import asyncio
import math
import re
from collections.abc import Awaitable, Callable, Iterator

import grpc
import pytest
from grpc import aio
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drvs.core.geometry import homography_from_pose
from drvs.server import DrvsServer
from drvs.v1 import detection_pb2, detection_pb2_grpc, geometry_pb2, registry_pb2, registry_pb2_grpc

FIELDS = ("request_id", "robot_id", "filter_def", "region", "callback_address", "continuous", "camera_id",
          "address", "homography", "image size", "max_range_m", "detector_kinds", "field_of_view")  # fmt: skip

#: A message starts with the field it is about, then ":", "." (a part of it) or "[" (an element).
FIELD_FIRST = re.compile(rf"^({'|'.join(map(re.escape, FIELDS))})[:.\[]")

numbers = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, -0.0, 1e-300, 1e300, -1e300, 1e6, 1e6 + 1, math.nan, math.inf, -math.inf]),
)
texts = st.one_of(st.text(max_size=60), st.sampled_from(["", "hsv_014110130035225200", "127.0.0.1:9", "a" * 500]))
points = st.lists(st.builds(geometry_pb2.Point2, x=numbers, y=numbers), max_size=8)
regions = st.one_of(
    st.none(),
    st.builds(
        lambda a, b, c, d: geometry_pb2.Region(box=geometry_pb2.Box(x_lower=a, y_lower=b, x_upper=c, y_upper=d)),
        numbers,
        numbers,
        numbers,
        numbers,
    ),
    st.builds(lambda p: geometry_pb2.Region(polygon=geometry_pb2.Polygon(points=p)), points),
)


def detection_request(request_id: str, robot_id: str, filter_def: str, region: geometry_pb2.Region | None,
                      callback: str, rate: float, duration: float) -> detection_pb2.DetectionRequest:  # fmt: skip
    msg = detection_pb2.DetectionRequest(
        request_id=request_id, robot_id=robot_id, filter_def=filter_def, callback_address=callback,
        continuous=detection_pb2.ContinuousMode(rate_hz=rate, duration_s=duration),
    )  # fmt: skip
    if region is not None:
        msg.region.CopyFrom(region)
    return msg


requests = st.builds(
    detection_request,
    st.one_of(st.just(""), texts),
    texts,
    st.one_of(texts, st.from_regex(r"hsv_[0-9]{12,20}", fullmatch=True)),
    regions,
    st.one_of(texts, st.from_regex(r"[a-z0-9.]{1,20}:[0-9]{1,6}", fullmatch=True)),
    numbers,
    numbers,
)

GOOD_H = homography_from_pose((0.0, 0.0, 3.0), 90.0, 40.0, 60.0, (640, 480)).to_list()
registrations = st.builds(
    lambda cid, addr, m, w, h, r, kinds: registry_pb2.RegisterRequest(
        camera_id=cid,
        address=addr,
        homography=registry_pb2.Homography(m=m),
        image_width=w,
        image_height=h,
        max_range_m=r,
        detector_kinds=kinds,
    ),
    st.one_of(texts, st.just("cam-x")),
    st.one_of(texts, st.just("127.0.0.1:9")),
    st.one_of(st.lists(numbers, max_size=12), st.just(GOOD_H), st.lists(numbers, min_size=9, max_size=9)),
    st.integers(0, 200_000),
    st.integers(0, 200_000),
    numbers,
    st.lists(texts, max_size=3),
)


@pytest.fixture(scope="module")
def server() -> Iterator[tuple[asyncio.AbstractEventLoop, DrvsServer, aio.Channel]]:
    """One real server on a real socket for all examples (hypothesis runs many per test).

    gRPC's aio calls bind to the loop they are created on, so everything runs on this one loop.
    """
    loop = asyncio.new_event_loop()
    srv = DrvsServer("127.0.0.1:0", lease_ttl_s=3600)

    async def setup() -> aio.Channel:
        await srv.start()
        channel = aio.insecure_channel(srv.address)
        reg = registry_pb2.RegisterRequest(
            camera_id="keep", address="127.0.0.1:9", homography=registry_pb2.Homography(m=GOOD_H),
            image_width=640, image_height=480, max_range_m=6, detector_kinds=["hsv"],
        )  # fmt: skip
        await registry_pb2_grpc.RegisterVisionServiceStub(channel).Register(reg)
        return channel

    channel = loop.run_until_complete(setup())
    yield loop, srv, channel
    loop.run_until_complete(channel.close())
    loop.run_until_complete(srv.stop(0))
    loop.close()


def call(loop: asyncio.AbstractEventLoop, make_call: Callable[[], Awaitable[object]]) -> grpc.StatusCode:
    async def go() -> object:
        return await make_call()

    try:
        loop.run_until_complete(go())
        return grpc.StatusCode.OK
    except aio.AioRpcError as exc:
        details = exc.details() or ""
        # A well-formed callback to somebody else's host is refused by policy, not as malformed.
        expected = (grpc.StatusCode.INVALID_ARGUMENT, grpc.StatusCode.PERMISSION_DENIED)
        assert exc.code() in expected, (exc.code(), details)
        if exc.code() == grpc.StatusCode.PERMISSION_DENIED:
            # ... and a re-registration of a held id (`keep`) without its secret, by ownership.
            assert details.startswith(("callback_address:", "camera_id: 'keep' belongs to another")), details
        # The field comes first ("region.box: x_lower ..."), not somewhere in the sentence.
        assert FIELD_FIRST.match(details), details
        return exc.code()


@pytest.mark.slow
@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(message=requests)
def test_any_detection_request_is_answered_cleanly(
    server: tuple[asyncio.AbstractEventLoop, DrvsServer, aio.Channel], message: detection_pb2.DetectionRequest
) -> None:
    loop, srv, channel = server
    stub = detection_pb2_grpc.DetectObjectBoundaryStub(channel)
    call(loop, lambda: stub.DetectObjects(message, timeout=10))
    assert [c.camera_id for c in srv.registry.cameras()] == ["keep"]


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(message=registrations)
def test_any_registration_is_answered_cleanly_and_bad_ones_change_nothing(
    server: tuple[asyncio.AbstractEventLoop, DrvsServer, aio.Channel], message: registry_pb2.RegisterRequest
) -> None:
    loop, srv, channel = server
    before = {c.camera_id: c.field_of_view for c in srv.registry.cameras()}
    stub = registry_pb2_grpc.RegisterVisionServiceStub(channel)
    code = call(loop, lambda: stub.Register(message, timeout=10))
    after = {c.camera_id: c.field_of_view for c in srv.registry.cameras()}
    if code == grpc.StatusCode.OK:
        assert message.camera_id in after
        if message.camera_id != "keep":
            srv.registry.remove(message.camera_id)
            srv.claims.release(message.camera_id)
    else:
        assert after.keys() == before.keys() and all(after[k].equals(before[k]) for k in before)

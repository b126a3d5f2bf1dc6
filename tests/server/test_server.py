"""The server in-process on a real socket: validation, routing, health and reflection, via raw stubs."""

from __future__ import annotations

from collections.abc import AsyncIterator
from typing import Any

import grpc
import pytest
import pytest_asyncio
from grpc import aio
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection_pb2, reflection_pb2_grpc

from drvs.core.errors import ResourceExhausted
from drvs.core.geometry import homography_from_pose
from drvs.robot import DrvsClient
from drvs.server import DrvsServer
from drvs.v1 import detection_pb2, detection_pb2_grpc, geometry_pb2, registry_pb2, registry_pb2_grpc
from tests.fakes import serve_camera
from tests.helpers import YELLOW, detect_message, register_message


@pytest_asyncio.fixture
async def server() -> AsyncIterator[DrvsServer]:
    async with DrvsServer("127.0.0.1:0", lease_ttl_s=30) as s:
        yield s


@pytest_asyncio.fixture
async def channel(server: DrvsServer) -> AsyncIterator[aio.Channel]:
    async with aio.insecure_channel(server.address) as ch:
        yield ch


async def test_health_and_reflection(channel: aio.Channel) -> None:
    health = health_pb2_grpc.HealthStub(channel)
    for service in ("", "drvs.v1.DetectObjectBoundary", "drvs.v1.RegisterVisionService"):
        reply = await health.Check(health_pb2.HealthCheckRequest(service=service))
        assert reply.status == health_pb2.HealthCheckResponse.SERVING

    stub = reflection_pb2_grpc.ServerReflectionStub(channel)

    async def one() -> AsyncIterator[reflection_pb2.ServerReflectionRequest]:
        yield reflection_pb2.ServerReflectionRequest(list_services="")

    names: set[str] = set()
    async for response in stub.ServerReflectionInfo(one()):
        names |= {s.name for s in response.list_services_response.service}
    assert {"drvs.v1.DetectObjectBoundary", "drvs.v1.RegisterVisionService", "grpc.health.v1.Health"} <= names


async def test_register_returns_lease_and_field_of_view(channel: aio.Channel, server: DrvsServer) -> None:
    stub = registry_pb2_grpc.RegisterVisionServiceStub(channel)
    reply = await stub.Register(register_message())
    assert reply.lease_ttl_s == 30
    assert len(reply.field_of_view.points) >= 4
    listed = await stub.ListCameras(registry_pb2.ListCamerasRequest())
    assert [c.camera_id for c in listed.cameras] == ["cam1"]
    assert 0 < listed.cameras[0].lease_remaining_s <= 30


@pytest.mark.parametrize(
    ("mutate", "field"),
    [
        (lambda m: setattr(m, "camera_id", ""), "camera_id"),
        (lambda m: setattr(m, "camera_id", "bad id!"), "camera_id"),
        (lambda m: setattr(m, "address", "nowhere"), "address"),
        (lambda m: m.ClearField("homography"), "homography"),
        (lambda m: m.homography.m.__delitem__(0), "homography"),
        (lambda m: m.homography.CopyFrom(registry_pb2.Homography(m=[0.0] * 9)), "homography"),
        (
            lambda m: m.homography.CopyFrom(registry_pb2.Homography(m=[1, 2, 3, 2, 4, 6, 0, 0, 1])),
            "homography",
        ),
        (lambda m: m.homography.m.__setitem__(4, float("nan")), "homography"),
        (lambda m: setattr(m, "image_width", 0), "image size"),
        (lambda m: m.ClearField("detector_kinds"), "detector_kinds"),
        # Pitched up: the bottom of the image is sky.
        (
            lambda m: m.homography.CopyFrom(
                registry_pb2.Homography(m=homography_from_pose((0, 0, 3), 90, -30, 60, (640, 480)).to_list())
            ),
            "floor",
        ),
    ],
)
async def test_bad_registration_is_refused_and_changes_nothing(
    channel: aio.Channel, server: DrvsServer, mutate: object, field: str
) -> None:
    stub = registry_pb2_grpc.RegisterVisionServiceStub(channel)
    await stub.Register(register_message("keep"))
    msg = register_message("cam1")
    mutate(msg)  # type: ignore[operator]
    with pytest.raises(aio.AioRpcError) as err:
        await stub.Register(msg)
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert field in (err.value.details() or "")
    assert [c.camera_id for c in server.registry.cameras()] == ["keep"]


async def test_heartbeat_and_deregister_unknown_camera_are_not_found(channel: aio.Channel) -> None:
    stub = registry_pb2_grpc.RegisterVisionServiceStub(channel)
    for call in (stub.Heartbeat(registry_pb2.HeartbeatRequest(camera_id="ghost")),):
        with pytest.raises(aio.AioRpcError) as err:
            await call
        assert err.value.code() == grpc.StatusCode.NOT_FOUND
    with pytest.raises(aio.AioRpcError) as err:
        await stub.Deregister(registry_pb2.DeregisterRequest(camera_id="ghost"))
    assert err.value.code() == grpc.StatusCode.NOT_FOUND


@pytest.mark.parametrize(
    ("overrides", "field"),
    [
        ({"filter_def": "hsv_0141101300352252"}, "filter_def"),
        ({"filter_def": "rgb_014110130035225200"}, "filter_def"),
        ({"filter_def": "hsv_200110130035225200"}, "filter_def"),
        ({"region": None}, "region"),
        ({"region": geometry_pb2.Region(box=geometry_pb2.Box(x_lower=1, x_upper=1, y_upper=1))}, "x_lower"),
        (
            {"region": geometry_pb2.Region(box=geometry_pb2.Box(x_lower=float("nan"), x_upper=1, y_upper=1))},
            "x_lower",
        ),
        ({"region": geometry_pb2.Region(box=geometry_pb2.Box(x_upper=1e300, y_upper=1))}, "x_upper"),
        (
            {
                "region": geometry_pb2.Region(
                    polygon=geometry_pb2.Polygon(
                        points=[
                            geometry_pb2.Point2(x=0, y=0),
                            geometry_pb2.Point2(x=1, y=1),
                            geometry_pb2.Point2(x=1, y=0),
                            geometry_pb2.Point2(x=0, y=1),
                        ]
                    )
                )
            },
            "polygon",
        ),
        ({"callback_address": ""}, "callback_address"),
        ({"callback_address": "no port"}, "callback_address"),
        ({"robot_id": "robot with spaces"}, "robot_id"),
        ({"continuous": detection_pb2.ContinuousMode(rate_hz=10)}, "continuous"),
        ({"continuous": detection_pb2.ContinuousMode(rate_hz=1e9, duration_s=1)}, "rate_hz"),
        ({"continuous": detection_pb2.ContinuousMode(rate_hz=1, duration_s=1e9)}, "duration_s"),
        ({"continuous": detection_pb2.ContinuousMode(rate_hz=float("inf"), duration_s=1)}, "rate_hz"),
    ],
)
async def test_bad_detection_request_is_invalid_argument(
    channel: aio.Channel, server: DrvsServer, overrides: dict[str, object], field: str
) -> None:
    await registry_pb2_grpc.RegisterVisionServiceStub(channel).Register(register_message())
    stub = detection_pb2_grpc.DetectObjectBoundaryStub(channel)
    with pytest.raises(aio.AioRpcError) as err:
        await stub.DetectObjects(detect_message(**overrides))
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert field in (err.value.details() or ""), err.value.details()
    assert len(server.registry) == 1


async def test_streamed_requests_are_answered_in_order_and_a_refusal_does_not_end_the_stream(
    channel: aio.Channel, server: DrvsServer
) -> None:
    await registry_pb2_grpc.RegisterVisionServiceStub(channel).Register(register_message())
    call = detection_pb2_grpc.DetectObjectBoundaryStub(channel).DetectStream()
    bad_region = geometry_pb2.Region(box=geometry_pb2.Box(x_lower=float("nan"), x_upper=1, y_upper=1))
    sent = [
        detect_message(request_id="s1"),
        detect_message(request_id="s2", region=bad_region),
        detect_message(request_id="s3", callback_address="10.1.2.3:9"),
        detect_message(request_id=""),
        # Identity given once: an empty robot_id and callback_address repeat the previous request's.
        detect_message(request_id="s5", robot_id="", callback_address=""),
        # The same objects in the same region: filter_def and region repeat too.
        detect_message(request_id="s6", robot_id="", callback_address="", filter_def="", region=None),
    ]
    for message in sent:
        await call.write(message)
    await call.done_writing()
    replies = [reply async for reply in call]
    assert [r.request_id for r in replies] == ["s1", "s2", "s3", "", "s5", "s6"]
    assert list(replies[0].camera_ids) == ["cam1"] and not replies[0].HasField("error")
    assert replies[1].error.code == "INVALID_ARGUMENT" and "x_lower" in replies[1].error.message
    assert replies[2].error.code == "PERMISSION_DENIED" and "callback_address" in replies[2].error.message
    assert replies[3].error.code == "INVALID_ARGUMENT" and "request_id" in replies[3].error.message
    # Accepted (cam1 itself may be skipped by now: nothing listens at its address, so s1's forward failed).
    assert not replies[4].HasField("error") and not replies[5].HasField("error")
    assert await call.code() == grpc.StatusCode.OK
    assert len(server.registry) == 1


async def test_streamed_request_without_any_callback_is_refused(channel: aio.Channel) -> None:
    call = detection_pb2_grpc.DetectObjectBoundaryStub(channel).DetectStream()
    await call.write(detect_message(request_id="s1", callback_address=""))
    await call.done_writing()
    replies = [reply async for reply in call]
    assert replies[0].error.code == "INVALID_ARGUMENT" and "callback_address" in replies[0].error.message


async def test_server_fills_an_empty_request_id(channel: aio.Channel) -> None:
    stub = detection_pb2_grpc.DetectObjectBoundaryStub(channel)
    reply = await stub.DetectObjects(detect_message(request_id=""))
    assert len(reply.request_id) == 32 and list(reply.camera_ids) == []


async def test_routing_uses_positive_area_overlap(channel: aio.Channel) -> None:
    reg = registry_pb2_grpc.RegisterVisionServiceStub(channel)
    fov = (await reg.Register(register_message("cam1", x=0.0))).field_of_view
    await reg.Register(register_message("cam2", x=20.0))
    xs = [p.x for p in fov.points]
    stub = detection_pb2_grpc.DetectObjectBoundaryStub(channel)
    # A box that only touches cam1's field of view at its rightmost point: zero area, not routed.
    edge = max(xs)
    touching = geometry_pb2.Region(box=geometry_pb2.Box(x_lower=edge, y_lower=0, x_upper=edge + 1, y_upper=10))
    reply = await stub.DetectObjects(detect_message(region=touching))
    assert list(reply.camera_ids) == []
    inside = geometry_pb2.Region(box=geometry_pb2.Box(x_lower=edge - 0.5, y_lower=0, x_upper=edge + 1, y_upper=10))
    reply = await stub.DetectObjects(detect_message(region=inside, request_id="req-2"))
    assert list(reply.camera_ids) == ["cam1"]


async def test_reports_go_only_to_the_requesting_robot(channel: aio.Channel) -> None:
    stub = detection_pb2_grpc.DetectObjectBoundaryStub(channel)
    with pytest.raises(aio.AioRpcError) as err:
        await stub.DetectObjects(detect_message(callback_address="10.1.2.3:9"))
    assert err.value.code() == grpc.StatusCode.PERMISSION_DENIED
    assert "callback_address: 10.1.2.3 is not the requesting robot's address (127.0.0.1)" in (err.value.details() or "")
    # The robot's own address, by number or by name, is fine.
    await stub.DetectObjects(detect_message(callback_address="127.0.0.1:9", request_id="own"))
    await stub.DetectObjects(detect_message(callback_address="localhost:9", request_id="own-name"))


async def test_allowed_callback_networks() -> None:
    async with DrvsServer("127.0.0.1:0", allow_callback=["10.0.0.0/8"]) as srv, aio.insecure_channel(srv.address) as ch:
        stub = detection_pb2_grpc.DetectObjectBoundaryStub(ch)
        await stub.DetectObjects(detect_message(callback_address="10.1.2.3:9"))
        with pytest.raises(aio.AioRpcError) as err:
            await stub.DetectObjects(detect_message(callback_address="192.0.2.7:9", request_id="r2"))
        assert err.value.code() == grpc.StatusCode.PERMISSION_DENIED


def test_peer_addresses_parse() -> None:
    from drvs.server.policy import peer_ip

    assert str(peer_ip("ipv4:127.0.0.1:5000")) == "127.0.0.1"
    assert str(peer_ip("ipv6:[::1]:5000")) == "::1"
    assert peer_ip("unix:/tmp/sock") is None and peer_ip("ipv4:garbage") is None


class _SilentCamera(detection_pb2_grpc.DetectObjectBoundaryServicer):
    """Takes streamed requests and never accepts them: a camera too busy to answer."""

    async def DetectBatches(
        self,
        request_iterator: AsyncIterator[detection_pb2.DetectionRequests],
        context: aio.ServicerContext[Any, Any],
    ) -> AsyncIterator[detection_pb2.DetectionReplies]:
        async for _ in request_iterator:
            pass
        return
        yield  # an async generator that never answers


async def test_server_sheds_load_when_a_camera_has_too_many_requests_waiting() -> None:
    camera, camera_address = await serve_camera(_SilentCamera())
    try:
        async with DrvsServer("127.0.0.1:0", max_queued_forwards=2, forward_timeout_s=30) as server:
            async with aio.insecure_channel(server.address) as channel:
                registration = register_message()
                registration.address = camera_address
                await registry_pb2_grpc.RegisterVisionServiceStub(channel).Register(registration)
            async with DrvsClient(server.address, robot_id="r", listen="127.0.0.1:0") as robot:
                waiting = [await robot.subscribe(YELLOW, (-1, 0, 1, 5), timeout_s=30) for _ in range(2)]
                # The third finds two forwards waiting for cam1: it is refused at once, before cam1
                # is asked, with a hint of when to come back.
                with pytest.raises(ResourceExhausted, match="busy: camera cam1 has 2 requests already waiting") as shed:
                    await robot.detect(YELLOW, (-1, 0, 1, 5), timeout_s=30)
                assert shed.value.retry_after_s > 0
                assert "cam1" not in server._unreachable  # busy is not gone: it stays in routing
                assert [c.camera_id for c in await robot.cameras()] == ["cam1"]
                for sub in waiting:
                    sub.close()
    finally:
        await camera.stop(0)

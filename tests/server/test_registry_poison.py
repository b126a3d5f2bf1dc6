"""A registry shared in etcd survives values that are not records (issue 28, finding 3): garbage,
wrong types, deep nesting and oversized values written straight into etcd are logged, counted in
drvs_registry_records_skipped_total and skipped; the watch goes on (new cameras are routed,
departed ones dropped); and a watch that fails for any other reason is restarted, registrations
refused (health NOT_SERVING for them) until it is back."""

from __future__ import annotations

import json
import re
import shutil
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
import pytest_asyncio
from grpc import aio
from grpc_health.v1 import health_pb2, health_pb2_grpc

from drvs.core.errors import Unavailable
from drvs.server.etcd import Endpoints, EtcdClient
from drvs.server.shared import MAX_VALUE_BYTES, POSES, PREFIX, PoseRecord, Record, SharedRegistry
from drvs.tools.launch import EtcdMember, start_etcd, start_server
from drvs.v1 import registry_pb2, registry_pb2_grpc
from drvs.wire import metrics
from tests.helpers import metrics_at_least, metrics_port, register_message, wait_until

pytestmark = pytest.mark.skipif(
    shutil.which("etcd") is None, reason="etcd is not installed (./run test installs it as root)"
)

REGISTRATION = "drvs.v1.RegisterVisionService"
SKIPPED = 'drvs_registry_records_skipped_total{kind="%s"}'


@pytest_asyncio.fixture
async def etcd(tmp_path: Path) -> AsyncIterator[EtcdMember]:
    members = await start_etcd(tmp_path)
    try:
        yield members[0]
    finally:
        await members[0].stop()


async def call(address: str, method: str, message: object) -> object:
    async with aio.insecure_channel(address) as channel:
        return await getattr(registry_pb2_grpc.RegisterVisionServiceStub(channel), method)(message)


async def listed(address: str) -> list[str]:
    reply = await call(address, "ListCameras", registry_pb2.ListCamerasRequest())
    assert isinstance(reply, registry_pb2.ListCamerasReply)
    return sorted(c.camera_id for c in reply.cameras)


async def health(address: str) -> int:
    async with aio.insecure_channel(address) as channel:
        reply = await health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(service=REGISTRATION))
        return int(reply.status)


def skipped_line(key: str, why: str) -> re.Pattern[str]:
    return re.compile(rf"registry: {re.escape(key)} in etcd is not one DRVS can read \({why}")


async def test_poison_in_etcd_is_skipped_and_the_watch_goes_on(etcd: EtcdMember) -> None:
    server, address = await start_server(
        "--registry", f"etcd://{etcd.address}", "--lease-ttl", "30", "--metrics-port", "0"
    )
    try:
        for camera_id in ("cam-old", "cam-gone"):
            await call(address, "Register", register_message(camera_id))
        assert await listed(address) == ["cam-gone", "cam-old"]
        async with EtcdClient(Endpoints.parse(f"etcd://{etcd.address}")) as client:
            found = await client.get(PREFIX + b"cam-gone")
            assert found is not None
            good = json.loads(found[0])
            wrong_type = dict(good, camera_id="wrong-type", max_range_m="15")
            poison = {
                b"garbage": b"\xff\xfe{not json",
                b"wrong-type": json.dumps(wrong_type).encode(),
                b"bad-homography": json.dumps(dict(good, camera_id="bad-homography", homography="abc")).encode(),
                b"deep": b"[" * 5000 + b"]" * 5000,  # under the size bound: json's recursion decides
                b"huge": b'{"camera_id":"huge","pad":"' + b"x" * (1 << 20) + b'"}',
                b"not-an-object": b"[1, 2, 3]",
                # A registered camera's key overwritten with a record that is not one: it leaves routing.
                b"cam-old": json.dumps(dict(good, camera_id="cam-old", image_size=[640])).encode(),
            }
            for key, value in poison.items():
                await client.put(PREFIX + key, value)
            await client.put(POSES + b"cam-gone", b'{"x":"1","y":0,"yaw":0,"time_unix":0,"origin":"elsewhere"}')
            await client.put(POSES + b"cam-deep", b"{" * 3000)
            # What another server would write: a new camera, then the departure of one.
            await client.put(PREFIX + b"cam-new", json.dumps(dict(good, camera_id="cam-new")).encode())
            await server.wait_for_line(re.compile(r"camera cam-new registered at \S+ through"), timeout=10)
            await client.delete(PREFIX + b"cam-gone")
            await server.wait_for_line(re.compile(r"camera cam-gone left routing: "), timeout=10)
        for name, why in (
            ("garbage", "not UTF-8|Expecting"),
            ("wrong-type", "max_range_m: '15' is not a finite number"),
            ("bad-homography", "homography: 'abc' is not a list"),
            ("deep", "JSON nested too deeply"),
            ("huge", rf"\d+ bytes, more than the {MAX_VALUE_BYTES}"),
            ("not-an-object", "JSON list, not an object"),
            ("cam-old", "image_size: \\[640\\] is not a list of 2"),
        ):
            assert any(skipped_line(f"/drvs/v1/cameras/{name}", why).search(line) for line in server.lines), name
        assert any(
            skipped_line("/drvs/v1/poses/cam-gone", "x: '1' is not a finite number").search(x) for x in server.lines
        )
        values = await metrics_at_least(metrics_port(server), SKIPPED % "camera", 7)
        assert values[SKIPPED % "pose"] >= 2
        # cam-old's registration is no longer a record: out of routing; the new one routed.
        assert await listed(address) == ["cam-new"]
        assert await health(address) == health_pb2.HealthCheckResponse.SERVING
        # And registrations go on.
        await call(address, "Register", register_message("cam-after"))
        assert await listed(address) == ["cam-after", "cam-new"]
        # A server started on the poisoned prefix reads past it too.
        fresh, fresh_address = await start_server("--registry", f"etcd://{etcd.address}", "--lease-ttl", "30")
        try:
            assert await listed(fresh_address) == ["cam-after", "cam-new"]
        finally:
            await fresh.stop()
    finally:
        await server.stop()


def test_a_record_names_what_is_wrong_with_it() -> None:
    good = Record("c", "127.0.0.1:1", (1.0,) * 9, (640, 480), ("hsv",), 15.0, "", "q", "s", "f")
    assert Record.decode(good.encode()) == good
    raw = json.loads(good.encode())
    for field, value, why in (
        ("max_range_m", "15", "max_range_m: '15' is not a finite number"),
        ("max_range_m", True, "max_range_m: True is not a finite number"),
        ("image_size", [1.5, 2], "image_size: 1.5 is not a whole number"),
        ("detector_kinds", [1], "detector_kinds: 1 is not a string"),
        ("mobile", 1, "mobile: 1 is not true or false"),
        ("address", None, "address: None is not a string"),
    ):
        with pytest.raises(ValueError, match=re.escape(why)):
            Record.decode(json.dumps(dict(raw, **{field: value})).encode())
    with pytest.raises(ValueError, match="nested too deeply"):
        Record.decode(b"[" * 5000 + b"]" * 5000)
    with pytest.raises(TypeError):  # a field missing
        Record.decode(json.dumps({k: v for k, v in raw.items() if k != "address"}).encode())
    # A field a newer server added is left out; one an older server lacked takes its default.
    assert Record.decode(json.dumps(dict(raw, newer=1)).encode()) == good
    with pytest.raises(ValueError, match="yaw: nan"):
        PoseRecord.decode(b'{"x":1,"y":2,"yaw":NaN,"time_unix":0,"origin":"o"}')


async def test_a_watch_that_fails_is_restarted_and_registrations_wait_for_it(etcd: EtcdMember) -> None:
    """The watch fails for a reason that is not etcd's (here the server's own callback raising,
    once): it is logged and restarted, health is told NOT_SERVING, then SERVING once it is back."""
    endpoints = Endpoints.parse(f"etcd://{etcd.address}")
    told: list[bool] = []
    applied: list[str] = []
    failures = [RuntimeError("a bug in the server's callback")]

    def known() -> list[str]:
        if failures:
            raise failures.pop()
        return applied

    async def on_reachable(reachable: bool) -> None:
        told.append(reachable)

    restarts = metrics.REGISTRY_WATCH_RESTARTS._value.get()
    shared = SharedRegistry(
        endpoints, lambda r: applied.append(r.camera_id), lambda c, why, lapsed: None, known, on_reachable=on_reachable
    )
    await shared.start()
    try:
        await wait_until(lambda: told == [False, True] and shared.synced.is_set(), "restarted", timeout=10)
        assert metrics.REGISTRY_WATCH_RESTARTS._value.get() == restarts + 1
        good = Record(
            "cam1", "127.0.0.1:1", (1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0), (640, 480), ("hsv",), 15.0, "", "q", "s", "f"
        )
        async with EtcdClient(endpoints) as client:
            await client.put(PREFIX + b"cam1", good.encode())
        await wait_until(lambda: applied == ["cam1"], "cam1 applied", timeout=10)
        # While the watch is down, registrations are refused (this server could not route them).
        shared.trouble = "the watch failed"
        with pytest.raises(Unavailable, match="the watch failed; registrations wait"):
            await shared.put(good, None, 5)
    finally:
        await shared.stop()

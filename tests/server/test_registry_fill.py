"""A registry shared in etcd does not fill (issue 28, findings 12 and 13a): registrations and pose
updates are rate-limited per identity (RESOURCE_EXHAUSTED with a retry hint), so a burst from one
caller is refused before it fills a real etcd's quota and a legitimate camera still registers; the
per-identity cap holds under concurrent registrations; and etcd as DRVS runs it compacts its history."""

from __future__ import annotations

import asyncio
import shutil
import time
import urllib.request
from pathlib import Path

import grpc
import pytest
from grpc import aio

from drvs.core.mobile import Mount
from drvs.server.etcd import Endpoints, EtcdClient
from drvs.tools.launch import ETCD_QUOTA_BYTES, start_etcd, start_server
from drvs.v1 import geometry_pb2, registry_pb2, registry_pb2_grpc
from tests.helpers import register_message

pytestmark = pytest.mark.skipif(
    shutil.which("etcd") is None, reason="etcd is not installed (./run test installs it as root)"
)

LOBBY_TOKEN = "lobby-token-0123456789abcdef"
YARD_TOKEN = "yard-token-fedcba9876543210"


def bearer(token: str) -> tuple[tuple[str, str], ...]:
    return (("authorization", f"Bearer {token}"),)


async def outcomes(
    address: str, messages: list[registry_pb2.RegisterRequest], parallel: int, token: str = ""
) -> dict[str, list[str]]:
    """Send every registration, `parallel` at a time; status code name -> the details of each."""
    found: dict[str, list[str]] = {}
    queue = list(messages)
    async with aio.insecure_channel(address) as channel:
        stub = registry_pb2_grpc.RegisterVisionServiceStub(channel)

        async def worker() -> None:
            while queue:
                message = queue.pop()
                try:
                    await stub.Register(message, metadata=bearer(token) if token else None)
                    found.setdefault("OK", []).append("")
                except aio.AioRpcError as exc:
                    found.setdefault(exc.code().name, []).append(exc.details() or "")

        await asyncio.gather(*(worker() for _ in range(parallel)))
    return found


async def test_the_cap_per_identity_holds_under_concurrent_registrations(tmp_path: Path) -> None:
    members = await start_etcd(tmp_path)
    try:
        server, address = await start_server(
            "--registry", f"etcd://{members[0].address}", "--max-cameras-per-identity", "5", "--lease-ttl", "30"
        )
        try:
            found = await outcomes(address, [register_message(f"cam{i}") for i in range(24)], parallel=24)
            assert len(found.get("OK", [])) == 5, found
            assert len(found["RESOURCE_EXHAUSTED"]) == 19
            assert all("(limit 5 per identity, --max-cameras-per-identity)" in d for d in found["RESOURCE_EXHAUSTED"])
            async with aio.insecure_channel(address) as channel:
                reply = await registry_pb2_grpc.RegisterVisionServiceStub(channel).ListCameras(
                    registry_pb2.ListCamerasRequest()
                )
            assert len(reply.cameras) == 5
        finally:
            await server.stop()
    finally:
        await members[0].stop()


async def test_a_burst_from_one_identity_is_refused_before_it_fills_etcd(tmp_path: Path) -> None:
    """etcd with a 256 KiB quota, which some 260 registrations fill (about 1.2 KB each, kept until
    compacted). One identity (its camera token) sends 400: past its burst (--registration-rate 60) they are
    refused with a retry hint, etcd has room left, and a camera with its own token registers."""
    members = await start_etcd(tmp_path, quota_bytes=256 * 1024)
    (tmp_path / "cameras.txt").write_text(f"lobby {LOBBY_TOKEN}\nyard {YARD_TOKEN}\n")
    try:
        server, address = await start_server(
            "--registry", f"etcd://{members[0].address}", "--camera-tokens", str(tmp_path / "cameras.txt"),
            "--lease-ttl", "30",
        )  # fmt: skip
        try:
            started = time.monotonic()
            found = await outcomes(address, [register_message(f"cam{i}") for i in range(400)], 16, YARD_TOKEN)
            refill = time.monotonic() - started  # one more a second
            assert 60 <= len(found.get("OK", [])) <= 61 + refill, {k: (len(v), v[:1]) for k, v in found.items()}
            assert set(found) == {"OK", "RESOURCE_EXHAUSTED"}, {k: v[:1] for k, v in found.items()}
            detail = found["RESOURCE_EXHAUSTED"][0]
            assert "registrations: token:yard made more than 60 a minute" in detail
            assert "--registration-rate" in detail and "retry in" in detail
            # Over its rate, a caller is refused before anything is done for it: its registration
            # is not read from etcd, nor its field of view computed (nor found wrong).
            broken = register_message("cam-broken")
            del broken.homography.m[:]
            broken.homography.m.extend([0.0] * 9)
            async with aio.insecure_channel(address) as channel:
                stub = registry_pb2_grpc.RegisterVisionServiceStub(channel)
                with pytest.raises(aio.AioRpcError) as refused:
                    await stub.Register(broken, metadata=bearer(YARD_TOKEN))
                assert refused.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED, refused.value.details()
                with pytest.raises(aio.AioRpcError) as invalid:  # another identity is told what is wrong
                    await stub.Register(broken, metadata=bearer(LOBBY_TOKEN))
                assert invalid.value.code() == grpc.StatusCode.INVALID_ARGUMENT, invalid.value.details()
            # etcd has room: a camera with its own identity registers.
            lobby = register_message("lobby-cam")
            async with aio.insecure_channel(address) as channel:
                stub = registry_pb2_grpc.RegisterVisionServiceStub(channel)
                reply = await stub.Register(lobby, metadata=bearer(LOBBY_TOKEN))
            assert reply.registration_secret
            async with EtcdClient(Endpoints.parse(f"etcd://{members[0].address}")) as client:
                status = await client.status()
            assert status.dbSize < 256 * 1024 and not status.errors, (status.dbSize, status.errors)
        finally:
            await server.stop()
    finally:
        await members[0].stop()


async def test_pose_updates_are_rate_limited_per_identity(tmp_path: Path) -> None:
    members = await start_etcd(tmp_path)
    try:
        server, address = await start_server(
            "--registry", f"etcd://{members[0].address}", "--pose-write-rate", "5", "--min-pose-interval", "0",
        )  # fmt: skip
        try:
            async with aio.insecure_channel(address) as channel:
                stub = registry_pb2_grpc.RegisterVisionServiceStub(channel)
                message = register_message("scout")
                mount = Mount(0.1, 0.0, 0.8, 0.0, 30.0, hfov_deg=70.0).base_homography((640, 480))
                message.homography.CopyFrom(registry_pb2.Homography(m=mount.to_list()))
                message.mobile = True
                reply = await stub.Register(message)
                codes: list[grpc.StatusCode] = []
                refusal = ""
                for i in range(12):
                    pose = geometry_pb2.Pose2(x=1.0 + i * 0.01, y=1.0)
                    request = registry_pb2.UpdatePoseRequest(
                        camera_id="scout", registration_secret=reply.registration_secret, pose=pose
                    )
                    try:
                        await stub.UpdatePose(request)
                        codes.append(grpc.StatusCode.OK)
                    except aio.AioRpcError as exc:
                        codes.append(exc.code())
                        refusal = exc.details() or ""
            # A burst of 5 (one second's worth); what comes faster is refused.
            assert codes[:5] == [grpc.StatusCode.OK] * 5
            assert grpc.StatusCode.RESOURCE_EXHAUSTED in codes[5:], codes
            assert codes.count(grpc.StatusCode.OK) < 12
            assert "pose updates: the anonymous caller at 127.0.0.1 made more than 5 a second" in refusal
            assert "--pose-write-rate" in refusal and "retry in" in refusal
        finally:
            await server.stop()
    finally:
        await members[0].stop()


def etcd_metrics(address: str) -> str:
    with urllib.request.urlopen(f"http://{address}/metrics", timeout=5) as reply:
        return str(reply.read().decode())


async def test_etcd_as_drvs_runs_it_compacts_its_history(tmp_path: Path) -> None:
    """start_etcd runs etcd with its quota (ETCD_QUOTA_BYTES unless told) and periodic auto-compaction
    (here of history older than 1 s): old revisions go, so the registrations and poses written do
    not pile up until the quota."""
    members = await start_etcd(tmp_path, compaction_retention="1s")
    try:
        text = await asyncio.to_thread(etcd_metrics, members[0].address)
        assert f"etcd_server_quota_backend_bytes {float(ETCD_QUOTA_BYTES):.8e}" in text
        async with EtcdClient(Endpoints.parse(f"etcd://{members[0].address}")) as client:
            first = await client.put(b"/drvs/v1/test", b"one")
            await client.put(b"/drvs/v1/test", b"two")
            rpc = client._rpc

            async def compacted() -> bool:
                try:
                    await client.kv.Range(rpc.RangeRequest(key=b"/drvs/v1/test", revision=first), timeout=5)
                except aio.AioRpcError as exc:
                    return "compacted" in (exc.details() or "")
                return False

            deadline = time.monotonic() + 15
            while not await compacted():
                assert time.monotonic() < deadline, "etcd did not compact its history within 15 s"
                await client.put(b"/drvs/v1/test", b"more")  # periodic compaction needs revisions to go past
                await asyncio.sleep(0.2)
    finally:
        await members[0].stop()

"""drvs-bench cluster `--parts writes`: what a fleet writes to etcd (issue 28, finding 12).

A real etcd member (as drvs.tools.launch runs it) and one `DrvsServer` in this process with the registry
in it (the default lease, 10 s, and the default rates lifted so that the run is not refused). Fake
cameras register, heartbeat and (the mobile ones) send pose updates over gRPC as camera nodes do,
one phase after another; around each phase the run reads etcd's own counters from its /metrics
(`etcd_network_client_grpc_received_bytes_total`: every byte the server sent etcd, reads and lease
renewals included) and sums the keys and values of the changes a watch of DRVS's prefix sees (the
history etcd keeps until it compacts: what fills its quota). Per operation, then per camera and
second at a camera's own cadence: one heartbeat every lease / 3 (camera nodes' default), and for a
mobile camera POSE_HZ pose updates a second besides. Registrations happen at a camera's start and
after a lost lease, so they are given per registration, not per second.
"""

from __future__ import annotations

import asyncio
import time
import urllib.request
from typing import Any

from grpc import aio

from drvs.core.mobile import Mount
from drvs.server import DrvsServer
from drvs.server.config import ServerConfig
from drvs.server.etcd import Endpoints, EtcdClient
from drvs.server.registry import DEFAULT_LEASE_TTL_S
from drvs.server.shared import ROOT
from drvs.tools.fakes import register_message
from drvs.tools.launch import running_etcd
from drvs.v1 import geometry_pb2, registry_pb2, registry_pb2_grpc

#: The fleet: fixed cameras, mobile ones, and how often a mobile camera sends its pose.
STATIC, MOBILE = 20, 5
QUICK_STATIC, QUICK_MOBILE = 6, 2
POSE_HZ = 5.0
#: Heartbeats per camera and pose updates per mobile camera measured.
HEARTBEATS, POSES = 3, 10


def _received(address: str) -> float:
    with urllib.request.urlopen(f"http://{address}/metrics", timeout=5) as reply:
        for line in reply.read().decode().splitlines():
            if line.startswith("etcd_network_client_grpc_received_bytes_total "):
                return float(line.split()[1])
    return 0.0


class _History:
    """Sums the keys and values of every change under DRVS's prefix (a watch of its own)."""

    def __init__(self, client: EtcdClient) -> None:
        self.bytes = 0
        self.changes = 0
        self._client = client
        self._task: asyncio.Task[None] | None = None

    async def start(self) -> None:
        revision = (await self._client.get_prefix(ROOT))[1]
        self._task = asyncio.get_running_loop().create_task(self._run(revision + 1))

    async def _run(self, revision: int) -> None:
        async for event in self._client.watch_prefix(ROOT, revision):
            self.bytes += len(event.key) + len(event.value)
            self.changes += 1

    async def until(self, changes: int) -> None:
        deadline = time.monotonic() + 30
        while self.changes < changes:  # the watch is behind the writes by a little
            assert time.monotonic() < deadline, f"the watch saw {self.changes} changes, not {changes}"
            await asyncio.sleep(0.01)

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)


async def fleet_writes(quick: bool) -> dict[str, Any]:
    static, mobile = (QUICK_STATIC, QUICK_MOBILE) if quick else (STATIC, MOBILE)
    async with running_etcd() as members:
        registry, address = "etcd://" + members[0].address, members[0].address
        config = ServerConfig(
            listen="127.0.0.1:0", registry=registry, registration_rate=1e9, pose_write_rate=1e9, min_pose_interval_s=0
        )
        server = DrvsServer(config=config)
        await server.start()
        client = EtcdClient(Endpoints.parse(registry))
        await client.start()
        history = _History(client)
        await history.start()
        phases: dict[str, dict[str, float]] = {}

        async def phase(name: str, count: int, changes: int, work: Any) -> None:
            sent0, kept0, seen0 = _received(address), history.bytes, history.changes
            await work()
            await history.until(seen0 + changes)
            phases[name] = {
                "count": count,
                "bytes_sent_to_etcd": (_received(address) - sent0) / count,
                "history_bytes": (history.bytes - kept0) / count,
            }

        try:
            async with aio.insecure_channel(server.address) as channel:
                stub = registry_pb2_grpc.RegisterVisionServiceStub(channel)
                secrets: dict[str, str] = {}
                mount = Mount(0.1, 0.0, 0.8, 0.0, 30.0, hfov_deg=70.0).base_homography((640, 480))

                async def register() -> None:
                    for i in range(static + mobile):
                        message = register_message(f"cam-{i:03d}", x=10.0 * i)
                        if i >= static:
                            message.homography.CopyFrom(registry_pb2.Homography(m=mount.to_list()))
                            message.mobile = True
                        secrets[message.camera_id] = (await stub.Register(message)).registration_secret

                async def heartbeat() -> None:
                    for _ in range(HEARTBEATS):
                        for camera_id, secret in secrets.items():
                            request = registry_pb2.HeartbeatRequest(camera_id=camera_id, registration_secret=secret)
                            await stub.Heartbeat(request)

                async def poses() -> None:
                    for k in range(POSES):
                        for camera_id in list(secrets)[static:]:
                            pose = geometry_pb2.Pose2(x=1.0 + k, y=1.0)
                            before = history.changes
                            await stub.UpdatePose(
                                registry_pb2.UpdatePoseRequest(
                                    camera_id=camera_id, registration_secret=secrets[camera_id], pose=pose
                                )
                            )
                            # One update at a time, as a camera sends them: its write lands first.
                            await history.until(before + 1)

                cameras = static + mobile
                await phase("registration", cameras, cameras, register)
                await phase("heartbeat", cameras * HEARTBEATS, 0, heartbeat)
                await phase("pose_update", mobile * POSES, 0, poses)
        finally:
            await history.stop()
            await client.close()
            await server.stop()
    heartbeat_hz = 3.0 / DEFAULT_LEASE_TTL_S
    per_s = {
        "static": {k: phases["heartbeat"][k] * heartbeat_hz for k in ("bytes_sent_to_etcd", "history_bytes")},
        "mobile": {
            k: phases["heartbeat"][k] * heartbeat_hz + phases["pose_update"][k] * POSE_HZ
            for k in ("bytes_sent_to_etcd", "history_bytes")
        },
    }
    return {
        "static_cameras": static,
        "mobile_cameras": mobile,
        "lease_ttl_s": DEFAULT_LEASE_TTL_S,
        "heartbeat_hz": heartbeat_hz,
        "pose_hz": POSE_HZ,
        "per_operation": phases,
        "per_camera_per_s": per_s,
        "fleet_100_static_10_mobile_per_s": {
            k: 100 * per_s["static"][k] + 10 * per_s["mobile"][k] for k in ("bytes_sent_to_etcd", "history_bytes")
        },
    }

"""Who may use the registry in etcd (issue 28, finding 4): etcd started with TLS, client
certificates and its own access control (drvs.server.etcd_auth, users from certificates' common names)
serves a DRVS server's certificate and refuses a robot's or a camera's from the same CA, for reads
and for writes; and etcd never holds a registration's secret, only its digest."""

from __future__ import annotations

import asyncio
import shutil
from pathlib import Path

import grpc
import pytest
from grpc import aio

from drvs.core.errors import InvalidArgument, Unavailable
from drvs.server import etcd_auth
from drvs.server.config import ServerConfig
from drvs.server.etcd import Endpoints, EtcdClient
from drvs.server.shared import PREFIX, secret_digest
from drvs.tools.certs import make_all
from drvs.tools.launch import ManagedProcess, running_etcd, start_etcd, start_server
from drvs.v1 import registry_pb2, registry_pb2_grpc
from tests.helpers import register_message

pytestmark = pytest.mark.skipif(
    shutil.which("etcd") is None, reason="etcd is not installed (./run test installs it as root)"
)


def credentials(ca: Path, cert: Path, key: Path) -> grpc.ChannelCredentials:
    return grpc.ssl_channel_credentials(ca.read_bytes(), key.read_bytes(), cert.read_bytes())


async def test_only_server_certificates_read_or_write_the_registry_in_etcd(tmp_path: Path) -> None:
    made = make_all(tmp_path / "certs", ["server", "camera", "robot"], [], cameras=["lobby"], etcd_hosts=[])
    ca = tmp_path / "certs" / "ca.pem"

    def setup(who: str, *users: str) -> int:
        cert, key = made[who]
        args = ["--endpoints", str(endpoints), "--ca", str(ca), "--cert", str(cert), "--key", str(key)]
        return etcd_auth.main([*args, *(a for u in users for a in ("--user", u))])

    # Two members, both given: under TLS the client holds a channel per member (finding 7).
    async with running_etcd(2, tls=(ca, *made["etcd"]), client_tls=made["server"]) as etcd:
        endpoints = Endpoints.parse("etcd://" + ",".join(m.address for m in etcd))
        assert await asyncio.to_thread(setup, "etcd-root", "server") == 0  # the documented command
        async with EtcdClient(endpoints, credentials=credentials(ca, *made["server"])) as server:
            await server.put(PREFIX + b"cam1", b"{}")
            assert (await server.get(PREFIX + b"cam1")) == (b"{}", 0)
        for who in ("robot", "camera", "camera-lobby"):
            async with EtcdClient(endpoints, credentials=credentials(ca, *made[who])) as stranger:
                with pytest.raises(Unavailable, match=r"user name not found|permission denied") as read:
                    await stranger.get_prefix(PREFIX)
                with pytest.raises(Unavailable, match=r"user name not found|permission denied"):
                    await stranger.put(PREFIX + b"cam1", b'{"address": "127.0.0.1:1"}')
                assert "cam1" not in str(read.value)
        # Nor may they give themselves a user; root may add one, again and again.
        assert await asyncio.to_thread(setup, "robot", "robot") == 2
        assert await asyncio.to_thread(setup, "etcd-root", "server", "server-b") == 0
        # A server's user may use DRVS's keys only.
        async with EtcdClient(endpoints, credentials=credentials(ca, *made["server"])) as server:
            with pytest.raises(Unavailable, match="permission denied"):
                await server.put(b"/elsewhere", b"x")
            assert (await server.get(PREFIX + b"cam1")) == (b"{}", 0)  # unchanged


async def test_a_real_server_registers_through_etcd_with_access_control(tmp_path: Path) -> None:
    """A drvs-server whose --etcd-cert is a server's registers a camera with etcd's access control
    on; the registration's secret works for a heartbeat, and etcd holds only its digest."""
    made = make_all(tmp_path / "certs", ["server"], [], etcd_hosts=[])
    ca = tmp_path / "certs" / "ca.pem"
    etcd = await start_etcd(
        tmp_path / "etcd", tls=(ca, *made["etcd"]), client_tls=made["server"], auth_users=["server"]
    )
    cert, key = made["server"]
    tls = ("--etcd-ca", str(ca), "--etcd-cert", str(cert), "--etcd-key", str(key))
    procs: list[ManagedProcess] = []
    try:
        proc, address = await start_server("--registry", "etcd://" + etcd[0].address, *tls)
        procs.append(proc)
        async with aio.insecure_channel(address) as channel:
            stub = registry_pb2_grpc.RegisterVisionServiceStub(channel)
            reply = await stub.Register(register_message("cam1"))
            secret = reply.registration_secret
            assert secret
            async with EtcdClient(
                Endpoints.parse("etcd://" + etcd[0].address), credentials=credentials(ca, cert, key)
            ) as e:
                stored = await e.get(PREFIX + b"cam1")
            assert stored is not None
            assert secret not in stored[0].decode()
            assert secret_digest(secret) in stored[0].decode()
            await stub.Heartbeat(registry_pb2.HeartbeatRequest(camera_id="cam1", registration_secret=secret))
            # What etcd holds does not stand in for the secret.
            with pytest.raises(aio.AioRpcError) as err:
                await stub.Heartbeat(
                    registry_pb2.HeartbeatRequest(camera_id="cam1", registration_secret=secret_digest(secret))
                )
            assert err.value.code() == grpc.StatusCode.FAILED_PRECONDITION
            assert "registration_secret: not the current one" in (err.value.details() or "")
    finally:
        for p in procs:
            await p.stop()
        for m in etcd:
            await m.stop()


def test_a_server_refuses_another_roles_certificate_for_etcd(tmp_path: Path) -> None:
    made = make_all(tmp_path / "certs", ["server", "robot"], [])
    ca = tmp_path / "certs" / "ca.pem"
    cert, key = made["robot"]
    with pytest.raises(InvalidArgument, match=r"--etcd-cert, DRVS_ETCD_CERT\): 'robot' is a robot certificate"):
        ServerConfig(registry="etcd://127.0.0.1:2379", etcd_ca=str(ca), etcd_cert=str(cert), etcd_key=str(key))


def test_drvs_certs_keeps_etcd_user_names_for_servers(tmp_path: Path) -> None:
    for name in ("root", "server", "server-b", "etcd"):
        with pytest.raises(InvalidArgument, match="etcd user"):
            make_all(tmp_path / "certs", [], [], cameras=[name])
        with pytest.raises(InvalidArgument, match="etcd user"):
            make_all(tmp_path / "certs", [], [], robots=[name])

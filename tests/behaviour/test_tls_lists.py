"""Mutual TLS to a list of servers, and the server's role (issue 28, findings 6 and 7).

A robot and a camera given `A,B` under mutual TLS verify each server's certificate against its own
address (a channel per server: one channel's authority would be the whole list, which no
certificate names) and go on through B when A dies. A robot or a camera whose server presents a
certificate made for another role (a camera's, from the same CA) refuses to talk to it: the robot
with PermissionDenied naming the role, the camera without ever sending its registration."""

from __future__ import annotations

import re
import shutil
import time
from pathlib import Path

import pytest

from drvs import DrvsClient
from drvs.core.errors import PermissionDenied, Unavailable
from drvs.sim.scene import RecordedCamera
from drvs.tools.certs import make_all
from drvs.tools.launch import ManagedProcess, start_camera, start_etcd, start_server
from drvs.wire.security import Security
from tests.helpers import CAM1_REGION, MAX_RANGE, YELLOW


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("certs")
    make_all(out, ["server", "camera", "robot"], [])
    return out


def tls_args(certs: Path, role: str) -> list[str]:
    return ["--tls-cert", str(certs / f"{role}.pem"), "--tls-key", str(certs / f"{role}-key.pem"),
            "--tls-ca", str(certs / "ca.pem"), "--tls-client-auth"]  # fmt: skip


def robot_tls(certs: Path) -> Security:
    return Security(tls_cert=certs / "robot.pem", tls_key=certs / "robot-key.pem", tls_ca=certs / "ca.pem")


@pytest.mark.skipif(shutil.which("etcd") is None, reason="etcd is not installed (./run test installs it as root)")
async def test_mutual_tls_through_a_server_list_survives_a_killed_server(
    tmp_path: Path, certs: Path, recorded: dict[str, RecordedCamera]
) -> None:
    etcd = await start_etcd(tmp_path)
    registry = "etcd://" + etcd[0].address
    procs: list[ManagedProcess] = []
    try:
        servers = [
            await start_server("--registry", registry, "--lease-ttl", "2", "--log-level", "DEBUG",
                               *tls_args(certs, "server"))
            for _ in range(2)
        ]  # fmt: skip
        procs += [p for p, _ in servers]
        (a, a_address), (b, b_address) = servers
        both = f"{a_address},{b_address}"
        rec = recorded["cam1"]
        procs.append(
            await start_camera(
                "cam1", rec.video, rec.homography_file, both, "--max-range", MAX_RANGE, *tls_args(certs, "camera")
            )
        )
        async with DrvsClient.connect(both, robot_id="r", listen="127.0.0.1:0", security=robot_tls(certs)) as robot:
            result = await robot.detect(YELLOW, CAM1_REGION, timeout_s=10)
            assert result.complete and len(result.detections) == 2
            seen = len(b.lines)
            a.kill()
            # The camera's heartbeats move to B (its 2 s lease would run out otherwise) ...
            beat = re.compile(r"camera cam1: heartbeat; its lease in etcd renewed")
            await b.wait_for_line(beat, timeout=10, start=seen)
            await b.wait_for_line(beat, timeout=10, start=len(b.lines))
            # ... and the robot's requests go through B.
            deadline = time.monotonic() + 10
            while True:
                try:
                    result = await robot.detect(YELLOW, CAM1_REGION, timeout_s=5)
                    break
                except Unavailable:
                    if time.monotonic() > deadline:
                        raise
            assert result.complete and len(result.detections) == 2
    finally:
        for p in reversed(procs):
            await p.stop()
        for m in etcd:
            await m.stop()


async def test_robot_and_camera_refuse_a_server_with_another_roles_certificate(
    certs: Path, recorded: dict[str, RecordedCamera]
) -> None:
    """A server listening with a camera's certificate (same CA, host names that match): the robot
    refuses it at connect, the camera logs why and never registers."""
    impostor, address = await start_server(*tls_args(certs, "camera"))
    procs = [impostor]
    try:
        with pytest.raises(PermissionDenied, match=r"its certificate 'camera' has the role camera \(OU=camera\), not "
                           r"server"):  # fmt: skip
            async with DrvsClient.connect(address, robot_id="r", security=robot_tls(certs)):
                pass
        rec = recorded["cam1"]
        camera = ManagedProcess.entry_point(
            "cam1", "drvs-camera", "--id", "cam1", "--source", str(rec.video), "--homography",
            str(rec.homography_file), "--server", address, "--listen", "127.0.0.1:0", "--max-range", MAX_RANGE,
            *tls_args(certs, "camera"),
        )  # fmt: skip
        procs.append(camera)
        await camera.start()
        await camera.wait_for_line(
            re.compile(r"camera cam1: server \S+: its certificate 'camera' has the role camera .* refusing"), timeout=15
        )
        assert not any("registered" in line for line in impostor.lines if "cam1" in line)
    finally:
        for p in reversed(procs):
            await p.stop()


def test_drvs_certs_gives_each_role_its_own_host_names(tmp_path: Path) -> None:
    from cryptography import x509

    from drvs.tools import certs as drvs_certs

    roles = ["--role", "server", "--role", "camera", "--role", "robot"]
    assert drvs_certs.main([*roles, "--out", str(tmp_path), "--server-host", "drvs.test", "--camera-host", "cams.test",
                            "--host", "all.test", "--etcd", "--etcd-host", "etcd.test"]) == 0  # fmt: skip

    def names(stem: str) -> set[str]:
        cert = x509.load_pem_x509_certificate((tmp_path / f"{stem}.pem").read_bytes())
        return set(cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value.get_values_for_type(
            x509.DNSName))  # fmt: skip

    assert names("server") == {"localhost", "all.test", "drvs.test"}
    assert names("camera") == {"localhost", "all.test", "cams.test"}
    assert names("robot") == {"localhost", "all.test"}
    assert names("etcd") == {"localhost", "etcd.test"}
    root = x509.load_pem_x509_certificate((tmp_path / "etcd-root.pem").read_bytes())
    assert root.subject.rfc4514_string().startswith("CN=root")

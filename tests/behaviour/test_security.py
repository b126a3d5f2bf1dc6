"""Who may talk to whom, with real processes: TLS and mutual TLS on every hop, tokens, camera-id
ownership, and per-robot limits."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from pathlib import Path

import grpc
import pytest
import pytest_asyncio
from grpc import aio
from grpc_health.v1 import health_pb2, health_pb2_grpc

from drvs.core.errors import InvalidArgument, ResourceExhausted, Unauthenticated, Unavailable
from drvs.robot import DrvsClient, RetryPolicy
from drvs.server import DrvsServer
from drvs.server.policy import RequestLimits
from drvs.sim.scene import RecordedCamera
from drvs.tools.certs import make_all
from drvs.tools.launch import ManagedProcess, start_camera, start_server
from drvs.v1 import detection_pb2, detection_pb2_grpc, geometry_pb2, registry_pb2, registry_pb2_grpc
from drvs.wire.security import Security, load_tokens
from tests.fakes import start_recorded_camera
from tests.helpers import CAM1_REGION, MAX_RANGE, YELLOW, detect_message, register_message

CAMERA_TOKEN = "camera-token-0123456789abcdef"
OTHER_CAMERA_TOKEN = "camera-token-fedcba9876543210"
ROBOT_TOKEN = "robot-token-0123456789abcdef"


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("certs")
    make_all(out, ["server", "camera", "robot"], [])
    make_all(out / "stranger", ["robot"], [])  # another CA altogether
    return out


def tls_args(certs: Path, role: str) -> list[str]:
    return ["--tls-cert", str(certs / f"{role}.pem"), "--tls-key", str(certs / f"{role}-key.pem"),
            "--tls-ca", str(certs / "ca.pem"), "--tls-client-auth"]  # fmt: skip


def tls(certs: Path, role: str, ca: Path | None = None) -> Security:
    return Security(
        tls_cert=certs / f"{role}.pem",
        tls_key=certs / f"{role}-key.pem",
        tls_ca=ca or certs / "ca.pem",
        require_client_cert=True,
    )


@pytest.mark.slow
async def test_mutual_tls_on_every_hop(certs: Path, recorded: dict[str, RecordedCamera]) -> None:
    """Robot -> server, server -> camera, camera -> server and camera -> robot all run over mutual
    TLS: the detection comes back, and a peer without a certificate from the CA gets nowhere."""
    procs: list[ManagedProcess] = []
    try:
        server, address = await start_server(*tls_args(certs, "server"))
        procs.append(server)
        assert any("security: mutual TLS" in line for line in server.lines)
        rec = recorded["cam1"]
        procs.append(
            await start_camera(
                "cam1", rec.video, rec.homography_file, address, "--max-range", MAX_RANGE, *tls_args(certs, "camera")
            )
        )
        async with DrvsClient(address, robot_id="r", listen="127.0.0.1:0", security=tls(certs, "robot")) as robot:
            result = await robot.detect(YELLOW, CAM1_REGION, timeout_s=10)
            assert result.complete and len(result.detections) == 2
        # Plain TCP to a TLS server: no handshake, no service.
        async with DrvsClient(address, robot_id="plain", listen="127.0.0.1:0") as plain:
            with pytest.raises(Unavailable):
                await plain.detect(YELLOW, CAM1_REGION, timeout_s=2)
        # A certificate from another CA is refused by the server (and its own CA refuses the server).
        stranger = tls(certs / "stranger", "robot", ca=certs / "stranger" / "ca.pem")
        async with DrvsClient(address, robot_id="s", listen="127.0.0.1:0", security=stranger) as other:
            with pytest.raises(Unavailable):
                await other.detect(YELLOW, CAM1_REGION, timeout_s=2)
    finally:
        for p in reversed(procs):
            await p.stop()


@pytest_asyncio.fixture
async def token_office(
    tmp_path: Path, recorded: dict[str, RecordedCamera]
) -> AsyncIterator[tuple[str, ManagedProcess, Path]]:
    (tmp_path / "cameras.txt").write_text(f"# name token\nlobby {CAMERA_TOKEN}\nyard {OTHER_CAMERA_TOKEN}\n")
    (tmp_path / "robots.txt").write_text(f"turtle {ROBOT_TOKEN}\n")
    (tmp_path / "cam.token").write_text(CAMERA_TOKEN + "\n")
    (tmp_path / "robot.token").write_text(ROBOT_TOKEN)
    server, address = await start_server(
        "--camera-tokens", str(tmp_path / "cameras.txt"), "--robot-tokens", str(tmp_path / "robots.txt")
    )
    camera: ManagedProcess | None = None
    try:
        camera = await start_recorded_camera(
            "cam1", recorded["cam1"], address, "--token-file", str(tmp_path / "cam.token")
        )
        yield address, camera, tmp_path
    finally:
        if camera is not None:
            await camera.stop()
        await server.stop()


def bearer(token: str) -> tuple[tuple[str, str], ...]:
    return (("authorization", f"Bearer {token}"),)


@pytest.mark.slow
async def test_tokens_robots_and_cameras_need_their_own(token_office: tuple[str, ManagedProcess, Path]) -> None:
    address, camera, _ = token_office
    robot_token = Security(token=ROBOT_TOKEN)
    async with DrvsClient(address, robot_id="turtle", listen="127.0.0.1:0", security=robot_token) as robot:
        result = await robot.detect(YELLOW, CAM1_REGION, timeout_s=10)
        assert result.complete and len(result.detections) == 2
        assert [c.camera_id for c in await robot.cameras()] == ["cam1"]
    for security in (Security(), Security(token=CAMERA_TOKEN)):  # none, or a camera's token
        async with DrvsClient(address, robot_id="x", listen="127.0.0.1:0", security=security) as stranger:
            with pytest.raises(Unauthenticated, match="needs a valid robot token"):
                await stranger.detect(YELLOW, CAM1_REGION, timeout_s=2)
            with pytest.raises(Unauthenticated):
                await stranger.cameras()
    async with aio.insecure_channel(address) as channel:
        registry = registry_pb2_grpc.RegisterVisionServiceStub(channel)
        # A robot's token does not register cameras.
        with pytest.raises(aio.AioRpcError) as err:
            await registry.Register(register_message("cam9"), metadata=bearer(ROBOT_TOKEN))
        assert err.value.code() == grpc.StatusCode.UNAUTHENTICATED
        # Another camera credential cannot take over cam1, renew it or deregister it.
        for call, message in (
            (registry.Register, register_message("cam1")),
            (registry.Heartbeat, registry_pb2.HeartbeatRequest(camera_id="cam1")),
            (registry.Deregister, registry_pb2.DeregisterRequest(camera_id="cam1")),
        ):
            with pytest.raises(aio.AioRpcError) as err:
                await call(message, metadata=bearer(OTHER_CAMERA_TOKEN))
            assert err.value.code() == grpc.StatusCode.PERMISSION_DENIED
            assert "camera_id: 'cam1' belongs to another credential" in (err.value.details() or "")
        # ... but may register an id of its own.
        own = await registry.Register(register_message("yard-1"), metadata=bearer(OTHER_CAMERA_TOKEN))
        await registry.Deregister(
            registry_pb2.DeregisterRequest(camera_id="yard-1", registration_secret=own.registration_secret),
            metadata=bearer(OTHER_CAMERA_TOKEN),
        )
        # Health stays open for probes.
        health = await health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest())
        assert health.status == health_pb2.HealthCheckResponse.SERVING
    # The camera takes requests only with its own token (the server presents it): not from strangers.
    listening = next(line for line in camera.lines if "listening on" in line).split("listening on ")[1].split()[0]
    async with aio.insecure_channel(listening) as channel:
        stub = detection_pb2_grpc.DetectObjectBoundaryStub(channel)
        request = detect_message(request_id="direct", callback_address="10.9.9.9:9")
        # (on DetectBatches, the one method a camera serves; the server's forwards use it)
        call = stub.DetectBatches(metadata=bearer(ROBOT_TOKEN))
        # The camera may refuse the call before our write goes out, and then the write itself
        # fails (grpc reports INTERNAL for a write on a finished call): the call's status is the
        # answer, whichever of the two came first.
        with contextlib.suppress(aio.AioRpcError):
            await call.write(detection_pb2.DetectionRequests(requests=[request]))
        assert await call.code() == grpc.StatusCode.UNAUTHENTICATED


async def test_server_logs_that_it_serves_loopback_only_without_credentials() -> None:
    server, _ = await start_server()
    try:
        assert any("security: none" in line and "serving this host only" in line for line in server.lines)
    finally:
        await server.stop()


async def test_rate_limit_and_continuous_cap_per_robot() -> None:
    limits = RequestLimits(rate_hz=0.001, burst=5, max_active=2)
    # five requests in all before the rate limit: three continuous ones and two single shots
    async with DrvsServer("127.0.0.1:0", limits=limits) as server, aio.insecure_channel(server.address) as channel:
        stub = detection_pb2_grpc.DetectObjectBoundaryStub(channel)

        def request(i: int, continuous: bool = False) -> detection_pb2.DetectionRequest:
            return detection_pb2.DetectionRequest(
                request_id=f"q{i}",
                filter_def=YELLOW,
                region=geometry_pb2.Region(box=geometry_pb2.Box(x_lower=0, y_lower=0, x_upper=1, y_upper=1)),
                callback_address="127.0.0.1:9",
                continuous=detection_pb2.ContinuousMode(rate_hz=1, duration_s=60) if continuous else None,
            )

        # No camera sees the region: nothing runs, so a continuous request holds no slot (the cap
        # itself, with a camera that takes the requests, is in tests/behaviour/test_exhaustion.py).
        for i in range(3):
            assert not (await stub.DetectObjects(request(i, continuous=True))).camera_ids
        assert limits.active("ipv4:127.0.0.1") == 0 and not limits._active
        for i in range(3, 5):
            await stub.DetectObjects(request(i))
        with pytest.raises(aio.AioRpcError) as err:
            await stub.DetectObjects(request(6))
        assert err.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        assert (err.value.details() or "").startswith("rate: more than")
        # Another robot (connection: a channel of its own, not sharing the first one's) has its own budget.
        async with aio.insecure_channel(server.address, options=[("grpc.use_local_subchannel_pool", 1)]) as other:
            await detection_pb2_grpc.DetectObjectBoundaryStub(other).DetectObjects(request(7))


def test_request_limits_refill_and_count_nothing_when_refusing() -> None:
    now = [0.0]
    limits = RequestLimits(rate_hz=10, burst=2, max_active=1, clock=lambda: now[0])
    limits.admit("a", 0)
    limits.admit("a", 0)
    with pytest.raises(ResourceExhausted, match="rate"):
        limits.admit("a", 0)
    now[0] = 0.1  # one token back
    limits.admit("a", 5.0)
    now[0] = 0.3
    with pytest.raises(ResourceExhausted, match="continuous"):
        limits.admit("a", 5.0)
    now[0] = 5.2  # the continuous request has ended
    limits.admit("a", 5.0)


def test_bad_security_settings_are_named(tmp_path: Path, certs: Path) -> None:
    with pytest.raises(InvalidArgument, match="tls_cert and tls_key: give both"):
        Security(tls_cert=certs / "server.pem")
    with pytest.raises(InvalidArgument, match="tls_ca: cannot read"):
        Security(tls_ca=tmp_path / "missing.pem")
    (tmp_path / "junk.pem").write_text("not a certificate")
    with pytest.raises(InvalidArgument, match=r"tls_ca: .* is not a PEM file"):
        Security(tls_ca=tmp_path / "junk.pem")
    with pytest.raises(InvalidArgument, match="require_client_cert: needs"):
        Security(require_client_cert=True)
    with pytest.raises(InvalidArgument, match="token: must be at least 16"):
        Security(token="short")
    for text, message in (
        ("lobby\n", "expected 'NAME TOKEN'"),
        ("lobby short\n", "shorter than 16"),
        (f"a {CAMERA_TOKEN}\nb {CAMERA_TOKEN}\n", "repeats the token of 'a'"),
        ("# nothing\n", "holds no tokens"),
    ):
        path = tmp_path / "tokens.txt"
        path.write_text(text)
        with pytest.raises(InvalidArgument, match=message):
            load_tokens(path, "--camera-tokens")


async def test_server_cli_refuses_a_bad_token_file(tmp_path: Path) -> None:
    (tmp_path / "robots.txt").write_text("turtle tooshort\n")
    proc = await ManagedProcess.entry_point(
        "server", "drvs-server", "--listen", "127.0.0.1:0", "--robot-tokens", str(tmp_path / "robots.txt")
    ).start()
    try:
        assert await proc.wait(timeout=30) == 2 and "Traceback" not in proc.output(), proc.output()
        assert proc.lines[-1].startswith("drvs-server: error: --robot-tokens: ") and "shorter than 16" in proc.lines[-1]
    finally:
        await proc.stop()


async def test_client_retries_while_the_server_is_unavailable() -> None:
    """Unavailable fails fast without retries; with them the client sends again once a server is up."""
    probe = DrvsServer("127.0.0.1:0")
    await probe.start()
    address = probe.address
    await probe.stop(0)
    async with DrvsClient(address, robot_id="r", listen="127.0.0.1:0") as client:
        with pytest.raises(Unavailable):
            await asyncio.wait_for(client.detect(YELLOW, CAM1_REGION, timeout_s=1), 5)
    async with DrvsClient(address, robot_id="r", listen="127.0.0.1:0", retry=RetryPolicy(31, 0.05)) as client:
        attempt = asyncio.ensure_future(client.detect(YELLOW, CAM1_REGION, timeout_s=1))
        async with DrvsServer(address):
            result = await asyncio.wait_for(attempt, 30)
        assert result.camera_ids == () and result.complete

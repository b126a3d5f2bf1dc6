"""Registration and identity under attack (issue 14), with real server and camera processes and a
hostile client built from the .proto files: nobody takes over a camera id, a re-registration never
inherits another's credential, ids lapse, non-loopback servers demand credentials, certificates say
their role, fields of view are bounded, identities are capped, ListCameras pages, and a camera
takes requests (and gives frames) only to whoever holds its secret."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import grpc
import pytest
from cryptography import x509
from cryptography.x509.oid import NameOID
from grpc import aio
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection_pb2, reflection_pb2_grpc

from drvs.robot import DrvsClient
from drvs.server import DrvsServer
from drvs.sim.scene import RecordedCamera
from drvs.tools import certs as drvs_certs
from drvs.tools.launch import ManagedProcess, start_camera, start_server
from drvs.v1 import (
    detection_pb2,
    detection_pb2_grpc,
    geometry_pb2,
    registry_pb2,
    registry_pb2_grpc,
    stream_pb2,
    stream_pb2_grpc,
)
from drvs.wire.convert import homography_from_pb
from drvs.wire.security import Security, bearer_token
from tests.fakes import server_process, start_recorded_camera
from tests.helpers import CAM1_REGION, MAX_RANGE, YELLOW, register_message, serving_detection

LOBBY_TOKEN = "lobby-token-0123456789abcdef"
YARD_TOKEN = "yard-token-fedcba9876543210"


def bearer(token: str) -> tuple[tuple[str, str], ...]:
    return (("authorization", f"Bearer {token}"),)


def at(message: registry_pb2.RegisterRequest, address: str, **fields: Any) -> registry_pb2.RegisterRequest:
    message.address = address
    for key, value in fields.items():
        setattr(message, key, value)
    return message


async def refused(call: Any, code: grpc.StatusCode) -> str:
    """Await a call that must fail with `code`; its details."""
    with pytest.raises(aio.AioRpcError) as err:
        await call
    assert err.value.code() == code, (err.value.code(), err.value.details())
    return err.value.details() or ""


def cam1_request(request_id: str) -> detection_pb2.DetectionRequest:
    box = geometry_pb2.Box(x_lower=-1, y_lower=0, x_upper=1, y_upper=5)
    return detection_pb2.DetectionRequest(
        request_id=request_id, filter_def=YELLOW, region=geometry_pb2.Region(box=box), callback_address="127.0.0.1:9"
    )


class Recorder(detection_pb2_grpc.DetectObjectBoundaryServicer):
    """A would-be camera: accepts every forward and remembers who sent it with which credential."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, str]] = []  # (request id, bearer token presented)
        self.changed = asyncio.Event()

    def _take(self, message: detection_pb2.DetectionRequest, context: aio.ServicerContext[Any, Any]) -> Any:
        self.calls.append((message.request_id, bearer_token(list(context.invocation_metadata() or ()))))
        self.changed.set()
        return detection_pb2.DetectionReply(request_id=message.request_id, camera_ids=["x"])

    async def DetectObjects(self, message: Any, context: aio.ServicerContext[Any, Any]) -> Any:
        return self._take(message, context)

    async def DetectBatches(self, request_iterator: Any, context: aio.ServicerContext[Any, Any]) -> Any:
        async for batch in request_iterator:
            yield detection_pb2.DetectionReplies(replies=[self._take(m, context) for m in batch.requests])

    async def wait_for(self, request_id: str) -> str:
        """The token the call for `request_id` presented."""
        while True:
            for rid, token in self.calls:
                if rid == request_id:
                    return token
            self.changed.clear()
            await asyncio.wait_for(self.changed.wait(), 10)


@asynccontextmanager
async def recorder() -> AsyncIterator[tuple[Recorder, str]]:
    servicer = Recorder()
    async with serving_detection(servicer) as address:
        yield servicer, address


async def batch(
    stub: detection_pb2_grpc.DetectObjectBoundaryStub,
    request: detection_pb2.DetectionRequest,
    metadata: tuple[tuple[str, str], ...] = (),
) -> detection_pb2.DetectionReplies:
    """Send one request to a camera as its server does (DetectBatches); the camera's replies."""
    call = stub.DetectBatches(metadata=metadata)
    try:
        try:
            await call.write(detection_pb2.DetectionRequests(requests=[request]))
        except aio.AioRpcError as exc:
            if exc.code() != grpc.StatusCode.INTERNAL:
                raise
            # The camera refused the call's credentials before the request went out, and gRPC turns
            # the failed write into INTERNAL, losing the camera's status (CI saw this race once). A
            # refusal comes with the call's headers, so a call that sends nothing shows it.
            again = stub.DetectBatches(metadata=metadata)
            try:
                refusal: detection_pb2.DetectionReplies = await asyncio.wait_for(again.read(), 10)
                return refusal
            finally:
                again.cancel()
        replies: detection_pb2.DetectionReplies = await call.read()
        return replies
    finally:
        call.cancel()


def camera_address(camera: ManagedProcess) -> str:
    line = next(line for line in camera.lines if "listening on" in line)
    return line.split("listening on ")[1].split()[0]


async def tokens_server(tmp_path: Path, *args: str) -> tuple[ManagedProcess, str]:
    (tmp_path / "cameras.txt").write_text(f"lobby {LOBBY_TOKEN}\nyard {YARD_TOKEN}\n")
    (tmp_path / "lobby.token").write_text(LOBBY_TOKEN)
    return await start_server("--camera-tokens", str(tmp_path / "cameras.txt"), *args)


# --- a camera id belongs to its registration ------------------------------------------------------


@pytest.mark.slow
async def test_a_second_client_cannot_take_over_a_live_anonymous_camera_id(
    recorded: dict[str, RecordedCamera],
) -> None:
    """Without credentials, a hostile client re-registers `cam1` at its own address and renews and
    deregisters it by id: every call is refused, the real camera keeps heartbeating and serving,
    and no request ever reaches the hijacker."""
    server, address = await start_server("--lease-ttl", "1.5")
    camera: ManagedProcess | None = None
    try:
        rec = recorded["cam1"]
        camera = await start_camera("cam1", rec.video, rec.homography_file, address, "--max-range", MAX_RANGE)
        async with recorder() as (hijacker, hijack_address), aio.insecure_channel(address) as channel:
            registry = registry_pb2_grpc.RegisterVisionServiceStub(channel)
            details = await refused(
                registry.Register(at(register_message("cam1"), hijack_address)), grpc.StatusCode.PERMISSION_DENIED
            )
            assert details.startswith("camera_id: 'cam1' belongs to another credential") and "until" in details
            for secret in ("", "guessed-secret"):
                await refused(
                    registry.Heartbeat(registry_pb2.HeartbeatRequest(camera_id="cam1", registration_secret=secret)),
                    grpc.StatusCode.FAILED_PRECONDITION,
                )
                await refused(
                    registry.Deregister(registry_pb2.DeregisterRequest(camera_id="cam1", registration_secret=secret)),
                    grpc.StatusCode.FAILED_PRECONDITION,
                )
            # For more than two leases the real camera's heartbeats hold the id and it answers every
            # request: it never left routing, and the hijacker hears nothing.
            loop = asyncio.get_running_loop()
            end = loop.time() + 3.5
            async with DrvsClient(address, robot_id="r", listen="127.0.0.1:0") as robot:
                while loop.time() < end:
                    result = await robot.detect(YELLOW, CAM1_REGION, timeout_s=10)
                    assert result.camera_ids == ("cam1",) and result.complete and len(result.detections) == 2
                    await asyncio.sleep(0.1)  # a robot's pace, well inside the server's rate limit
                listed = await robot.cameras()
            assert [(c.camera_id, c.address) for c in listed] == [("cam1", camera_address(camera))]
            assert hijacker.calls == []
            assert not any("registering again" in line or "CONFLICT" in line for line in camera.lines)
    finally:
        if camera is not None:
            await camera.stop()
        await server.stop()


async def test_a_reregistration_never_inherits_the_previous_registrations_token() -> None:
    """A camera registered with a token, then re-registered (with its secret) without one at another
    address: the server must not present the old token to the new address."""
    server, address = await start_server()
    try:
        async with (
            recorder() as (first, first_address),
            recorder() as (second, second_address),
            aio.insecure_channel(address) as channel,
        ):
            registry = registry_pb2_grpc.RegisterVisionServiceStub(channel)
            robot = detection_pb2_grpc.DetectObjectBoundaryStub(channel)
            reply = await registry.Register(at(register_message("lobby"), first_address), metadata=bearer(LOBBY_TOKEN))
            await robot.DetectObjects(cam1_request("q1"))
            assert await first.wait_for("q1") == LOBBY_TOKEN  # presented back to the address that had it
            again = at(register_message("lobby"), second_address, registration_secret=reply.registration_secret)
            await registry.Register(again)
            await robot.DetectObjects(cam1_request("q2"))
            assert await second.wait_for("q2") == ""
        assert all(token != LOBBY_TOKEN for _, token in second.calls)
    finally:
        await server.stop()


@pytest.mark.slow
async def test_a_stale_registration_secret_is_refused_and_the_camera_registers_again(
    tmp_path: Path, recorded: dict[str, RecordedCamera]
) -> None:
    """The same credential registering the id again replaces the registration (a new secret): the
    old secret's heartbeats are refused with FAILED_PRECONDITION, and the real camera, told so,
    registers again instead of heartbeating a registration that is no longer its own."""
    server, address = await tokens_server(tmp_path, "--lease-ttl", "1.5")
    camera: ManagedProcess | None = None
    try:
        camera = await start_recorded_camera(
            "cam1", recorded["cam1"], address, "--token-file", str(tmp_path / "lobby.token")
        )
        async with aio.insecure_channel(address) as channel:
            registry = registry_pb2_grpc.RegisterVisionServiceStub(channel)
            first = await registry.Register(
                at(register_message("lobby-2"), "127.0.0.1:9"), metadata=bearer(LOBBY_TOKEN)
            )
            second = await registry.Register(
                at(register_message("lobby-2"), "127.0.0.1:9"), metadata=bearer(LOBBY_TOKEN)
            )
            assert first.registration_secret != second.registration_secret
            stale = registry_pb2.HeartbeatRequest(camera_id="lobby-2", registration_secret=first.registration_secret)
            details = await refused(
                registry.Heartbeat(stale, metadata=bearer(LOBBY_TOKEN)), grpc.StatusCode.FAILED_PRECONDITION
            )
            assert details.startswith("registration_secret: not the current one for camera_id 'lobby-2'")
            current = registry_pb2.HeartbeatRequest(camera_id="lobby-2", registration_secret=second.registration_secret)
            await registry.Heartbeat(current, metadata=bearer(LOBBY_TOKEN))
            # The same against the running camera: its registration is replaced under it.
            mark = len(camera.lines)
            await registry.Register(at(register_message("cam1"), camera_address(camera)), metadata=bearer(LOBBY_TOKEN))
        await camera.wait_for_line(r"camera cam1: the server says another registration replaced ours", 10, mark)
        await camera.wait_for_line(r"camera cam1 re-registered with", 10, mark)
    finally:
        if camera is not None:
            await camera.stop()
        await server.stop()


@pytest.mark.slow
async def test_a_squatted_id_lapses_with_its_lease_and_grace_and_the_camera_says_why(
    tmp_path: Path, recorded: dict[str, RecordedCamera]
) -> None:
    """Another credential holds `cam1`: the real camera logs the conflict (which id, another
    credential, until when) and keeps retrying; once the squatter stops renewing, the id lapses
    with its lease and grace, and the camera gets it."""
    server, address = await tokens_server(tmp_path, "--lease-ttl", "1", "--registration-grace", "1")
    rec = recorded["cam1"]
    camera = ManagedProcess.entry_point(
        "cam1", "drvs-camera", "--id", "cam1", "--source", str(rec.video), "--homography", str(rec.homography_file),
        "--server", address, "--listen", "127.0.0.1:0", "--max-range", MAX_RANGE,
        "--token-file", str(tmp_path / "lobby.token"),
    )  # fmt: skip
    squatting: asyncio.Task[None] | None = None
    try:
        async with aio.insecure_channel(address) as channel:
            registry = registry_pb2_grpc.RegisterVisionServiceStub(channel)
            held = await registry.Register(at(register_message("cam1"), "127.0.0.1:9"), metadata=bearer(YARD_TOKEN))

            async def squat() -> None:
                beat = registry_pb2.HeartbeatRequest(camera_id="cam1", registration_secret=held.registration_secret)
                while True:
                    await registry.Heartbeat(beat, metadata=bearer(YARD_TOKEN))
                    await asyncio.sleep(0.3)  # the squatter's own pace, inside its 1 s lease

            squatting = asyncio.get_running_loop().create_task(squat())
            await camera.start()
            conflict = (
                r"camera cam1: CONFLICT: the server gives camera id cam1 to another registration: PERMISSION_DENIED "
                r"camera_id: 'cam1' belongs to another credential until \d\d:\d\d:\d\d UTC \(\d+ s from now\)"
            )
            await camera.wait_for_line(conflict, 30)
            assert not any("camera cam1 registered with" in line for line in camera.lines)
            squatting.cancel()
            await asyncio.gather(squatting, return_exceptions=True)
        await camera.wait_for_line(r"camera cam1 registered with", 15)
        await server.wait_for_line(r"camera cam1 registered at 127\.0\.0\.1:\d+ by token:lobby", 5)
    finally:
        if squatting is not None:
            squatting.cancel()
            await asyncio.gather(squatting, return_exceptions=True)
        await camera.stop()
        await server.stop()


# --- who may register ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def role_certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("role-certs")
    assert drvs_certs.main(["--out", str(out), "--role", "server", "--role", "robot",
                            "--camera", "lobby", "--camera", "hall-1"]) == 0  # fmt: skip
    return out


def cert_security(certs: Path, stem: str, client_auth: bool = True) -> Security:
    return Security(
        tls_cert=certs / f"{stem}.pem",
        tls_key=certs / f"{stem}-key.pem",
        tls_ca=certs / "ca.pem",
        require_client_cert=client_auth,
    )


def server_tls(certs: Path, client_auth: bool = True) -> list[str]:
    args = ["--tls-cert", str(certs / "server.pem"), "--tls-key", str(certs / "server-key.pem"),
            "--tls-ca", str(certs / "ca.pem")]  # fmt: skip
    return [*args, "--tls-client-auth"] if client_auth else args


def test_drvs_certs_issues_one_certificate_per_camera_that_says_its_role(role_certs: Path) -> None:
    for stem, name, role in (("camera-lobby", "lobby", "camera"), ("camera-hall-1", "hall-1", "camera"),
                             ("robot", "robot", "robot"), ("server", "server", "server")):  # fmt: skip
        cert = x509.load_pem_x509_certificate((role_certs / f"{stem}.pem").read_bytes())
        assert [a.value for a in cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)] == [name]
        assert [a.value for a in cert.subject.get_attributes_for_oid(NameOID.ORGANIZATIONAL_UNIT_NAME)] == [role]


async def test_under_mutual_tls_only_camera_certificates_register_and_each_camera_is_its_own_identity(
    role_certs: Path,
) -> None:
    server, address = await start_server(*server_tls(role_certs))
    try:
        channels = {stem: cert_security(role_certs, stem).channel(address)
                    for stem in ("robot", "camera-lobby", "camera-hall-1")}  # fmt: skip
        try:
            stubs = {stem: registry_pb2_grpc.RegisterVisionServiceStub(ch) for stem, ch in channels.items()}
            details = await refused(
                stubs["robot"].Register(register_message("lobby")), grpc.StatusCode.PERMISSION_DENIED
            )
            assert details.startswith("Register: the client certificate 'robot' has the role robot")
            await stubs["camera-lobby"].Register(register_message("lobby"))
            details = await refused(
                stubs["camera-hall-1"].Register(register_message("lobby")), grpc.StatusCode.PERMISSION_DENIED
            )
            assert details.startswith("camera_id: 'lobby' belongs to another credential")
            await stubs["camera-hall-1"].Register(register_message("hall-1", x=20))
        finally:
            for ch in channels.values():
                await ch.close()
        await server.wait_for_line(r"camera lobby registered at \S+ by cert:lobby", 5)
        await server.wait_for_line(r"camera hall-1 registered at \S+ by cert:hall-1", 5)
    finally:
        await server.stop()


@pytest.mark.slow
async def test_beyond_loopback_registration_needs_a_credential_unless_the_network_is_trusted(
    role_certs: Path,
) -> None:
    """A server on 0.0.0.0 without camera credentials refuses anonymous cameras (and says so at
    start); TLS without client authentication proves nobody; --trust-network opens it, and says so."""
    cases: list[tuple[list[str], Security, grpc.StatusCode | None, str]] = [
        ([], Security(), grpc.StatusCode.UNAUTHENTICATED, "registration: REFUSED"),
        (server_tls(role_certs, client_auth=False), cert_security(role_certs, "camera-lobby", client_auth=False),
         grpc.StatusCode.UNAUTHENTICATED, "registration: REFUSED"),
        (server_tls(role_certs), cert_security(role_certs, "camera-lobby"), None,
         "registration: cameras need a client certificate with the camera role"),
        (["--trust-network"], Security(), None, "registration: open to cameras without a credential (--trust-network)"),
    ]  # fmt: skip
    for args, security, code, logged in cases:
        server, address = await start_server("--listen", "0.0.0.0:0", *args)
        try:
            assert any(logged in line for line in server.lines), (logged, server.lines)
            async with security.channel(address.replace("0.0.0.0", "127.0.0.1")) as channel:
                call = registry_pb2_grpc.RegisterVisionServiceStub(channel).Register(register_message("lobby"))
                if code is None:
                    await call
                else:
                    details = await refused(call, code)
                    assert "needs a camera token or a client certificate with the camera role" in details
                    assert "--trust-network" in details
        finally:
            await server.stop()


# --- bounds on what one registration or identity may claim --------------------------------------


async def test_a_field_of_view_beyond_the_servers_range_or_area_is_refused_naming_the_field() -> None:
    async with server_process("--max-fov-range", "20", "--max-fov-area", "40") as address:
        async with aio.insecure_channel(address) as channel:
            registry = registry_pb2_grpc.RegisterVisionServiceStub(channel)
            details = await refused(
                registry.Register(at(register_message("far"), "127.0.0.1:9", max_range_m=30)),
                grpc.StatusCode.INVALID_ARGUMENT,
            )
            assert details == "max_range_m: 30 m is beyond this server's limit of 20 m"
            details = await refused(
                registry.Register(at(register_message("wide"), "127.0.0.1:9", max_range_m=15)),
                grpc.StatusCode.INVALID_ARGUMENT,
            )
            assert details == "field_of_view: 63 m² of floor is more than this server's limit of 40 m² for one camera"
            await registry.Register(at(register_message("fits"), "127.0.0.1:9", max_range_m=6))
        async with DrvsClient(address, robot_id="r", listen="127.0.0.1:0") as robot:
            assert [c.camera_id for c in await robot.cameras()] == ["fits"]
    # The defaults are sized for a building: 100 m.
    async with DrvsServer("127.0.0.1:0") as default, aio.insecure_channel(default.address) as channel:
        details = await refused(
            registry_pb2_grpc.RegisterVisionServiceStub(channel).Register(
                at(register_message("far"), "127.0.0.1:9", max_range_m=150)
            ),
            grpc.StatusCode.INVALID_ARGUMENT,
        )
        assert details.startswith("max_range_m: 150 m is beyond this server's limit of 100 m")


async def test_one_identity_holds_at_most_the_configured_number_of_camera_ids(tmp_path: Path) -> None:
    server, address = await tokens_server(tmp_path, "--max-cameras-per-identity", "2")
    try:
        async with aio.insecure_channel(address) as channel:
            registry = registry_pb2_grpc.RegisterVisionServiceStub(channel)
            a = await registry.Register(register_message("a"), metadata=bearer(LOBBY_TOKEN))
            await registry.Register(register_message("b"), metadata=bearer(LOBBY_TOKEN))
            details = await refused(
                registry.Register(register_message("c"), metadata=bearer(LOBBY_TOKEN)),
                grpc.StatusCode.RESOURCE_EXHAUSTED,
            )
            assert details == (
                "registrations: token:lobby already holds 2 camera ids "
                "(limit 2 per identity, --max-cameras-per-identity)"
            )
            await registry.Register(register_message("a"), metadata=bearer(LOBBY_TOKEN))  # its own: replaced
            await registry.Register(register_message("c"), metadata=bearer(YARD_TOKEN))  # another identity
            # Deregistering frees a place.
            renewed = await registry.Register(register_message("a"), metadata=bearer(LOBBY_TOKEN))
            assert renewed.registration_secret != a.registration_secret
            await registry.Deregister(
                registry_pb2.DeregisterRequest(camera_id="a", registration_secret=renewed.registration_secret),
                metadata=bearer(LOBBY_TOKEN),
            )
            await registry.Register(register_message("d"), metadata=bearer(LOBBY_TOKEN))
    finally:
        await server.stop()


@pytest.mark.slow
async def test_list_cameras_pages_past_the_message_limit_and_clients_follow_the_pages() -> None:
    """4 500 cameras with long ids and addresses list as about 4.5 MB, past the 4 MB message limit:
    the server answers in pages, and DrvsClient.cameras and `drvs-robot cameras` follow them."""
    count = 4500
    host = ".".join(["h" * 60] * 4)
    async with DrvsServer("127.0.0.1:0", lease_ttl_s=600) as server:
        homography = homography_from_pb(register_message().homography)
        ids = [f"cam-{i:05d}-" + "x" * 110 for i in range(count)]
        for i, camera_id in enumerate(ids):
            server.registry.register(camera_id, f"{host}:{1000 + i}", homography, (640, 480), {"hsv"}, 6.0)
        async with aio.insecure_channel(server.address) as channel:
            first = await registry_pb2_grpc.RegisterVisionServiceStub(channel).ListCameras(
                registry_pb2.ListCamerasRequest()
            )
        assert len(first.cameras) == 500 and first.next_page_token == ids[499]
        async with DrvsClient(server.address, robot_id="r", listen="127.0.0.1:0") as robot:
            assert [c.camera_id for c in await robot.cameras()] == ids
        cli = await ManagedProcess.entry_point(
            "robot", "drvs-robot", "cameras", "--server", server.address, "--json"
        ).start()
        try:
            assert await cli.wait(timeout=60) == 0, cli.output()[-2000:]
        finally:
            await cli.stop()
        assert sum(1 for line in cli.lines if line.startswith('{"camera_id": "cam-')) == count


# --- a camera serves only its server --------------------------------------------------------------


@pytest.mark.slow
async def test_a_camera_without_credentials_takes_requests_and_gives_frames_only_with_its_secret(
    tmp_path: Path, recorded: dict[str, RecordedCamera]
) -> None:
    """No token anywhere: the camera still refuses a stranger who dials it directly (its server
    presents the secret the camera gave it at registration), and --serve-frames streams frames only
    to whoever presents the camera's token."""
    server, address = await start_server()
    procs = [server]
    try:
        rec = recorded["cam1"]
        plain = await start_camera("cam1", rec.video, rec.homography_file, address, "--max-range", MAX_RANGE)
        procs.append(plain)
        (tmp_path / "frames.token").write_text(LOBBY_TOKEN)
        framing = await start_camera(
            "cam2", recorded["cam2"].video, recorded["cam2"].homography_file, address, "--max-range", MAX_RANGE,
            "--serve-frames", "--token-file", str(tmp_path / "frames.token"),
        )  # fmt: skip
        procs.append(framing)
        async with aio.insecure_channel(camera_address(plain)) as channel:
            stub = detection_pb2_grpc.DetectObjectBoundaryStub(channel)
            for metadata in ((), bearer("not-the-secret-0123456789")):
                details = await refused(batch(stub, cam1_request("direct"), metadata), grpc.StatusCode.UNAUTHENTICATED)
                assert "need the secret this camera gave its server" in details
        async with aio.insecure_channel(camera_address(framing)) as channel:
            frames = stream_pb2_grpc.FrameStreamStub(channel)
            ask = stream_pb2.StreamFramesRequest(encoding=stream_pb2.FRAME_ENCODING_JPEG)
            call = frames.StreamFrames(ask)
            await refused(call.read(), grpc.StatusCode.UNAUTHENTICATED)
            call = frames.StreamFrames(ask, metadata=bearer(LOBBY_TOKEN))
            frame = await asyncio.wait_for(call.read(), 10)
            assert frame.camera_id == "cam2" and frame.data
            call.cancel()
        # Through the server, requests reach it.
        async with DrvsClient(address, robot_id="r", listen="127.0.0.1:0") as robot:
            result = await robot.detect(YELLOW, CAM1_REGION, timeout_s=10)
            assert result.camera_ids == ("cam1",) and result.complete and len(result.detections) == 2
    finally:
        for proc in reversed(procs):
            await proc.stop()


async def test_a_camera_serves_its_server_only_detect_batches(
    recorded: dict[str, RecordedCamera], tmp_path: Path
) -> None:
    """The server forwards to cameras only on DetectBatches; the robot-facing DetectObjects and
    DetectStream of the shared service are not served by a camera (UNIMPLEMENTED), even to a caller
    that holds the camera's own token, to whom DetectBatches answers."""
    server, address = await start_server()
    procs = [server]
    try:
        (tmp_path / "cam.token").write_text(LOBBY_TOKEN)
        rec = recorded["cam1"]
        camera = await start_camera(
            "cam1", rec.video, rec.homography_file, address, "--max-range", MAX_RANGE,
            "--token-file", str(tmp_path / "cam.token"),
        )  # fmt: skip
        procs.append(camera)
        async with aio.insecure_channel(camera_address(camera)) as channel:
            stub = detection_pb2_grpc.DetectObjectBoundaryStub(channel)
            for metadata in ((), bearer(LOBBY_TOKEN)):
                details = await refused(
                    stub.DetectObjects(cam1_request("one"), metadata=metadata), grpc.StatusCode.UNIMPLEMENTED
                )
                assert details.startswith("DetectObjects: a camera takes requests only from the server"), details
                stream = stub.DetectStream(metadata=metadata)
                details = await refused(stream.read(), grpc.StatusCode.UNIMPLEMENTED)
                assert details.startswith("DetectStream: a camera takes requests only from the server"), details
            replies = await batch(stub, cam1_request("batched"), bearer(LOBBY_TOKEN))
            [reply] = replies.replies
            assert reply.request_id == "batched" and list(reply.camera_ids) == ["cam1"], reply
            # Health and reflection stay open to probes (grpc_health_probe, grpcurl list), and list
            # what a camera serves: no FrameStream without --serve-frames.
            health = await health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(service=""))
            assert health.status == health_pb2.HealthCheckResponse.SERVING
            listing = reflection_pb2_grpc.ServerReflectionStub(channel).ServerReflectionInfo()
            await listing.write(reflection_pb2.ServerReflectionRequest(list_services=""))
            answer = await listing.read()
            listing.cancel()
            names = {s.name for s in answer.list_services_response.service}
            assert names == {
                "drvs.v1.DetectObjectBoundary",
                "grpc.health.v1.Health",
                "grpc.reflection.v1alpha.ServerReflection",
            }, names
    finally:
        for proc in reversed(procs):
            await proc.stop()

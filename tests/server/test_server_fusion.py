"""Fused delivery in the server, with real processes: a drvs-server and drvs-camera processes whose
footage shows the same floor from two overlapping viewpoints, and a robot that is nothing but a raw
gRPC stub on DetectStream (no listener, no callback address). The cameras report to the server,
which merges what both see of one object, tracks it across a continuous request's periods, and
answers on the robot's own stream; hostile callers of its report service get nothing in."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import math
import secrets
import signal
import time
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import grpc
import pytest
import pytest_asyncio
from grpc import aio

from drvs.camera.node import CameraNode
from drvs.camera.source import VideoSource
from drvs.core.errors import FailedPrecondition
from drvs.core.filters import HsvRange
from drvs.core.geometry import box_region
from drvs.core.model import DetectionRequest
from drvs.server import DrvsServer
from drvs.server import servicers as servicers_module
from drvs.sim.scene import FloorPatch, RecordedCamera
from drvs.tools.certs import make_all
from drvs.tools.launch import ManagedProcess, start_server
from drvs.v1 import detection_pb2, detection_pb2_grpc, geometry_pb2, registry_pb2_grpc
from drvs.wire.convert import snapshot_from_pb
from drvs.wire.report_auth import KEY_BYTES
from tests.fakes import serve_camera, start_recorded_camera
from tests.helpers import (
    YELLOW,
    CapturingCamera,
    Scene,
    metrics_at_least,
    metrics_port,
    poll,
    record_facing,
    register_message,
    scrape,
    wait_until,
)

#: Two cameras 3 m apart, both 3 m up looking along +y: at y = 4.5 "left" sees x -4.6..1.6 and
#: "right" x -1.6..4.6. SHARED lies where both see it, LONE where only left does.
POSES = {"left": (-1.5, 0.0, 3.0), "right": (1.5, 0.0, 3.0)}
SHARED = (0.0, 4.5)
LONE = (-3.2, 4.0)
REGION = (-4.5, 2.0, 4.5, 6.5)
#: Seen by left alone: right's field of view starts at x -2.3.
LEFT_ONLY = (-4.5, 2.0, -2.5, 6.0)
CAMERA_TOKEN = "camera-token-0123456789abcdef"
ROBOT_TOKEN = "robot-token-0123456789abcdef"


@pytest.fixture(scope="module")
def overlap(tmp_path_factory: pytest.TempPathFactory) -> dict[str, RecordedCamera]:
    yellow = HsvRange.parse(YELLOW).centre_bgr()
    patches = [FloorPatch.disc(SHARED, 0.3, yellow), FloorPatch.disc(LONE, 0.25, yellow)]
    directory = tmp_path_factory.mktemp("overlap")
    return record_facing(directory, POSES, patches)


@contextlib.asynccontextmanager
async def scene(
    overlap: dict[str, RecordedCamera],
    server_args: tuple[str, ...] = (),
    camera_args: tuple[str, ...] = (),
    env: dict[str, str] | None = None,
) -> AsyncIterator[Scene]:
    """The server and both cameras as processes; all stopped and reaped on exit (a camera the test
    stopped with SIGSTOP is continued first)."""
    server, address = await start_server("--lease-ttl", "5", "--metrics-port", "0", *server_args, env=env)
    running = Scene(server, address, {})
    try:
        for camera_id in POSES:
            running.cameras[camera_id] = await start_recorded_camera(
                camera_id, overlap[camera_id], address, *camera_args, env=env
            )
        yield running
    finally:
        for proc in running.cameras.values():
            if proc.returncode is None:
                with contextlib.suppress(ProcessLookupError):
                    proc.process.send_signal(signal.SIGCONT)  # type: ignore[union-attr]
            await proc.stop()
        await server.stop()


@pytest_asyncio.fixture
async def office(overlap: dict[str, RecordedCamera]) -> AsyncIterator[Scene]:
    async with scene(overlap) as running:
        yield running


def box(region: tuple[float, float, float, float]) -> geometry_pb2.Region:
    x0, y0, x1, y1 = region
    return geometry_pb2.Region(box=geometry_pb2.Box(x_lower=x0, y_lower=y0, x_upper=x1, y_upper=y1))


def fused(
    request_id: str,
    region: tuple[float, float, float, float] = REGION,
    *,
    rate_hz: float = 0.0,
    duration_s: float = 0.0,
    deadline_s: float = 0.0,
    drop_after_s: float = 0.0,
) -> detection_pb2.DetectionRequest:
    """A fused request as a robot without a listener sends it: no callback address."""
    return detection_pb2.DetectionRequest(
        request_id=request_id,
        robot_id="r",
        filter_def=YELLOW,
        region=box(region),
        continuous=detection_pb2.ContinuousMode(rate_hz=rate_hz, duration_s=duration_s),
        fusion=detection_pb2.FusionOptions(deadline_s=deadline_s, drop_after_s=drop_after_s),
    )


async def read(call: Any, timeout: float = 20.0) -> detection_pb2.DetectionReply:
    reply = await asyncio.wait_for(call.read(), timeout)
    assert reply is not aio.EOF, "the stream ended"
    assert not reply.HasField("error"), reply.error
    return reply  # type: ignore[no-any-return]


async def snapshots(call: Any, request_id: str) -> list[detection_pb2.WorldSnapshot]:
    """Every snapshot of `request_id` on the stream until its final one."""
    out = []
    while True:
        reply = await read(call)
        assert reply.request_id == request_id and reply.HasField("snapshot"), reply
        out.append(reply.snapshot)
        if reply.snapshot.final:
            return out


def cameras_of(snapshot: detection_pb2.WorldSnapshot, obj: detection_pb2.WorldObject) -> list[str]:
    """The cameras a fused object names: by index into its snapshot's cameras (an older server: by name)."""
    return list(obj.camera_ids) or [snapshot.camera_ids[i] for i in obj.camera_index]


def near(
    snapshot: detection_pb2.WorldSnapshot, xy: tuple[float, float], within: float = 0.25
) -> list[detection_pb2.WorldObject]:
    """The snapshot's objects whose centroid (as a robot reads it) lies within `within` of `xy`."""
    read = snapshot_from_pb(snapshot).objects
    return [pb for pb, o in zip(snapshot.objects, read, strict=True) if math.dist(o.centroid_xy, xy) < within]


def missing(snapshot: detection_pb2.WorldSnapshot) -> dict[str, str]:
    return {m.camera_id: m.code for m in snapshot.missing_cameras}


@contextlib.contextmanager
def stopped(proc: ManagedProcess) -> Iterator[None]:
    """The process frozen (SIGSTOP): it neither answers nor reports, and its sockets stay open."""
    assert proc.process is not None
    proc.process.send_signal(signal.SIGSTOP)
    try:
        yield
    finally:
        proc.process.send_signal(signal.SIGCONT)


@pytest.mark.slow
async def test_two_overlapping_cameras_seeing_one_box_give_one_object(office: Scene) -> None:
    """A fused single shot: one reply naming both cameras, whose snapshot holds ONE object for the
    disc both cameras see (with both camera ids) and one for the disc only left sees. The same on
    DetectObjects. The robot sent no callback address and listens nowhere."""
    async with aio.insecure_channel(office.address) as channel:
        stub = detection_pb2_grpc.DetectObjectBoundaryStub(channel)
        call = stub.DetectStream()
        await call.write(fused("one"))
        reply = await read(call)
        unary = await stub.DetectObjects(fused("two"), timeout=20)
        bare = fused("three")
        bare.omit_outlines = True
        lean = await stub.DetectObjects(bare, timeout=20)
        current = fused("four")
        current.fusion.compact_geometry = True  # as a DrvsClient asks
        compact = await stub.DetectObjects(current, timeout=20)
        call.cancel()
    # A robot that did not say it reads millimetre integers (an older one) gets the three messages
    # of floats it reads; one that did gets geometry_mm, the same places: within 1 cm, since the two
    # single shots read different frames (a centroid moves by a few mm between frames; the rounding
    # to millimetres is checked exactly in tests/wire/test_convert.py).
    assert all(o.HasField("centroid") and not o.geometry_mm for o in unary.snapshot.objects)
    assert all(len(o.geometry_mm) == 8 and not o.HasField("centroid") for o in compact.snapshot.objects)
    for xy in (SHARED, LONE):
        [old], [new] = near(unary.snapshot, xy), near(compact.snapshot, xy)
        assert math.dist((old.centroid.x, old.centroid.y), [v / 1000 for v in new.geometry_mm[:2]]) < 0.01
    # A robot that asks for no outlines gets none, and the same two objects.
    assert len(lean.snapshot.objects) == 2 and all(not o.outline_xy for o in lean.snapshot.objects)
    for answer in (reply, unary):
        assert sorted(answer.camera_ids) == ["left", "right"]
        snapshot = answer.snapshot
        assert answer.HasField("snapshot") and snapshot.final and snapshot.sequence == 0
        assert sorted(snapshot.camera_ids) == ["left", "right"] and not snapshot.missing_cameras
        assert len(snapshot.objects) == 2, snapshot.objects
        [shared] = near(snapshot, SHARED)
        assert sorted(cameras_of(snapshot, shared)) == ["left", "right"]
        [lone] = near(snapshot, LONE)
        assert cameras_of(snapshot, lone) == ["left"]
        assert len(shared.outline_xy) >= 6
        # When each object was last seen travels as its age before the snapshot's time.
        assert all(0 < o.last_seen <= snapshot_from_pb(snapshot).time for o in snapshot_from_pb(snapshot).objects)


@pytest.mark.slow
async def test_continuous_fused_request_tracks_at_its_rate_and_ends_final(office: Scene) -> None:
    """5 Hz for 2 s: the first reply at once without a snapshot, then 11 snapshots (one per report
    time) about 0.2 s apart, numbered 0..10, the last final, each with both objects under the same
    track ids throughout."""
    async with aio.insecure_channel(office.address) as channel:
        call = detection_pb2_grpc.DetectObjectBoundaryStub(channel).DetectStream()
        await call.write(fused("track", rate_hz=5, duration_s=2))
        first = await read(call)
        assert first.request_id == "track" and not first.HasField("snapshot")
        assert sorted(first.camera_ids) == ["left", "right"]
        shots = await snapshots(call, "track")
        call.cancel()
    assert [s.sequence for s in shots] == list(range(11))
    assert [s.final for s in shots] == [False] * 10 + [True]
    times = [s.time.ToNanoseconds() / 1e9 for s in shots]
    gaps = sorted(b - a for a, b in itertools.pairwise(times))
    assert 0.1 < gaps[len(gaps) // 2] < 0.3, gaps  # the median period: the rate asked for
    ids = []
    for s in shots[1:]:  # the first period may come before both cameras' first look
        [shared] = near(s, SHARED)
        [lone] = near(s, LONE)
        assert len(s.objects) == 2 and shared.track_id != lone.track_id
        ids.append((shared.track_id, lone.track_id))
    assert len(set(ids)) == 1, ids  # stable track ids


@pytest.mark.slow
async def test_a_camera_killed_mid_request_is_missing_and_holds_back_nobody(office: Scene) -> None:
    """Right is killed during a continuous request: the snapshots go on at the rate with left's
    objects, and name right as missing (DEADLINE_EXCEEDED) once it has been silent beyond the
    deadline grace; the request still ends with its final snapshot on time."""
    async with aio.insecure_channel(office.address) as channel:
        call = detection_pb2_grpc.DetectObjectBoundaryStub(channel).DetectStream()
        await call.write(fused("kill", rate_hz=5, duration_s=3, deadline_s=0.2))
        await read(call)
        before = [(await read(call)).snapshot for _ in range(4)]
        office.cameras["right"].kill()
        after = await snapshots(call, "kill")
        call.cancel()
    assert all(not s.missing_cameras for s in before[1:])
    assert len(before) + len(after) == 16 and after[-1].final
    # Silent for more than a period (0.2 s) and the grace (0.2 s): missing from then on.
    assert [missing(s) for s in after[-5:]] == [{"right": "DEADLINE_EXCEEDED"}] * 5
    for s in after[-5:]:
        assert list(s.camera_ids) == ["left"] and near(s, LONE)
        [shared] = near(s, SHARED)
        assert cameras_of(s, shared) == ["left"]


@pytest.mark.slow
async def test_a_frozen_camera_does_not_hold_a_single_shot_beyond_its_deadline(
    overlap: dict[str, RecordedCamera],
) -> None:
    """Right is frozen (SIGSTOP): a fused single shot with a 1 s deadline answers with left's
    objects and names right missing (DEADLINE_EXCEEDED), long before right's forward would time out
    (10 s here). Its report, once it is thawed, counts as late."""
    async with (
        scene(overlap, server_args=("--forward-timeout", "10")) as slow,
        aio.insecure_channel(slow.address) as channel,
    ):
        stub = detection_pb2_grpc.DetectObjectBoundaryStub(channel)
        # Once first, so the server's stream to each camera is open: frozen, right holds it open
        # and answers nothing (a camera that cannot be reached at all is missing at once instead).
        warm = await stub.DetectObjects(fused("warm"), timeout=20)
        assert sorted(warm.snapshot.camera_ids) == ["left", "right"]
        with stopped(slow.cameras["right"]):
            started = time.monotonic()
            reply = await stub.DetectObjects(fused("frozen", deadline_s=1.0), timeout=20)
            took = time.monotonic() - started
        # Thawed, right takes the request and reports: late, which is not a forgery.
        values = await metrics_at_least(metrics_port(slow.server), 'drvs_fusion_reports_total{outcome="late"}', 1)
        assert values.get('drvs_fusion_reports_total{outcome="rejected"}', 0.0) == 0.0
    assert took < 5.0, took  # the deadline, not the forward timeout
    assert missing(reply.snapshot) == {"right": "DEADLINE_EXCEEDED"}, reply.snapshot.missing_cameras
    assert list(reply.snapshot.camera_ids) == ["left"] and len(reply.snapshot.objects) == 2


@pytest.mark.slow
async def test_a_waiting_fused_single_shot_does_not_delay_later_replies(office: Scene) -> None:
    """With right frozen, a fused single shot waits for its deadline; a per-camera request sent
    after it on the same stream is answered first, and the fused answer follows."""
    async with aio.insecure_channel(office.address) as channel:
        call = detection_pb2_grpc.DetectObjectBoundaryStub(channel).DetectStream()
        with stopped(office.cameras["right"]):
            await call.write(fused("slow", deadline_s=3.0))
            later = detection_pb2.DetectionRequest(
                request_id="later",
                robot_id="r",
                filter_def=YELLOW,
                region=box(LEFT_ONLY),
                callback_address="127.0.0.1:9",
            )
            await call.write(later)
            first = await read(call)
            second = await read(call)
        call.cancel()
    assert first.request_id == "later" and list(first.camera_ids) == ["left"] and not first.HasField("snapshot")
    assert second.request_id == "slow" and second.snapshot.final
    assert "right" in missing(second.snapshot) and near(second.snapshot, LONE)


async def dropped_at_least(ports: dict[str, int], count: int) -> None:
    """Until every camera has dropped `count` reports of a request its server cancelled (at most 10 s)."""
    name = 'drvs_reports_sent_total{outcome="dropped"}'

    async def dropped() -> dict[str, float]:
        return {c: (await scrape(port)).get(name, 0.0) for c, port in ports.items()}

    await poll(dropped, lambda values: all(v >= count for v in values.values()), what=f"{count} dropped by each camera",
               every=0.1)  # fmt: skip


@pytest.mark.slow
async def test_cameras_stop_when_the_robot_cancels_or_its_stream_ends(overlap: dict[str, RecordedCamera]) -> None:
    """Two 30 s continuous fused requests: the robot cancels the first on its stream, and no
    snapshot of it follows the cancel's reply; then it closes the stream with the second running.
    Each time, the server tells both cameras to stop (each drops its next report of the request and
    ends it), rather than letting them report for 30 s."""
    async with scene(overlap, camera_args=("--metrics-port", "0")) as running:
        ports = {camera_id: metrics_port(proc) for camera_id, proc in running.cameras.items()}
        async with aio.insecure_channel(running.address) as channel:
            call = detection_pb2_grpc.DetectObjectBoundaryStub(channel).DetectStream()
            await call.write(fused("a", rate_hz=5, duration_s=30))
            await read(call)
            await read(call)
            await read(call)
            await call.write(detection_pb2.DetectionRequest(request_id="a", cancel=True))
            while (reply := await read(call)).HasField("snapshot"):
                assert reply.request_id == "a"
            assert reply.request_id == "a"  # the cancel's own reply
            await dropped_at_least(ports, 1)
            await call.write(fused("b", rate_hz=5, duration_s=30))
            assert (await read(call)).request_id == "b"  # nothing more of a
            assert (await read(call)).snapshot.sequence == 0
            call.cancel()
            await dropped_at_least(ports, 2)


@pytest.mark.slow
async def test_a_robot_may_not_ask_cameras_to_report_to_the_server(office: Scene) -> None:
    """report_to_server is the server's to set on its forwards: a robot's request with it is
    refused, on DetectObjects and on a stream (where the stream goes on); and a continuous fused
    request needs a stream."""
    async with aio.insecure_channel(office.address) as channel:
        stub = detection_pb2_grpc.DetectObjectBoundaryStub(channel)
        sneaky = fused("sneaky")
        sneaky.ClearField("fusion")
        sneaky.report_to_server = True
        with pytest.raises(aio.AioRpcError) as err:
            await stub.DetectObjects(sneaky, timeout=10)
        assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert (err.value.details() or "").startswith("report_to_server: set only by the server")
        with pytest.raises(aio.AioRpcError) as err:
            await stub.DetectObjects(fused("forever", rate_hz=1, duration_s=5), timeout=10)
        assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert (err.value.details() or "").startswith("fusion: a continuous fused request needs a request stream")
        call = stub.DetectStream()
        await call.write(sneaky)
        await call.write(fused("fine"))
        refused = await asyncio.wait_for(call.read(), 20)
        answered = await read(call)
        call.cancel()
    assert refused.request_id == "sneaky" and refused.error.code == "INVALID_ARGUMENT"
    assert answered.request_id == "fine" and len(answered.snapshot.objects) == 2


def forged(request_id: str, camera_id: str, xy: tuple[float, float], key: bytes = b"") -> detection_pb2.DetectionReport:
    x, y = xy
    return detection_pb2.DetectionReport(
        request_id=request_id,
        camera_id=camera_id,
        sequence=0,
        final=True,
        report_key=key,
        detections=[
            detection_pb2.Detection(
                bounds=geometry_pb2.FloorBox(x_lower=x - 0.2, y_lower=y - 0.2, x_upper=x + 0.2, y_upper=y + 0.2),
                centroid=geometry_pb2.FloorPoint(x=x, y=y),
                ground_contact=geometry_pb2.FloorPoint(x=x, y=y - 0.2),
            )
        ],
    )


@pytest.mark.slow
async def test_injected_reports_do_not_count(office: Scene) -> None:
    """evil, a registered camera far away, is dispatched a fused single shot of its own and so holds
    a valid key, for that request. Into a continuous fused request dispatched to left and right it
    injects reports: in left's name with its key, in its own name (the request was not dispatched
    to it), in left's name with a guessed key, and in left's name without a key. None counts: no
    snapshot holds the forged object, the server counts four rejected reports and tells evil's
    stream to stop each. Its report for its own request, with its key, is taken."""
    evil = CapturingCamera()
    evil_server, evil_address = await serve_camera(evil)
    try:
        async with aio.insecure_channel(office.address) as channel:
            registration = register_message("evil", x=20.0, address=evil_address)
            registration.detector_kinds[:] = ["hsv"]
            await registry_pb2_grpc.RegisterVisionServiceStub(channel).Register(registration)
            call = detection_pb2_grpc.DetectObjectBoundaryStub(channel).DetectStream()
            await call.write(fused("lure", (17.0, 2.0, 23.0, 6.0), deadline_s=20))
            lure = await asyncio.wait_for(evil.requests.get(), 10)
            assert lure.report_to_server and not lure.callback_address and not lure.HasField("fusion")
            # Forwarded under an id unique in the server; the next fused request's is easily guessed.
            prefix, _, number = lure.request_id.rpartition(":")
            assert prefix == "lure"
            victim_id = f"victim:{int(number, 16) + 1:x}"
            key = lure.report_key
            assert len(key) == KEY_BYTES
            await call.write(fused("victim", rate_hz=4, duration_s=2.5))
            first = await read(call)
            assert first.request_id == "victim" and sorted(first.camera_ids) == ["left", "right"]
            fake = (0.5, 3.0)
            reports = detection_pb2_grpc.CallbackCoordinatesStub(channel).ReportDetections()
            # One at a time, each answered before the next: the server folds cancels of one request
            # that are waiting to be written into one (a flood of forgeries is not a flood back).
            cancelled: list[str] = []
            for message in (
                forged(victim_id, "left", fake, key),
                forged(victim_id, "evil", fake, key),
                forged(victim_id, "left", fake, secrets.token_bytes(KEY_BYTES)),
                forged(victim_id, "left", fake),
            ):
                await reports.write(message)
                control = await asyncio.wait_for(reports.read(), 10)
                assert control is not aio.EOF
                cancelled.extend(control.cancelled_request_ids)
            await reports.write(forged(lure.request_id, "evil", (21.0, 4.0), key))
            replies = [await read(call) for _ in range(12)]
            await reports.done_writing()
            call.cancel()
    finally:
        await evil_server.stop(0)
    assert cancelled == [victim_id] * 4
    victim = [r.snapshot for r in replies if r.request_id == "victim"]
    assert len(victim) == 11 and victim[-1].final
    assert all(not near(s, fake, 0.3) for s in victim)
    assert all(set(cameras_of(s, o)) <= {"left", "right"} for s in victim for o in s.objects)
    [lured] = [r for r in replies if r.request_id == "lure"]
    assert [cameras_of(lured.snapshot, o) for o in lured.snapshot.objects] == [["evil"]]
    assert near(lured.snapshot, (21.0, 4.0))
    values = await scrape(metrics_port(office.server))
    assert values['drvs_fusion_reports_total{outcome="rejected"}'] == 4.0


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("certs")
    make_all(out, ["server", "camera", "robot"], [])
    return out


def tls_args(certs: Path, role: str) -> tuple[str, ...]:
    return ("--tls-cert", str(certs / f"{role}.pem"), "--tls-key", str(certs / f"{role}-key.pem"),
            "--tls-ca", str(certs / "ca.pem"), "--tls-client-auth")  # fmt: skip


@pytest.mark.slow
async def test_with_tokens_only_cameras_report_to_the_server(
    overlap: dict[str, RecordedCamera], tmp_path: Path
) -> None:
    """Camera and robot tokens: the cameras' report streams carry their token, so a fused single shot
    works; a robot's credential on ReportDetections is refused (UNAUTHENTICATED)."""
    (tmp_path / "cameras.txt").write_text(f"cams {CAMERA_TOKEN}\n")
    (tmp_path / "robots.txt").write_text(f"r {ROBOT_TOKEN}\n")
    (tmp_path / "cam.token").write_text(CAMERA_TOKEN)
    server_args = ("--camera-tokens", str(tmp_path / "cameras.txt"), "--robot-tokens", str(tmp_path / "robots.txt"))
    async with scene(overlap, server_args, ("--token-file", str(tmp_path / "cam.token"))) as secured:
        robot = (("authorization", f"Bearer {ROBOT_TOKEN}"),)
        async with aio.insecure_channel(secured.address) as channel:
            reply = await detection_pb2_grpc.DetectObjectBoundaryStub(channel).DetectObjects(
                fused("tokens"), timeout=20, metadata=robot
            )
            code, details = await _report_as(channel, robot)
    assert sorted(reply.snapshot.camera_ids) == ["left", "right"] and len(reply.snapshot.objects) == 2
    assert code == grpc.StatusCode.UNAUTHENTICATED and "needs a valid camera token" in details


@pytest.mark.slow
async def test_with_mutual_tls_only_camera_certificates_report_to_the_server(
    overlap: dict[str, RecordedCamera], certs: Path
) -> None:
    """Mutual TLS: the cameras report over TLS with their certificates, so a fused single shot works;
    a caller with a robot's certificate is refused on ReportDetections (PERMISSION_DENIED)."""
    from drvs.wire.security import Security

    async with scene(overlap, tls_args(certs, "server"), tls_args(certs, "camera")) as secured:
        robot = Security(
            tls_cert=certs / "robot.pem",
            tls_key=certs / "robot-key.pem",
            tls_ca=certs / "ca.pem",
            require_client_cert=True,
        )
        async with robot.channel(secured.address) as channel:
            reply = await detection_pb2_grpc.DetectObjectBoundaryStub(channel).DetectObjects(fused("mtls"), timeout=20)
            code, details = await _report_as(channel, ())
    assert sorted(reply.snapshot.camera_ids) == ["left", "right"] and len(reply.snapshot.objects) == 2
    assert code == grpc.StatusCode.PERMISSION_DENIED and "OU=camera" in details, details


async def _report_as(channel: aio.Channel, metadata: tuple[tuple[str, str], ...]) -> tuple[grpc.StatusCode, str]:
    """Open a report stream to the server as the channel's caller and write one report."""
    call = detection_pb2_grpc.CallbackCoordinatesStub(channel).ReportDetections(metadata=metadata or None)
    with contextlib.suppress(Exception):
        await call.write(forged("any", "left", (0.0, 4.0), b"k" * KEY_BYTES))
        await call.done_writing()
    with contextlib.suppress(aio.AioRpcError):
        async for _ in call:
            pass
    return await call.code(), await call.details() or ""


async def _first_snapshot(call: Any, request_id: str) -> detection_pb2.WorldSnapshot:
    while (reply := await read(call)).request_id != request_id or not reply.HasField("snapshot"):
        pass
    return reply.snapshot


async def test_a_camera_counts_fused_continuous_requests_per_robot(overlap: dict[str, RecordedCamera]) -> None:
    """A camera's per-robot cap on continuous requests counts fused ones by whom the server knows
    the robot as (here its connection), not by the robot_id it names: with a cap of one, a robot's
    second is refused there, naming another robot's id gets it no fresh slot, and the refusal is in
    that request's snapshot; another robot's is taken even when it names the first one's id (one
    robot cannot use up another's slots by naming it)."""
    rec = overlap["left"]
    async with DrvsServer("127.0.0.1:0") as server:
        node = CameraNode(
            "left", VideoSource(str(rec.video)), rec.homography, server.address, max_range_m=6.0, max_continuous=1
        )
        async with (
            node,
            aio.insecure_channel(server.address) as channel,
            # Another robot: its own connection (channels to one address otherwise share one).
            aio.insecure_channel(server.address, options=[("grpc.use_local_subchannel_pool", 1)]) as other_channel,
        ):
            await asyncio.wait_for(node.registered.wait(), 10)
            call = detection_pb2_grpc.DetectObjectBoundaryStub(channel).DetectStream()
            await call.write(fused("a", LEFT_ONLY, rate_hz=2, duration_s=5))
            assert list((await read(call)).camera_ids) == ["left"]
            await call.write(fused("b", LEFT_ONLY, rate_hz=2, duration_s=5))
            assert list((await read(call)).camera_ids) == ["left"]
            refused = await _first_snapshot(call, "b")
            posing = fused("c", LEFT_ONLY, rate_hz=2, duration_s=5)
            posing.robot_id = "q"
            posing.requester = "q"  # the server overwrites it
            await call.write(posing)
            assert list((await read(call)).camera_ids) == ["left"]
            posed = await _first_snapshot(call, "c")
            assert [m.code for m in posed.missing_cameras] == ["RESOURCE_EXHAUSTED"], posed
            other = detection_pb2_grpc.DetectObjectBoundaryStub(other_channel).DetectStream()
            await other.write(fused("d", LEFT_ONLY, rate_hz=2, duration_s=5))  # robot_id "r", as the first's
            assert list((await read(other)).camera_ids) == ["left"]
            taken = await _first_snapshot(other, "d")
            assert sorted(node.shares.continuous().values()) == [1, 1], node.shares.continuous()
            call.cancel()
            other.cancel()
    [why] = refused.missing_cameras
    assert why.camera_id == "left" and why.code == "RESOURCE_EXHAUSTED"
    assert "continuous requests already running for robot 'ipv4:127.0.0.1:" in why.message, why.message
    assert "(fused, via the server)" in why.message, why.message
    assert list(taken.missing_cameras) == [], taken


async def test_a_camera_without_its_server_refuses_to_report_to_it(overlap: dict[str, RecordedCamera]) -> None:
    """A camera that is not registered with a server (none answers at its address) has nowhere to
    send a fused request's reports: it refuses the request (FAILED_PRECONDITION) and runs nothing."""
    rec = overlap["left"]
    node = CameraNode("left", VideoSource(str(rec.video)), rec.homography, "127.0.0.1:1", max_range_m=6.0)
    async with node:
        request = DetectionRequest(
            request_id="x",
            robot_id="r",
            filter_def=YELLOW,
            region=box_region(*LEFT_ONLY),
            callback_address="",
            report_to_server=True,
        )
        with pytest.raises(FailedPrecondition) as err:
            node.accept(request)
        assert not node._jobs
    assert str(err.value) == (
        "report_to_server: camera left is not registered with its server (127.0.0.1:1), so it has nowhere to report"
    )


@contextlib.asynccontextmanager
async def server_with_quiet_camera() -> AsyncIterator[tuple[DrvsServer, aio.Channel, CapturingCamera]]:
    """A DrvsServer in this process with one registered camera, "quiet", that records the requests
    forwarded to it and never reports; yields the server, a channel to it and the camera."""
    quiet = CapturingCamera()
    quiet_server, quiet_address = await serve_camera(quiet)
    try:
        async with DrvsServer("127.0.0.1:0") as server, aio.insecure_channel(server.address) as channel:
            await registry_pb2_grpc.RegisterVisionServiceStub(channel).Register(
                register_message("quiet", address=quiet_address)
            )
            yield server, channel, quiet
    finally:
        await quiet_server.stop(0)


async def test_fused_requests_are_bounded_and_end_with_their_stream(monkeypatch: pytest.MonkeyPatch) -> None:
    """A camera that never reports keeps fused single shots waiting: a second fused request with the
    same id on the stream is refused, so is one past the stream's waiting single shots and one past
    the server's sessions; the refusals hold nothing. When the robot's stream ends, its session
    ends: nothing is left in flight."""
    monkeypatch.setattr(servicers_module, "MAX_FUSED_WAITING_PER_STREAM", 2)
    async with server_with_quiet_camera() as (server, channel, _quiet):
        region = (-1.0, 2.0, 1.0, 5.0)
        call = detection_pb2_grpc.DetectObjectBoundaryStub(channel).DetectStream()
        await call.write(fused("a", region, deadline_s=30))
        await call.write(fused("a", region, deadline_s=30))
        assert (await asyncio.wait_for(call.read(), 10)).error.message == (
            "request_id: 'a' is already a fused request in flight on this stream"
        )
        await call.write(fused("b", region, deadline_s=30))
        await call.write(fused("c", region, deadline_s=30))
        refused = await asyncio.wait_for(call.read(), 10)
        assert refused.request_id == "c" and refused.error.code == "RESOURCE_EXHAUSTED"
        assert refused.error.message.startswith("fusion: 2 fused single shots already waiting")
        server.fusion.max_sessions = 2
        other = detection_pb2_grpc.DetectObjectBoundaryStub(channel).DetectStream()
        await other.write(fused("d", region, deadline_s=30))
        refused = await asyncio.wait_for(other.read(), 10)
        assert refused.error.code == "RESOURCE_EXHAUSTED"
        assert refused.error.message.startswith("fusion: 2 fused requests already in flight on this server")
        assert server.fusion.count == 2 and len(server.limits._active) == 0
        call.cancel()
        other.cancel()
        await wait_until(lambda: not server.fusion.count, "the server's fusion sessions all ended", timeout=10)


def crowd(request_id: str, camera_id: str, key: bytes, count: int) -> detection_pb2.DetectionReport:
    """A final report of `count` small objects 1 m apart on a grid."""
    report = forged(request_id, camera_id, (0.0, 0.0), key)
    del report.detections[:]
    for i in range(count):
        x, y = float(i % 16), float(i // 16)
        report.detections.add(
            bounds=geometry_pb2.FloorBox(x_lower=x - 0.1, y_lower=y - 0.1, x_upper=x + 0.1, y_upper=y + 0.1),
            centroid=geometry_pb2.FloorPoint(x=x, y=y),
            ground_contact=geometry_pb2.FloorPoint(x=x, y=y - 0.1),
        )
    return report


async def test_a_crowded_report_is_fused_aside_and_capped() -> None:
    """A camera reporting 20 objects (more than are fused on the event loop) gets them fused in a
    worker thread: 20 objects in the answer. One reporting 200 has the first 128 fused."""
    async with server_with_quiet_camera() as (_server, channel, quiet):
        stub = detection_pb2_grpc.DetectObjectBoundaryStub(channel)
        counts = []
        for count in (20, 200):
            answer = asyncio.ensure_future(stub.DetectObjects(fused(f"n{count}", (-1.0, 2.0, 1.0, 5.0)), timeout=20))
            forwarded = await asyncio.wait_for(quiet.requests.get(), 10)
            reports = detection_pb2_grpc.CallbackCoordinatesStub(channel).ReportDetections()
            await reports.write(crowd(forwarded.request_id, "quiet", forwarded.report_key, count))
            reply = await answer
            await reports.done_writing()
            counts.append(len(reply.snapshot.objects))
    assert counts == [20, 128]

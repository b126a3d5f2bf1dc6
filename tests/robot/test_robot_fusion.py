"""The robot's side of fused delivery: DrvsClient.snapshot, DrvsClient.track and
drvs-robot track / detect --fuse.

The first half runs the client against a real gRPC server in this process (port 0) that answers
fused requests on DetectStream the way protos/drvs/v1/detection.proto says the DRVS server does
(a single shot's one reply carries its snapshot; a continuous request's first reply carries none,
then one reply per period with only request_id and snapshot). It can do what the real server
should not (end a stream mid-track, never finish), so the client's handling of both is proven.
"""

from __future__ import annotations

import asyncio
import json
import math
import os
import re
import sys
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio
from grpc import aio

import drvs
from drvs.core.errors import DeadlineExceeded, InvalidArgument, ResourceExhausted, Unavailable
from drvs.core.filters import HsvRange
from drvs.core.model import CameraError, Snapshot, WorldObject
from drvs.robot import DrvsClient, snapshot_json
from drvs.sim.scene import FloorPatch, RecordedCamera
from drvs.tools.launch import ManagedProcess, start_server
from drvs.v1 import detection_pb2, detection_pb2_grpc
from drvs.wire import _grpc
from drvs.wire.convert import snapshot_to_pb
from drvs.wire.request_stream import StreamContext, refusal
from tests.fakes import start_recorded_camera
from tests.helpers import YELLOW, Scene, metrics_port, poll, record_facing, scrape, serving_detection, wait_until

DOC = Path(__file__).resolve().parents[2] / "docs" / "validation.md"
#: Filters the in-test server treats specially.
REFUSED = "hsv_000000000010010010"  # answered RESOURCE_EXHAUSTED
BREAKS = "hsv_001001001011011011"  # its track's stream ends after two snapshots
STALLS = "hsv_002002002012012012"  # its track never sends the final snapshot
#: Its track's stream ends after two snapshots; the stream the track is sent again on ends before
#: any reply; sent a third time, it runs to its end.
BREAKS_TWICE = "hsv_003003003013013013"
#: Its track's stream ends after two snapshots; the track sent again is refused for load (with a
#: retry hint); sent a third time, it runs to its end.
BREAKS_THEN_BUSY = "hsv_004004004014014014"

OBJECT_KEYS = {
    "track_id", "centroid", "bounds", "velocity", "heading_deg", "uncertainty_m", "cameras", "marker_id",
    "label", "last_seen", "score", "area_m2",
}  # fmt: skip
SNAPSHOT_KEYS = {"time", "sequence", "final", "objects", "missing_cameras", "cameras", "uncovered"}


LATE_C = "camera camC: no report in time"


def box_object(track_id: int, x: float, y: float, t: float, vx: float = 0.0) -> WorldObject:
    from shapely.geometry import box

    outline = box(x - 0.2, y - 0.2, x + 0.2, y + 0.2)
    return WorldObject(
        track_id=track_id,
        outline=outline,
        bounds=outline.bounds,
        centroid_xy=(x, y),
        velocity_xy=(vx, 0.0),
        course_deg=0.0 if vx else None,
        uncertainty_m=0.02,
        camera_ids=("camA", "camB"),
        last_seen=t,
        label="",
        score=0.9,
        area_m2=outline.area,
    )


@dataclass
class FusingServer(detection_pb2_grpc.DetectObjectBoundaryServicer):
    """DetectStream as the proto describes it for fused requests; records what it was sent."""

    requests: list[detection_pb2.DetectionRequest] = field(default_factory=list)
    #: as they came on the wire, before the stream's repeated fields were filled back in
    raw: list[detection_pb2.DetectionRequest] = field(default_factory=list)
    cancelled: list[str] = field(default_factory=list)
    #: request id -> snapshots it has sent
    sent: dict[str, int] = field(default_factory=dict)
    per_camera: list[str] = field(default_factory=list)
    #: request id -> times a track with it was sent
    attempts: dict[str, int] = field(default_factory=dict)

    async def DetectStream(
        self, request_iterator: AsyncIterator[detection_pb2.DetectionRequest], context: aio.ServicerContext[Any, Any]
    ) -> AsyncIterator[detection_pb2.DetectionReply]:
        out: asyncio.Queue[detection_pb2.DetectionReply | None] = asyncio.Queue()
        runs: dict[str, asyncio.Task[None]] = {}

        async def read() -> None:
            stream = StreamContext()
            async for message in request_iterator:
                self.raw.append(detection_pb2.DetectionRequest())
                self.raw[-1].CopyFrom(message)
                stream.fill(message)
                self.requests.append(message)
                rid = message.request_id
                if message.cancel:
                    self.cancelled.append(rid)
                    if rid in runs:
                        runs.pop(rid).cancel()
                    continue
                if message.filter_def == REFUSED:
                    out.put_nowait(refusal(rid, _grpc.status_of(ResourceExhausted("x")), "continuous: too many"))
                elif not message.HasField("fusion"):
                    self.per_camera.append(rid)  # dispatched to a camera that never reports
                    out.put_nowait(detection_pb2.DetectionReply(request_id=rid, camera_ids=["camZ"]))
                elif message.continuous.rate_hz == 0:
                    now = 1_700_000_000.0
                    snapshot = Snapshot(
                        time=now,
                        objects=(box_object(1, 1.0, 2.0, now),),
                        camera_errors={"camC": CameraError("DEADLINE_EXCEEDED", LATE_C, "camC")},
                        camera_ids=("camA", "camB"),
                    )
                    reply = detection_pb2.DetectionReply(request_id=rid, camera_ids=["camA", "camB", "camC"])
                    reply.snapshot.CopyFrom(snapshot_to_pb(snapshot))
                    out.put_nowait(reply)
                else:
                    self.attempts[rid] = self.attempts.get(rid, 0) + 1
                    if message.filter_def == BREAKS_TWICE and self.attempts[rid] == 2:
                        out.put_nowait(detection_pb2.DetectionReply(request_id="END"))  # no reply
                        continue
                    if message.filter_def == BREAKS_THEN_BUSY and self.attempts[rid] == 2:
                        busy = refusal(rid, _grpc.status_of(ResourceExhausted("x")), "overloaded: past its capacity")
                        busy.error.retry_after_s = 0.2
                        out.put_nowait(busy)
                        continue
                    reply = detection_pb2.DetectionReply(request_id=rid, camera_ids=["camA", "camB"])
                    reply.missing_cameras.add(camera_id="camM", code="UNAVAILABLE", message="camera camM: gone")
                    out.put_nowait(reply)
                    runs[rid] = asyncio.get_running_loop().create_task(self._run(message, out))
            out.put_nowait(None)

        reader = asyncio.get_running_loop().create_task(read())
        try:
            while (reply := await out.get()) is not None:
                if reply.request_id == "END":
                    return  # the stream ends under the robot
                yield reply
        finally:
            reader.cancel()
            for task in runs.values():
                task.cancel()

    async def _run(self, message: detection_pb2.DetectionRequest, out: asyncio.Queue[Any]) -> None:
        rid = message.request_id
        rate = message.continuous.rate_hz
        count = math.floor(message.continuous.duration_s * rate + 1e-9) + 1
        t0 = 1_700_000_000.0
        for n in range(count):
            if n:
                await asyncio.sleep(1 / rate)
            if message.filter_def in (BREAKS, BREAKS_TWICE, BREAKS_THEN_BUSY) and n == 2 and self.attempts[rid] == 1:
                out.put_nowait(detection_pb2.DetectionReply(request_id="END"))
                return
            final = n == count - 1
            if final and message.filter_def == STALLS:
                return
            t = t0 + n / rate
            snapshot = Snapshot(
                time=t,
                objects=(box_object(7, 1.0 + 0.1 * n, 2.0, t, vx=0.1 * rate), box_object(8, 3.0, 1.0, t)),
                camera_ids=("camA", "camB"),
                sequence=n,
                final=final,
            )
            out.put_nowait(detection_pb2.DetectionReply(request_id=rid, snapshot=snapshot_to_pb(snapshot)))
            self.sent[rid] = n + 1


async def track_json(*args: str) -> list[dict[str, Any]]:
    """Run `drvs-robot track ARGS --json` to its end: it opens no listening socket (fused delivery
    needs none) and exits 0; returns the snapshots it printed, parsed."""
    async with robot_cli("track", *args, "--json") as proc:
        await proc.wait_for_line(r'^\{"time"')
        assert listening_ports(proc.pid) == set()
        code = await proc.wait(timeout=20)
    assert code == 0, proc.output()
    return [json.loads(line) for line in proc.lines]


@pytest_asyncio.fixture
async def fusing() -> AsyncIterator[tuple[FusingServer, str]]:
    servicer = FusingServer()
    async with serving_detection(servicer) as address:
        yield servicer, address


async def test_fused_detect_returns_one_snapshot_and_opens_no_listener(fusing: tuple[FusingServer, str]) -> None:
    servicer, address = fusing
    async with DrvsClient.connect(address, robot_id="r1") as robot:
        snapshot = await robot.snapshot(YELLOW, (0, 0, 5, 5), deadline_s=1.5)
        assert isinstance(snapshot, drvs.Snapshot)
        time, objects, missing = snapshot
        assert (time, objects, missing) == (snapshot.time, snapshot.objects, tuple(snapshot.camera_errors.values()))
        assert time == 1_700_000_000.0 and snapshot.final and snapshot.camera_ids == ("camA", "camB")
        assert [o.track_id for o in snapshot.objects] == [1]
        assert snapshot.objects[0].centroid_xy == pytest.approx((1.0, 2.0))
        late = CameraError("DEADLINE_EXCEEDED", LATE_C, "camC")
        assert snapshot.camera_errors == {"camC": late}
        with pytest.warns(DeprecationWarning, match=r"Snapshot\.missing_cameras is deprecated"):
            assert snapshot.missing_cameras == (late,)
        assert snapshot.request_id == servicer.requests[-1].request_id
        sent = servicer.requests[-1]
        assert sent.fusion.deadline_s == 1.5 and sent.callback_address == "" and not sent.report_to_server
        assert not robot.listening and robot.callback_address == "" and robot.port == 0
        # A per-camera request afterwards starts the listener, and names it as its callback.
        sub = await robot.subscribe(YELLOW, (0, 0, 5, 5), timeout_s=0.1)
        async with sub:
            assert robot.listening and robot.port > 0
            assert servicer.requests[-1].callback_address == f"127.0.0.1:{robot.port}"
        # ... and a fused request after it still sends no callback address (on the wire: the
        # server's StreamContext fills the previous one back in, which it ignores for fused requests).
        # (detect(fuse=True), the deprecated spelling of snapshot(), warns and still works.)
        with pytest.warns(DeprecationWarning, match=r"detect\(fuse=True\) is deprecated: use snapshot\(\)"):
            old = await robot.detect(YELLOW, (0, 0, 5, 5), fuse=True)
        assert isinstance(old, drvs.Snapshot) and old.objects == snapshot.objects
        assert servicer.raw[-1].callback_address == "" and servicer.raw[-1].HasField("fusion")


async def test_track_yields_snapshots_in_order_with_stable_ids_and_ends_after_the_final(
    fusing: tuple[FusingServer, str],
) -> None:
    servicer, address = fusing
    async with DrvsClient.connect(address, robot_id="r1") as robot:
        seen = [s async for s in robot.track(YELLOW, (0, 0, 5, 5), rate_hz=20, duration_s=0.25, drop_after_s=2)]
        assert [s.sequence for s in seen] == [0, 1, 2, 3, 4, 5] and [s.final for s in seen] == [False] * 5 + [True]
        assert all([o.track_id for o in s.objects] == [7, 8] for s in seen)
        assert seen[-1].objects[0].velocity_xy == pytest.approx((2.0, 0.0))
        sent = servicer.requests[-1]
        assert sent.fusion.drop_after_s == 2 and sent.continuous.rate_hz == 20 and sent.callback_address == ""
        assert servicer.cancelled == []  # it ran to its end: nothing to cancel
        assert not robot.listening


async def test_leaving_a_track_early_cancels_it_at_the_server(fusing: tuple[FusingServer, str]) -> None:
    servicer, address = fusing
    async with DrvsClient.connect(address, robot_id="r1") as robot:
        async with robot.track(YELLOW, (0, 0, 5, 5), rate_hz=20, duration_s=30) as track:
            assert track.camera_ids == ("camA", "camB")
            gone = CameraError("UNAVAILABLE", "camera camM: gone", "camM")
            assert track.camera_errors == {"camM": gone}
            # The deprecated tuple of CameraErrors warns and still works.
            with pytest.warns(DeprecationWarning, match=r"Track\.missing_cameras is deprecated"):
                assert track.missing_cameras == (gone,)
            async for snapshot in track:
                if snapshot.sequence == 1:
                    break
        rid = track.request_id
        await robot._requests.flush_cancels()  # type: ignore[union-attr]
        await wait_until(lambda: rid in servicer.cancelled)
        sent = servicer.sent[rid]
        # A bare `async for ... break` (no `async with`) cancels too, once the iterator is dropped.
        async for snapshot in robot.track(YELLOW, (0, 0, 5, 5), rate_hz=20, duration_s=30):
            if snapshot.sequence == 0:
                second = snapshot.request_id
                break
        await wait_until(lambda: second in servicer.cancelled)
        assert servicer.sent[rid] == sent  # the server stopped: no snapshot after the cancel


async def test_an_unread_track_keeps_the_newest_snapshots_and_always_the_final(
    fusing: tuple[FusingServer, str],
) -> None:
    _, address = fusing
    async with DrvsClient.connect(address, robot_id="r1") as robot:
        track = await robot.track(YELLOW, (0, 0, 5, 5), rate_hz=100, duration_s=0.2, max_queued=3)
        await wait_until(lambda: track.finished)  # every snapshot has arrived, none read
        seen = [s.sequence async for s in track]
        assert track.received == 21 and track.dropped == 21 - len(seen)
        assert seen == [17, 18, 19, 20]  # the newest three unread, and the final


async def test_a_refused_track_raises_the_servers_error_and_holds_nothing(fusing: tuple[FusingServer, str]) -> None:
    servicer, address = fusing
    async with DrvsClient.connect(address, robot_id="r1") as robot:
        with pytest.raises(ResourceExhausted, match="continuous: too many"):
            async for _ in robot.track(REFUSED, (0, 0, 5, 5), duration_s=1):
                pass
        assert robot._tracks == {} and robot._requests._consumers == {}  # type: ignore[union-attr]
        assert servicer.cancelled == []


async def test_a_stream_that_ends_mid_track_raises_unavailable_after_what_came(
    fusing: tuple[FusingServer, str],
) -> None:
    _, address = fusing
    async with DrvsClient.connect(address, robot_id="r1") as robot:
        seen: list[int] = []
        with pytest.raises(Unavailable, match="the request stream ended before the final snapshot"):
            async for snapshot in robot.track(BREAKS, (0, 0, 5, 5), rate_hz=20, duration_s=1):
                seen.append(snapshot.sequence)
        assert seen == [0, 1]
        # The next request opens a new stream.
        assert (await robot.snapshot(YELLOW, (0, 0, 5, 5))).objects


async def test_a_resumed_track_whose_new_stream_ends_too_is_sent_again(fusing: tuple[FusingServer, str]) -> None:
    # Through a server list (here the one server twice: the client fails over all the same) the
    # track is sent again when its stream ends. The stream it was sent again on ends too, before
    # any reply (as one that went to the dying server before the channel knew): the track is sent a
    # third time and runs to its final snapshot. (The stream's end reached the track while it was
    # being sent again, and it gave up: Unavailable, once in a full suite run.)
    servicer, address = fusing
    async with DrvsClient.connect(f"{address},{address}", robot_id="r1") as robot:
        async with robot.track(BREAKS_TWICE, (0, 0, 5, 5), rate_hz=20, duration_s=1) as track:
            seen = [snapshot.final async for snapshot in track]
        assert seen[-1] and len(seen) >= 3, seen
        assert servicer.attempts[track.request_id] == 3 and track.resumes == 1, servicer.attempts


async def test_a_resumed_track_refused_for_load_is_sent_again_after_the_hint(fusing: tuple[FusingServer, str]) -> None:
    # The server a track is sent again to refuses it for load (its door, with a retry hint: the
    # survivors take the dead server's robots): the track is sent again no sooner than the hint
    # asks, and runs to its end, where it used to end with Unavailable.
    servicer, address = fusing
    async with DrvsClient.connect(f"{address},{address}", robot_id="r1") as robot:
        async with robot.track(BREAKS_THEN_BUSY, (0, 0, 5, 5), rate_hz=20, duration_s=1.5) as track:
            seen = [snapshot.final async for snapshot in track]
        assert seen[-1] and servicer.attempts[track.request_id] == 3 and track.resumes == 1, servicer.attempts
        assert track.gaps_s[0] >= 0.2  # waited the hint


async def test_a_track_without_its_final_snapshot_raises_deadline_exceeded(fusing: tuple[FusingServer, str]) -> None:
    servicer, address = fusing
    async with DrvsClient.connect(address, robot_id="r1") as robot:
        track = robot.track(STALLS, (0, 0, 5, 5), rate_hz=20, duration_s=0.1, timeout_s=0.2)
        with pytest.raises(DeadlineExceeded, match="no final snapshot within"):
            async for _ in track:
                pass
        await robot._requests.flush_cancels()  # type: ignore[union-attr]
        await wait_until(lambda: servicer.requests[-1].cancel)  # told the server to stop it


BAD: Any = "1"
BOX = (0, 0, 5, 5)
#: Bad arguments of the fused calls and their whole messages (docs/validation.md rows cite this file).
API_CASES: list[tuple[Callable[[DrvsClient], Any], str]] = [
    (
        lambda r: r.track(YELLOW, BOX, duration_s=0),
        "duration_s: 0 must be a number > 0 (a track runs at a rate for a time)",
    ),
    (
        lambda r: r.track(YELLOW, BOX, rate_hz=-1, duration_s=1),
        "rate_hz: -1 must be a number > 0 (a track runs at a rate for a time)",
    ),
    (
        lambda r: r.track(YELLOW, BOX, duration_s=1, drop_after_s=99),
        "fusion.drop_after_s: 99.0 is not between 0 and 60 seconds",
    ),
    (
        lambda r: r.track(YELLOW, BOX, duration_s=1, deadline_s=BAD),
        "deadline_s: '1' must be a number of seconds, or None for the server's default",
    ),
    (
        lambda r: r.track(YELLOW, BOX, duration_s=1, drop_after_s=BAD),
        "drop_after_s: '1' must be a number of seconds, or None for the server's default",
    ),
    (
        lambda r: r.track(YELLOW, BOX, duration_s=1, max_queued=0),
        "max_queued: 0 must be a whole number of snapshots >= 1",
    ),
    (
        lambda r: r.detect(YELLOW, BOX, fuse=True, rate_hz=1, duration_s=1),
        "fuse: detect(fuse=True) is a single shot (rate_hz and duration_s 0); use track() for snapshots over time",
    ),
    (
        lambda r: r.snapshot(YELLOW, BOX, deadline_s=31),
        "fusion.deadline_s: 31.0 is not between 0 and 30 seconds",
    ),
    (
        lambda r: r.detect(YELLOW, BOX, deadline_s=1),  # type: ignore[call-overload]
        "deadline_s: only for fused requests (fuse=True)",
    ),
]
#: Bad flags of drvs-robot track / detect --fuse and the line each prints (exit 2).
CLI_CASES: list[tuple[list[str], str]] = [
    (["track", "--duration", "0"], "--duration: 0 must be in (0, 3600]"),
    (["track", "--duration", "1", "--rate", "0"], "--rate: 0 must be in (0, 100]"),
    (["track", "--duration", "1", "--rate", "101"], "--rate: 101 must be in (0, 100]"),
    (["track", "--duration", "1", "--drop-after", "-1"], "--drop-after: -1 must be in [0, 60]"),
    (["track", "--duration", "1", "--deadline", "31"], "--deadline: 31 must be in [0, 30]"),
    (["detect", "--fuse", "--deadline", "-2"], "--deadline: -2 must be in [0, 30]"),
    (["track", "--duration", "1", "--timeout", "-1"], "--timeout: -1 must be >= 0"),
    (
        ["detect", "--fuse", "--rate", "1", "--duration", "1"],
        "--fuse: a single shot; drvs-robot track gives snapshots at --rate for --duration",
    ),
    (["detect", "--fuse", "--listen", "127.0.0.1:0"], "--listen: a fused request needs no listener (--fuse)"),
    (["detect", "--fuse", "--advertise", "127.0.0.1:9"], "--advertise: a fused request needs no listener (--fuse)"),
    (["detect", "--deadline", "1"], "--deadline: only with --fuse (or drvs-robot track)"),
    (["track"], "the following arguments are required: --duration"),
]


@pytest.mark.filterwarnings("ignore:detect\\(fuse=True\\) is deprecated:DeprecationWarning")  # one case is its refusal
async def test_bad_fused_arguments_are_refused_before_anything_is_sent(fusing: tuple[FusingServer, str]) -> None:
    servicer, address = fusing
    async with DrvsClient.connect(address, robot_id="r1") as robot:
        for call, message in API_CASES:
            with pytest.raises(InvalidArgument) as refused:
                result = call(robot)
                if asyncio.iscoroutine(result):
                    await result
            assert str(refused.value) == message
        # The request's own rules, as for DetectionRequest.
        with pytest.raises(InvalidArgument, match=r"^filter_def: "):
            robot.track("hsv_1", BOX, duration_s=1)
        with pytest.raises(InvalidArgument, match=r"^continuous.rate_hz: 1000 exceeds the limit of 100"):
            robot.track(YELLOW, BOX, rate_hz=1000, duration_s=1)
        assert servicer.requests == [] and not robot.listening


def test_every_fused_refusal_is_in_validation_md() -> None:
    """Each row of docs/validation.md that cites this file gives messages that these tests get,
    and each message these tests get has its row."""
    rows = [
        line
        for line in DOC.read_text().splitlines()
        if line.startswith("|") and "tests/robot/test_robot_fusion.py" in line
    ]
    patterns = []
    for row in rows:
        cells = row.strip("|").split(" | ")
        for text in re.findall(r"`([^`]+)`", cells[2]):
            if ": " in text:  # a message, not a name (`--advertise` alike)
                parts = re.split(r"(…)", text)
                patterns.append(re.compile("".join(".*" if p == "…" else re.escape(p) for p in parts)))
    messages = [m for _, m in API_CASES] + [m for _, m in CLI_CASES]
    for pattern in patterns:
        assert any(pattern.fullmatch(m) for m in messages), f"validation.md's {pattern.pattern!r} is not tested here"
    for message in messages:
        assert any(p.fullmatch(message) for p in patterns), f"{message!r} has no row in docs/validation.md"


# --- drvs-robot against the in-test server --------------------------------------------------------


def listening_ports(pid: int) -> set[int]:
    """The TCP ports process `pid` listens on: its socket descriptors (/proc/PID/fd) that are in
    state LISTEN in its network namespace's tables (/proc/PID/net/tcp, tcp6)."""
    inodes = set()
    for fd in os.listdir(f"/proc/{pid}/fd"):
        try:
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[len("socket:[") : -1])
    ports = set()
    for table in ("tcp", "tcp6"):
        with open(f"/proc/{pid}/net/{table}") as f:
            for line in f.readlines()[1:]:
                fields = line.split()
                if fields[3] == "0A" and fields[9] in inodes:  # 0A: TCP_LISTEN
                    ports.add(int(fields[1].rsplit(":", 1)[1], 16))
    return ports


def robot_cli(*args: str) -> ManagedProcess:
    return ManagedProcess.entry_point("robot", "drvs-robot", *args)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
async def test_drvs_robot_track_json_listens_on_no_port(fusing: tuple[FusingServer, str]) -> None:
    servicer, address = fusing
    args = ("--server", address, "--filter", YELLOW, "--roi", "0,0,5,5")
    snapshots = await track_json(*args, "--rate", "10", "--duration", "1.5")
    assert [s["sequence"] for s in snapshots] == list(range(16)) and snapshots[-1]["final"] is True
    for s in snapshots:
        assert set(s) == SNAPSHOT_KEYS and s["cameras"] == ["camA", "camB"] and s["missing_cameras"] == []
        assert [o["track_id"] for o in s["objects"]] == [7, 8]
        for o in s["objects"]:
            assert set(o) == OBJECT_KEYS and len(o["centroid"]) == 2 and len(o["bounds"]) == 4
    assert snapshots[3]["objects"][0]["centroid"] == [1.3, 2.0] and snapshots[3]["objects"][0]["velocity"] == [1.0, 0]
    assert servicer.requests[0].continuous.duration_s == 1.5 and servicer.requests[0].callback_address == ""
    # The control: a per-camera request from the same command listens (so the check above can fail).
    async with robot_cli("detect", *args, "--rate", "10", "--duration", "5") as per_camera:
        await per_camera.wait_for_line(r"dispatched to camZ")
        assert len(listening_ports(per_camera.pid)) == 1


async def test_drvs_robot_detect_fuse_prints_the_snapshot(fusing: tuple[FusingServer, str]) -> None:
    _, address = fusing
    args = ("--server", address, "--filter", YELLOW, "--roi", "0,0,5,5")
    async with robot_cli("detect", *args, "--fuse", "--json", "--deadline", "1") as proc:
        code = await proc.wait(timeout=20)
    lines = proc.lines
    # camC missed the deadline: exit 3, like a per-camera request with a camera missing.
    assert code == 3, lines
    snapshot = json.loads(lines[0])
    assert set(snapshot) == SNAPSHOT_KEYS and snapshot["final"] is True
    assert snapshot["missing_cameras"] == [
        {"camera_id": "camC", "code": "DEADLINE_EXCEEDED", "message": "camera camC: no report in time"}
    ]
    assert lines[1].startswith("drvs-robot: no answer from camC: DEADLINE_EXCEEDED")
    async with robot_cli("detect", *args, "--fuse") as proc:
        assert await proc.wait(timeout=20) == 3
    assert proc.lines[0].startswith("snapshot #0 final at 1700000000.000: 1 object(s) from camA, camB")
    assert proc.lines[1] == "  missing camC: DEADLINE_EXCEEDED camera camC: no report in time"
    header, row = proc.lines[2].split(), proc.lines[3].split()
    assert header[:3] == ["track", "x", "m"] and row[:3] == ["1", "1.000", "2.000"]


@pytest.mark.parametrize(("argv", "message"), CLI_CASES)
async def test_bad_fused_flags_exit_2_naming_the_flag(argv: list[str], message: str) -> None:
    proc = robot_cli(*argv, "--server", "127.0.0.1:9", "--filter", YELLOW, "--roi", "0,0,5,5")
    async with proc:
        code = await proc.wait(timeout=20)
    output = proc.output()
    assert code == 2 and "Traceback" not in output, output
    # Its own line: "drvs-robot: MESSAGE" (argparse: "drvs-robot track: error: MESSAGE").
    assert any(line.startswith("drvs-robot") and line.endswith(": " + message) for line in proc.lines), output


def test_snapshot_json_has_exactly_the_documented_keys() -> None:
    marker = WorldObject(
        track_id=3,
        outline=box_object(1, 0, 0, 0).outline,
        bounds=(0.0, 0.0, 1.0, 1.0),
        centroid_xy=(0.123456, 1.0),
        marker_id=7,
        label="",
        last_seen=12.5,
    )
    out = snapshot_json(Snapshot(time=12.5, objects=(marker,), sequence=2, final=False, camera_ids=("c",)))
    assert set(out) == SNAPSHOT_KEYS and set(out["objects"][0]) == OBJECT_KEYS
    assert out["objects"][0]["centroid"] == [0.1235, 1.0] and out["objects"][0]["marker_id"] == 7
    assert out["objects"][0]["heading_deg"] is None and out["objects"][0]["cameras"] == []
    assert json.loads(json.dumps(out)) == out


# --- end to end: the real drvs-server and two drvs-camera processes that overlap -----------------

#: Two cameras 1 m apart looking the same way (+y): both see the two yellow discs.
OVERLAP_POSES = {"camA": (0.0, 0.0, 3.0), "camB": (1.0, 0.0, 3.0)}
DISCS = [((-1.0, 4.0), 0.25), ((1.5, 3.0), 0.20)]
REGION = (-3.0, 1.0, 4.0, 8.0)


@pytest.fixture(scope="module")
def overlapping(tmp_path_factory: pytest.TempPathFactory) -> dict[str, RecordedCamera]:
    directory = tmp_path_factory.mktemp("overlap")
    patches = [FloorPatch.disc(c, r, HsvRange.parse(YELLOW).centre_bgr()) for c, r in DISCS]
    return record_facing(directory, OVERLAP_POSES, patches)


@pytest_asyncio.fixture
async def fused_office(overlapping: dict[str, RecordedCamera]) -> AsyncIterator[Scene]:
    """drvs-server (metrics on) and both cameras (DEBUG: they log the requests they stop) as processes."""
    server, address = await start_server("--lease-ttl", "5", "--metrics-port", "0")
    scene = Scene(server, address, {})
    try:
        for camera_id, rec in overlapping.items():
            scene.cameras[camera_id] = await start_recorded_camera(camera_id, rec, address, "--log-level", "DEBUG")
        yield scene
    finally:
        for proc in scene.cameras.values():
            await proc.stop()
        await server.stop()


def near_disc(xy: tuple[float, float] | list[float]) -> float:
    return min(math.dist(c, xy) for c, _ in DISCS)


@pytest.mark.slow
async def test_end_to_end_fused_detect_merges_two_cameras_into_one_object_each(fused_office: Scene) -> None:
    async with DrvsClient.connect(fused_office.address, robot_id="r1") as robot:
        snapshot = await robot.snapshot(YELLOW, REGION)
        assert snapshot.final and not snapshot.camera_errors and set(snapshot.camera_ids) == {"camA", "camB"}
        assert len(snapshot.objects) == len(DISCS)  # each disc once, not once per camera
        for o in snapshot.objects:
            assert o.camera_ids == ("camA", "camB") and near_disc(o.centroid_xy) < 0.03
            assert 0 < o.uncertainty_m < 0.05
        assert not robot.listening


@pytest.mark.slow
async def test_end_to_end_track_keeps_ids_and_ends_with_a_final_snapshot(fused_office: Scene) -> None:
    async with DrvsClient.connect(fused_office.address, robot_id="r1") as robot:
        seen = [s async for s in robot.track(YELLOW, REGION, rate_hz=5, duration_s=1.2)]
        assert [s.final for s in seen][-1] is True and not any(s.final for s in seen[:-1])
        assert [s.sequence for s in seen] == list(range(len(seen))) and len(seen) >= 5
        ids = {tuple(sorted(o.track_id for o in s.objects)) for s in seen if s.objects}
        assert len(ids) == 1 and len(next(iter(ids))) == len(DISCS)  # the same two ids throughout
        for s in seen:
            for o in s.objects:
                assert near_disc(o.centroid_xy) < 0.05 and o.speed_mps < 0.1  # the discs do not move
        assert not robot.listening


@pytest.mark.slow
async def test_end_to_end_drvs_robot_track_json_and_no_listening_port(fused_office: Scene) -> None:
    seen = (-1.5, 2.2, 2.0, 5.0)  # around both discs, all of it seen (camA's floor): nothing uncovered
    args = ("--server", fused_office.address, "--filter", YELLOW, "--roi", ",".join(str(v) for v in seen))
    snapshots = await track_json(*args, "--rate", "5", "--duration", "1")
    assert snapshots[-1]["final"] is True and [s["sequence"] for s in snapshots] == list(range(len(snapshots)))
    for s in snapshots:
        assert set(s) == SNAPSHOT_KEYS and sorted(s["cameras"]) == ["camA", "camB"]
        for o in s["objects"]:
            assert set(o) == OBJECT_KEYS and near_disc(o["centroid"]) < 0.05
    assert len(snapshots[-1]["objects"]) == len(DISCS)


@pytest.mark.slow
async def test_end_to_end_leaving_a_track_early_stops_the_cameras(fused_office: Scene) -> None:
    async with DrvsClient.connect(fused_office.address, robot_id="r1") as robot:
        async with robot.track(YELLOW, REGION, rate_hz=5, duration_s=60) as track:
            async for snapshot in track:
                if snapshot.sequence == 1:
                    break
        # Each camera stops the request (the server told it on its report stream) ...
        # (Cameras know a fused request by the server's forward id: the robot's id, ':' and a counter.)
        cancelled = rf"request {re.escape(track.request_id)}:[0-9a-f]+ cancelled"
        for proc in fused_office.cameras.values():
            await proc.wait_for_line(cancelled, timeout=10)
        # ... and the server has no fused session left.
        port = metrics_port(fused_office.server)
        await poll(lambda: scrape(port), lambda values: values.get("drvs_fusion_sessions") == 0.0,
                   what="the server's fused session ended")  # fmt: skip

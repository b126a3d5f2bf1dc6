"""drvs-replay, with real files and real processes: recordings written by foxglove-sdk (through
DRVS's LiveHub, the way the server records) and by a real DrvsServer, read back independently with
mcap's own reader; damaged copies of them (cut short, bytes overwritten); and a replay into a live
view watched by a client that speaks the Foxglove WebSocket protocol as the Foxglove app does."""

from __future__ import annotations

import json
import random
import re
import struct
import subprocess
import sys
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from mcap.records import Schema
from shapely.geometry import box

from drvs.live import liveview as lv
from drvs.live.foxglove_client import FoxgloveClient
from drvs.live.replay import MAGIC, MAX_CHUNK_BYTES, MAX_EXPANSION, utc
from drvs.robot import DrvsClient
from drvs.server.server import DrvsServer
from drvs.tools.launch import LIVE_READY, ManagedProcess
from drvs.v1 import detection_pb2, geometry_pb2
from tests.helpers import YELLOW

#: 2026-01-01T00:00:00Z, the recording's first log time; messages 10 ms apart.
T0_NS = 1_767_225_600 * 10**9
STEP_NS = 10_000_000
REPORTS = 300
EVERY = 10
FLOOR_PLAN = """\
floor_plan:
  bounds: [-6, 0, 6, 8]
  walls:
    - [[-6, 7.5], [6, 7.5], [6, 8], [-6, 8]]
"""


@dataclass(frozen=True)
class Recorded:
    """A recording as mcap's own reader sees it: every message in file order."""

    path: Path
    messages: list[tuple[str, int, bytes]]  # topic, log time, data
    schemas: dict[str, str]  # topic -> schema name ("" schemaless)

    def counts(self, first: int | None = None) -> Counter[str]:
        return Counter(topic for topic, _, _ in self.messages[:first])


def read_independently(path: Path) -> Recorded:
    """What mcap's reader (its indexed reader, through the summary section) finds in the file."""
    with path.open("rb") as f:
        reader = make_reader(f)
        messages, schemas = [], {}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            messages.append((channel.topic, message.log_time, message.data))
            schemas[channel.topic] = schema.name if schema is not None else ""
    return Recorded(path, messages, schemas)


def write_recording(path: Path) -> None:
    """~1 MB of real messages on four channels, as DRVS records them (foxglove-sdk's MCAP writer,
    zstd chunks of ~256 KiB): camera reports with incompressible outlines (so the file has several
    chunks), requests, a scene, and a schemaless JSON channel."""
    rng = random.Random(7)
    hub = lv.LiveHub("test-replay", record=path)
    try:
        reports = hub.proto_channel("/drvs/rpc/reports", detection_pb2.DetectionReport)
        requests = hub.proto_channel("/drvs/rpc/requests", detection_pb2.DetectionRequest)
        tracks = hub.scene_channel("/drvs/tracks")
        notes = hub.channel_for("/test/notes", "json", None)
        for i in range(REPORTS):
            t = T0_NS + i * STEP_NS
            report = detection_pb2.DetectionReport(
                request_id=f"req-{i // EVERY}",
                camera_id=f"cam{i % 3}",
                sequence=i,
                detections=[
                    detection_pb2.Detection(outline_xy=[rng.uniform(-50, 50) for _ in range(200)], score=0.9)
                    for _ in range(4)
                ],
            )
            reports.log(report.SerializeToString(), log_time=t)
            if i % EVERY == 0:
                request = detection_pb2.DetectionRequest(
                    request_id=f"req-{i // EVERY}",
                    robot_id="r1",
                    filter_def=YELLOW,
                    region=geometry_pb2.Region(box=geometry_pb2.Box(x_lower=0, y_lower=0, x_upper=5, y_upper=5)),
                )
                requests.log(request.SerializeToString(), log_time=t)
                square = box(i * 0.01, 0.0, i * 0.01 + 0.5, 0.5)
                tracks.log(lv.scene([lv.area_entity(f"track/{i}", square, lv.rgba(1, 0, 0))]), log_time=t)
                notes.log(json.dumps({"i": i, "note": "checkpoint"}).encode(), log_time=t)
    finally:
        hub.close()


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Recorded:
    path = tmp_path_factory.mktemp("replay") / "site.mcap"
    write_recording(path)
    recorded = read_independently(path)
    assert len(recorded.counts()) == 4 and len(recorded.messages) == REPORTS + 3 * REPORTS // EVERY
    return recorded


def replay_argv(*args: str) -> list[str]:
    """drvs-replay as installed (the console script beside this interpreter), else its module."""
    script = Path(sys.executable).parent / "drvs-replay"
    return [str(script), *args] if script.exists() else [sys.executable, "-m", "drvs.live.replay", *args]


def replay(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(replay_argv(*args), capture_output=True, text=True, timeout=60, check=False)


def summary(*args: str) -> tuple[subprocess.CompletedProcess[str], dict[str, Any]]:
    done = replay("--summary", *args, "--json")
    return done, json.loads(done.stdout)


def damaged(recording: Recorded, tmp_path: Path, how: str) -> Path:
    data = recording.path.read_bytes()
    copy = tmp_path / f"{how}.mcap"
    if how == "truncated":
        copy.write_bytes(data[: int(len(data) * 0.6)])
    else:  # garbage written over the middle tenth
        start, end = int(len(data) * 0.45), int(len(data) * 0.55)
        copy.write_bytes(data[:start] + random.Random(3).randbytes(end - start) + data[end:])
    return copy


BROKEN = re.compile(
    r"^drvs-replay: (?P<file>\S+): truncated or corrupt after byte (?P<at>\d+) of (?P<size>\d+) "
    r"\((?P<read>\d+) messages read, up to (?P<up_to>\S+)\): (?P<reason>.+)$"
)


def test_the_summary_counts_every_channel_as_mcaps_own_reader_does(recording: Recorded) -> None:
    done, got = summary(str(recording.path))
    assert done.returncode == 0, done.stderr
    assert done.stderr == ""
    size = recording.path.stat().st_size
    times = [t for _, t, _ in recording.messages]
    assert got["file"] == str(recording.path) and got["bytes"] == size
    assert got["complete"] is True and got["error"] is None and got["read_bytes"] == size
    assert got["library"].startswith("foxglove-sdk") and got["profile"] == ""
    assert got["messages"] == len(recording.messages)
    assert {c["topic"]: c["messages"] for c in got["channels"]} == recording.counts()
    assert {c["topic"]: c["schema"] for c in got["channels"]} == recording.schemas
    assert {c["topic"]: c["message_encoding"] for c in got["channels"]} == {
        "/drvs/rpc/reports": "protobuf",
        "/drvs/rpc/requests": "protobuf",
        "/drvs/tracks": "protobuf",
        "/test/notes": "json",
    }
    assert got["start_ns"] == min(times) == T0_NS and got["end_ns"] == max(times)
    assert got["start"] == "2026-01-01T00:00:00.000Z" and got["end"] == utc(max(times))
    assert got["duration_s"] == pytest.approx((REPORTS - 1) * STEP_NS / 1e9)

    # The same as text: one row per channel with its schema, encoding and count.
    text = replay("--summary", str(recording.path))
    assert text.returncode == 0 and text.stderr == ""
    assert f"messages  {len(recording.messages)} on 4 channels" in text.stdout
    assert f"({size} bytes, foxglove-sdk" in text.stdout
    rows = {line.split()[0]: line.split() for line in text.stdout.splitlines() if line.startswith("/")}
    assert {topic: int(row[-1]) for topic, row in rows.items()} == recording.counts()
    assert rows["/drvs/rpc/reports"][1:3] == ["drvs.v1.DetectionReport", "protobuf"]


async def test_a_recording_drvs_server_made_is_summarised_with_what_it_recorded(tmp_path: Path) -> None:
    plan = tmp_path / "floor.yaml"
    plan.write_text(FLOOR_PLAN)
    path = tmp_path / "server.mcap"
    server = DrvsServer("127.0.0.1:0")
    server.show(record=path, floor_plan=plan)
    await server.start()
    try:
        async with DrvsClient.connect(server.address, robot_id="replayer") as drvs:
            for _ in range(3):
                await drvs.snapshot(YELLOW, (0, 0, 5, 5))
    finally:
        await server.stop()  # finishes the file: its summary and index
    recorded = read_independently(path)
    done, got = summary(str(path))
    assert done.returncode == 0, done.stderr
    assert got["complete"] and got["messages"] == len(recorded.messages)
    counts = {c["topic"]: c["messages"] for c in got["channels"]}
    assert counts == recorded.counts()
    assert counts["/drvs/rpc/requests"] == counts["/drvs/rpc/replies"] == 3 and counts["/drvs/floor_plan"] >= 1
    assert {c["topic"]: c["schema"] for c in got["channels"]}["/drvs/rpc/replies"] == "drvs.v1.DetectionReply"


@pytest.mark.parametrize("how", ["truncated", "overwritten"])
def test_a_damaged_recording_is_summarised_up_to_where_it_breaks(recording: Recorded, tmp_path: Path, how: str) -> None:
    path = damaged(recording, tmp_path, how)
    size = path.stat().st_size
    done, got = summary(str(path))
    assert done.returncode == 1
    lines = done.stderr.splitlines()
    assert len(lines) == 1 and "Traceback" not in done.stderr
    error = BROKEN.match(lines[0])
    assert error is not None, lines[0]
    at, read = int(error["at"]), int(error["read"])
    assert error["file"] == str(path) and int(error["size"]) == size
    assert 8 < at < (size if how == "truncated" else int(size * 0.45) + 1)
    # What could be read: a first part of the file, in order, chunk by whole chunk, and no more.
    assert 0 < read < len(recording.messages)
    assert got["messages"] == read and got["read_bytes"] == at
    assert got["complete"] is False and got["error"] == error["reason"]
    assert {c["topic"]: c["messages"] for c in got["channels"]} == recording.counts(read)
    assert error["up_to"] == utc(recording.messages[read - 1][1]) == got["end"]
    if how == "truncated":
        assert error["reason"] == f"the file ends inside a record that starts at byte {at}"
    else:
        assert "chunk" in error["reason"]

    # The text summary says the same, before the error.
    text = replay("--summary", str(path))
    assert text.returncode == 1 and text.stderr == done.stderr
    assert f"messages  {read} on 4 channels" in text.stdout
    assert f"read      {at} of {size} bytes: truncated or corrupt" in text.stdout


def test_a_file_that_is_not_a_recording_gets_one_line_naming_it(tmp_path: Path) -> None:
    text = tmp_path / "notes.mcap"
    text.write_text("these are not the bytes you are looking for\n")
    missing = tmp_path / "missing.mcap"
    for path, why in [(text, "not an MCAP file"), (missing, "no such file")]:
        for args in (["--summary", str(path)], [str(path), "--foxglove", "127.0.0.1:0", "--no-wait"]):
            done = replay(*args)
            assert done.returncode == 2, (args, done.stderr)
            assert done.stderr.splitlines() == [done.stderr.strip()], done.stderr  # one line
            assert done.stderr.startswith(f"drvs-replay: {path}: {why}") and "Traceback" not in done.stderr
            assert "live view on" not in done.stdout


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["--speed", "-1"], "--speed: -1 is not a speed"),
        (["--speed", "fast"], "--speed: invalid float value"),
        (["--json"], "--json goes with --summary"),
        (["--summary", "--loop"], "--summary plays nothing: --loop"),
        (["--foxglove", "127.0.0.1:99999"], "--foxglove"),
    ],
)
def test_bad_flags_are_refused_with_a_clear_message(recording: Recorded, args: list[str], says: str) -> None:
    done = replay(str(recording.path), *args)
    assert done.returncode == 2
    assert says in done.stderr and "Traceback" not in done.stderr
    assert "live view on" not in done.stdout


async def test_replay_into_a_live_view_delivers_every_message_with_its_bytes_and_time(recording: Recorded) -> None:
    proc = await ManagedProcess(
        "replay", replay_argv(str(recording.path), "--foxglove", "127.0.0.1:0", "--speed", "0")
    ).start()
    try:
        url = (await proc.wait_for_line(LIVE_READY, timeout=20)).group(1)
        client = await FoxgloveClient.connect(url)
        try:
            assert "time" in client.server_info["capabilities"]  # the app's clock follows the recording
            channels = await client.wait_for_topics(recording.counts())
            # Each channel as recorded: encoding and schema (protobuf schemas byte for byte).
            with recording.path.open("rb") as f:
                summary_ = make_reader(f).get_summary()
            assert summary_ is not None
            recorded_channels = {c.topic: c for c in summary_.channels.values()}
            for topic, channel in channels.items():
                assert channel.encoding == recorded_channels[topic].message_encoding
                schema: Schema = summary_.schemas[recorded_channels[topic].schema_id]
                if channel.encoding == "protobuf":
                    assert (channel.schema_name, channel.schema_encoding, channel.schema) == (
                        schema.name,
                        schema.encoding,
                        schema.data,
                    )
            # Nothing is played before a client subscribes; then all of it, in order.
            assert not any("played" in line for line in proc.lines)
            await client.subscribe(channels.values())
            got: dict[str, list[tuple[int, bytes]]] = {}
            for _ in recording.messages:
                message = await client.next_message(timeout=15)
                got.setdefault(message.channel.topic, []).append((message.log_time_ns, message.data))
            assert client.dropped == 0
            want: dict[str, list[tuple[int, bytes]]] = {}
            for topic, t, data in recording.messages:
                want.setdefault(topic, []).append((t, data))
            assert got == want
            await proc.wait_for_line(rf"played {len(recording.messages)} messages", timeout=15)
        finally:
            await client.close()
        # The view stays open while a client watches it; once it has gone, drvs-replay exits.
        assert await proc.wait(timeout=15) == 0
    finally:
        await proc.stop()


async def test_a_damaged_recording_plays_what_can_be_read_then_says_where_it_broke(
    recording: Recorded, tmp_path: Path
) -> None:
    path = damaged(recording, tmp_path, "truncated")
    async with ManagedProcess(
        "replay", replay_argv(str(path), "--foxglove", "127.0.0.1:0", "--speed", "0", "--no-wait")
    ) as proc:
        assert await proc.wait(timeout=20) == 1
    played = next(int(m[1]) for line in proc.lines if (m := re.search(r"played (\d+) messages", line)))
    errors = [m for line in proc.lines if (m := BROKEN.match(line))]
    assert len(errors) == 1 and errors[0]["file"] == str(path)
    assert 0 < played == int(errors[0]["read"]) < len(recording.messages)
    assert not any("Traceback" in line for line in proc.lines)


async def test_playback_keeps_the_recordings_pace_divided_by_speed(recording: Recorded) -> None:
    async with ManagedProcess(
        "replay", replay_argv(str(recording.path), "--foxglove", "127.0.0.1:0", "--speed", "4", "--no-wait")
    ) as proc:
        assert await proc.wait(timeout=20) == 0
    span_s = (REPORTS - 1) * STEP_NS / 1e9
    line = next(m for line in proc.lines if (m := re.search(r"played (\d+) messages .* in ([\d.]+) s", line)))
    assert int(line[1]) == len(recording.messages)
    assert float(line[2]) >= span_s / 4 - 0.001  # paced by the log times, never ahead of them


async def test_loop_plays_again_and_sigterm_stops_it_cleanly_at_any_point(recording: Recorded) -> None:
    # Waiting for a client: SIGTERM ends it, nothing played.
    waiting = await ManagedProcess("replay", replay_argv(str(recording.path), "--foxglove", "127.0.0.1:0")).start()
    try:
        await waiting.wait_for_line(r"waiting for a client to subscribe", timeout=20)
    finally:
        assert await waiting.stop() == 0
    assert waiting.lines[-1] == "drvs-replay: stopped"
    assert not any("played" in line or "Traceback" in line for line in waiting.lines)

    # Looping: the whole recording each pass, until SIGTERM.
    looping = await ManagedProcess(
        "replay", replay_argv(str(recording.path), "--foxglove", "127.0.0.1:0", "--speed", "0", "--no-wait", "--loop")
    ).start()
    try:
        await looping.wait_for_line(r"from the start again \(pass 3\)", timeout=20)
    finally:
        assert await looping.stop() == 0
    passes = [int(m[1]) for line in looping.lines if (m := re.search(r"played (\d+) messages", line))]
    assert len(passes) >= 2 and set(passes) == {len(recording.messages)}
    assert looping.lines[-1] == "drvs-replay: stopped"
    assert not any("Traceback" in line for line in looping.lines)


def write_bomb(path: Path, compression: str, size: int, claimed: int, chunks: int = 1) -> None:
    """A small MCAP file of `chunks` chunks that each decompress to `size` bytes and claim `claimed`:
    one record of an opcode readers skip (0x80), its length, then zeros."""
    import lz4.frame  # type: ignore[import-untyped]
    import zstandard
    from mcap.data_stream import RecordBuilder
    from mcap.records import Chunk, DataEnd, Footer, Header

    block = bytes(1 << 20)
    head = struct.pack("<BQ", 0x80, size - 9)
    if compression == "zstd":
        zstd = zstandard.ZstdCompressor(level=3).compressobj()
        data = zstd.compress(head + block[9:]) + b"".join(zstd.compress(block) for _ in range(1, size >> 20))
        data += zstd.flush()
    else:
        lz4c = lz4.frame.LZ4FrameCompressor()
        data = lz4c.begin() + lz4c.compress(head + block[9:])
        data += b"".join(lz4c.compress(block) for _ in range(1, size >> 20)) + lz4c.flush()
    out = RecordBuilder()
    out.write(MAGIC)
    Header(profile="", library="a bomb").write(out)
    for _ in range(chunks):
        Chunk(
            compression=compression,
            data=data,
            message_start_time=T0_NS,
            message_end_time=T0_NS,
            uncompressed_crc=0,
            uncompressed_size=claimed,
        ).write(out)
    DataEnd(data_section_crc=0).write(out)
    Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(out)
    out.write(MAGIC)
    path.write_bytes(out.end())  # type: ignore[no-untyped-call]


@pytest.mark.parametrize(
    ("compression", "size", "claimed"),
    [
        ("zstd", 1 << 30, (1 << 30) - 1),  # claims (under the old 1 GiB limit) what it holds: 1 GiB of zeros
        ("zstd", 1 << 30, 1000),  # claims 1000 bytes, holds 1 GiB
        ("lz4", 256 << 20, 1000),
    ],
)
def test_a_compression_bomb_is_refused_naming_the_file_and_the_limit_in_bounded_memory(
    tmp_path: Path, compression: str, size: int, claimed: int
) -> None:
    path = tmp_path / f"bomb-{compression}.mcap"
    write_bomb(path, compression, size, claimed)
    assert path.stat().st_size < 2 << 20  # a small file
    # drvs-replay in a process of its own, whose peak memory its parent reads when it ends.
    measure = (
        "import resource, subprocess, sys; "
        "done = subprocess.run(sys.argv[1:], capture_output=True, text=True); "
        "sys.stdout.write(f'{done.returncode}\\n{resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss}\\n'); "
        "sys.stdout.write(done.stderr)"
    )
    done = subprocess.run(
        [sys.executable, "-c", measure, *replay_argv("--summary", str(path))],
        capture_output=True,
        text=True,
        timeout=60,
    )
    code, peak_kib, *stderr = done.stdout.splitlines()
    assert int(peak_kib) < 128 * 1024, f"drvs-replay took {int(peak_kib) >> 10} MiB on a {path.stat().st_size} B file"
    assert int(code) == 1 and len(stderr) == 1, done.stdout
    assert stderr[0].startswith(f"drvs-replay: {path}: truncated or corrupt after byte "), stderr
    assert f"(no message read): a {compression} chunk " in stderr[0], stderr
    assert f"over the limit of {MAX_CHUNK_BYTES} bytes a chunk may decompress to" in stderr[0], stderr


def test_chunks_that_together_decompress_past_the_files_budget_are_refused(tmp_path: Path) -> None:
    """Each chunk within its own limit (20 MiB, as claimed), but a 3 KB file may decompress to at most
    MAX_CHUNK_BYTES in all (1000 times its size is less): the second chunk is refused, naming what
    was left of that budget."""
    path = tmp_path / "many.mcap"
    write_bomb(path, "zstd", 20 << 20, 20 << 20, chunks=3)
    assert path.stat().st_size * MAX_EXPANSION < MAX_CHUNK_BYTES
    done = replay("--summary", str(path))
    assert done.returncode == 1 and "Traceback" not in done.stderr, done.stderr
    left = MAX_CHUNK_BYTES - (20 << 20)
    assert done.stderr.startswith(f"drvs-replay: {path}: truncated or corrupt after byte "), done.stderr
    assert f"claims {20 << 20} bytes uncompressed: over the limit of {left} bytes" in done.stderr, done.stderr

"""drvs-replay: play a recording (an MCAP file from `drvs-server --record` or `drvs-office`) back into
a Foxglove live view, or say what it holds.

    drvs-replay FILE.mcap [--foxglove [HOST:]PORT] [--speed X] [--loop] [--no-wait]
    drvs-replay --summary FILE.mcap [--json]
    drvs-replay FILE.mcap --rosbag2 OUT/     (drvs.ros2.bag; pip install 'drvs[ros2]')

Playing: a live view on ws://HOST:PORT (default 127.0.0.1:8765; port 0 picks a free one, and the
line `drvs-replay: live view on ws://HOST:PORT` says which) advertises one channel per recorded
topic, with the recording's message encoding, schema and metadata, and logs every message's bytes
unchanged with its original log time, at the pace of the recording's log times divided by --speed
(default 1; 0 plays as fast as it can, and a client that falls more than `BACKLOG` messages behind
loses the oldest). The view has Foxglove's `time` capability: the app's clock follows the
recording's time (and jumps back when --loop starts again), so what it draws expires as it did live.
Playback starts once a client subscribes to a channel (and `SETTLE_S` has passed with no new
subscription, so panels that subscribe together all get the start); --no-wait starts at once. At
the end the view stays open while a client is still subscribed (what was sent reaches it, and the
app keeps showing the last state), then drvs-replay exits; --loop plays it again instead (a damaged
file is played once: it ends at its break).
Ctrl-C or SIGTERM stops it cleanly at any point.

Summary (--summary): every channel (topic, schema name, message encoding, message count), the total,
the first and last log times (UTC) and the span between them, the file's size. --json prints one
JSON object instead:

    file        the path as given
    bytes       the file's size
    library     the writer's name from the MCAP header ("" when it has none)
    profile     the MCAP profile ("" for DRVS's recordings)
    complete    true when the file was read to its footer and closing magic without a fault
    read_bytes  how far it could be read: the end of the last record read whole (== bytes when complete)
    messages    messages read
    start_ns, end_ns        the earliest and latest log time read, in ns since the Unix epoch (null: none)
    start, end              the same as UTC ISO 8601 with milliseconds ("...Z"; null: none)
    duration_s  end - start in seconds (0 without messages)
    channels    a list, in channel id order, of {id, topic, schema, schema_encoding,
                message_encoding, metadata, messages}; schema and schema_encoding are "" for a
                schemaless channel
    error       null, or why the file could not be read to the end (REASON in the line on stderr)

Reading: the data section is read record by record with mcap's StreamReader (chunks decompressed
one at a time, their CRCs and the data section's checked), in file order, never trusting the
summary section, which a truncated file does not have. A file that breaks (cut short, bytes
overwritten) is read up to the break: what was read is summarised (or played), then stderr says

    drvs-replay: FILE: truncated or corrupt after byte N of SIZE (M messages read, up to TIME): REASON

N is the offset where the last record read whole ends: everything before it was read and checked;
the break is in the record that starts there or later (REASON says which and why). A chunk that
decompresses past what it claims, or past `MAX_CHUNK_BYTES`, or all chunks past `MAX_EXPANSION`
times the file's size, is such a break: decompression stops there, so a compression bomb costs no
memory, and REASON names the limit. Chunks are
checked whole, by their CRC, so a damaged chunk's messages are all left out, and M counts only
messages that passed. TIME is the latest log time among them. After the data section, the summary
section must match its CRC and its message count the data section's, or that is reported the same
way (all messages read, N where the summary starts).

Exit codes: 0 read (and played) to the end; 1 truncated or corrupt (what could be read was
summarised or played); 2 a bad flag, a missing or unreadable file, or a file that is not MCAP.
"""

from __future__ import annotations

import argparse
import io
import json
import math
import os
import signal
import struct
import sys
import threading
import time
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import datetime, timedelta, timezone
from pathlib import Path
from types import FrameType
from typing import IO, TYPE_CHECKING, Any

from drvs.core.errors import DrvsError

if TYPE_CHECKING:
    from mcap.records import Footer, McapRecord, Message, Schema, Statistics

    from drvs.live.liveview import LiveHub

PROG = "drvs-replay"
#: Where the live view listens unless --foxglove says otherwise (Foxglove's default connection).
DEFAULT_LISTEN = "127.0.0.1:8765"
#: MCAP's magic bytes, at the start and the end of every MCAP file.
MAGIC = b"\x89MCAP0\r\n"
#: While waiting for the next message's time, the app's clock is sent this often (seconds, wall).
TICK_S = 0.1
#: After a client's first subscription, playback starts once this long passes with no new one.
SETTLE_S = 0.5
#: How often the main thread looks up from a wait (for subscriptions, for clients to leave).
POLL_S = 0.2
#: Messages a slow client may fall behind by before the oldest are dropped for it.
BACKLOG = 10_000
#: A chunk claiming or decompressing to more than this is refused (DRVS writes ~256 KiB chunks,
#: and records no message over drvs.live.liveview.MAX_RECORDED_BYTES): a compression bomb stops here.
MAX_CHUNK_BYTES = 32 << 20
#: All of a file's chunks together may decompress to at most this many times the file's size (or
#: MAX_CHUNK_BYTES, whichever is more): many small bombs stop too. DRVS's recordings compress ~5-20x.
MAX_EXPANSION = 1000
EXIT_OK, EXIT_BROKEN, EXIT_UNREADABLE = 0, 1, 2


class Unreadable(DrvsError):
    """The file is missing, unreadable, or not MCAP at all (exit 2)."""


class Corrupt(Exception):
    """A record inside the file that cannot be right (the reason is the message)."""


@dataclass
class Topic:
    """One recorded channel and the messages read of it."""

    id: int
    topic: str
    message_encoding: str
    schema: Schema | None
    metadata: dict[str, str]
    messages: int = 0

    def as_json(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "topic": self.topic,
            "schema": self.schema.name if self.schema else "",
            "schema_encoding": self.schema.encoding if self.schema else "",
            "message_encoding": self.message_encoding,
            "metadata": dict(self.metadata),
            "messages": self.messages,
        }


@dataclass
class Recording:
    """What has been read of one MCAP file so far (`messages()` fills it in as it reads)."""

    path: Path
    size: int
    library: str = ""
    profile: str = ""
    channels: dict[int, Topic] = field(default_factory=dict)
    messages: int = 0
    start_ns: int | None = None
    end_ns: int | None = None
    #: The end of the last record read whole: how far the file could be read.
    read_bytes: int = 0
    #: Read to its footer and closing magic, every check passed.
    complete: bool = False
    error: str | None = None

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) / 1e9 if self.start_ns is not None and self.end_ns is not None else 0.0

    def broken(self) -> str:
        """The error line for a file that could not be read to the end."""
        read = (
            f"{self.messages} messages read, up to {utc(self.end_ns)}"
            if self.messages and self.end_ns is not None
            else "no message read"
        )
        return (
            f"{PROG}: {self.path}: truncated or corrupt after byte {self.read_bytes} of {self.size} "
            f"({read}): {self.error}"
        )

    def as_json(self) -> dict[str, Any]:
        return {
            "file": str(self.path),
            "bytes": self.size,
            "library": self.library,
            "profile": self.profile,
            "complete": self.complete,
            "read_bytes": self.read_bytes,
            "messages": self.messages,
            "start_ns": self.start_ns,
            "end_ns": self.end_ns,
            "start": utc(self.start_ns) if self.start_ns is not None else None,
            "end": utc(self.end_ns) if self.end_ns is not None else None,
            "duration_s": round(self.duration_s, 9),
            "channels": [c.as_json() for _, c in sorted(self.channels.items())],
            "error": self.error,
        }


def utc(ns: int | None) -> str:
    """Nanoseconds since the Unix epoch as UTC ISO 8601 with milliseconds: 2026-01-02T03:04:05.678Z."""
    if ns is None:
        return "-"
    t = datetime(1970, 1, 1, tzinfo=timezone.utc) + timedelta(microseconds=ns // 1000)
    return t.isoformat(timespec="milliseconds").replace("+00:00", "Z")


def open_recording(path: Path) -> Recording:
    """The file's size once its magic says it is MCAP; Unreadable (naming it) when it is not."""
    try:
        with path.open("rb") as f:
            head = f.read(len(MAGIC))
            size = os.fstat(f.fileno()).st_size
    except FileNotFoundError:
        raise Unreadable(f"{path}: no such file") from None
    except IsADirectoryError:
        raise Unreadable(f"{path}: is a directory, not an MCAP file") from None
    except OSError as exc:
        raise Unreadable(f"{path}: cannot read it: {exc.strerror or exc}") from None
    if head != MAGIC:
        what = "it is empty" if size == 0 else "it does not start with MCAP's magic bytes"
        raise Unreadable(f"{path}: not an MCAP file ({what})")
    return Recording(path, size)


def messages(rec: Recording) -> Iterator[tuple[Topic, Message]]:
    """Every message of the file's data section in file order, with its channel. `rec` is updated as
    it reads (channels, counts, times, read_bytes); at a break the iteration ends with `rec.error`
    set, at the end with `rec.complete` set."""
    from mcap.records import Channel, Chunk, DataEnd, Footer, Header, Message, Schema, Statistics
    from mcap.stream_reader import StreamReader

    schemas: dict[int, Schema] = {}
    statistics: Statistics | None = None
    footer: Footer | None = None
    data_end = 0

    def take(record: McapRecord) -> Message | None:
        nonlocal statistics
        if isinstance(record, Message):
            topic = rec.channels.get(record.channel_id)
            if topic is None:
                raise Corrupt(f"a message on channel {record.channel_id}, which no Channel record defined before it")
            return record
        if isinstance(record, Header):
            rec.library, rec.profile = record.library, record.profile
        elif isinstance(record, Schema):
            schemas.setdefault(record.id, record)
        elif isinstance(record, Channel) and record.id not in rec.channels:
            schema = schemas.get(record.schema_id) if record.schema_id else None
            if record.schema_id and schema is None:
                raise Corrupt(
                    f"channel {record.id} ({record.topic}) names schema {record.schema_id}, "
                    "which no Schema record defined before it"
                )
            rec.channels[record.id] = Topic(
                record.id, record.topic, record.message_encoding, schema, dict(record.metadata)
            )
        elif isinstance(record, Statistics):
            statistics = record
        return None

    def count(message: Message) -> Topic:
        topic = rec.channels[message.channel_id]
        topic.messages += 1
        rec.messages += 1
        t = message.log_time
        rec.start_ns = t if rec.start_ns is None else min(rec.start_ns, t)
        rec.end_ns = t if rec.end_ns is None else max(rec.end_ns, t)
        return topic

    rec.read_bytes = len(MAGIC)  # open_recording read it
    budget = [max(MAX_CHUNK_BYTES, rec.size * MAX_EXPANSION)]  # bytes all chunks may still decompress to
    with rec.path.open("rb") as f:
        reader = StreamReader(f, emit_chunks=True, validate_crcs=True, record_size_limit=rec.size)
        try:
            for record in reader.records:
                for inner in _chunk_records(record, budget) if isinstance(record, Chunk) else (record,):
                    message = take(inner)
                    if message is not None:
                        yield count(message), message
                rec.read_bytes = f.tell()
                if isinstance(record, DataEnd):
                    data_end = rec.read_bytes
                footer = record if isinstance(record, Footer) else None
            rec.read_bytes = f.tell()
            assert footer is not None  # the reader stops at the footer, and only there
            problem = _check_summary(f, rec, footer, statistics, data_end)
        except Exception as exc:  # a break anywhere: every library error, a bad length, a bad string ...
            rec.error = _reason(exc, f, rec, footer is not None)
            return
    if problem is not None:
        rec.read_bytes, rec.error = problem
        return
    rec.complete = True


def _check_summary(
    f: IO[bytes], rec: Recording, footer: Footer, statistics: Statistics | None, data_end: int
) -> tuple[int, str] | None:
    """(how far the file is good, why) when the summary section does not match its CRC or the
    data section; None when it does (or the file has none)."""
    if footer.summary_start and footer.summary_crc:
        # The CRC covers the summary section and the footer up to its own summary_crc field.
        f.seek(footer.summary_start)
        covered = f.read(rec.size - len(MAGIC) - 4 - footer.summary_start)
        if zlib.crc32(covered) != footer.summary_crc:
            return footer.summary_start, "the summary section's CRC does not match its contents"
    if statistics is not None and statistics.message_count != rec.messages:
        return (
            data_end,
            f"its summary counts {statistics.message_count} messages, its data section holds {rec.messages}",
        )
    return None


def _chunk_records(chunk: Any, budget: list[int]) -> Iterator[McapRecord]:
    """A chunk's records, decompressed (never past what it claims, nor past MAX_CHUNK_BYTES or what is
    left of the file's `budget` [bytes], which it spends) and CRC-checked whole first."""
    from mcap.data_stream import ReadDataStream
    from mcap.opcode import Opcode
    from mcap.records import Channel, Message, Schema

    limit = min(MAX_CHUNK_BYTES, budget[0])
    if chunk.uncompressed_size > limit:
        raise Corrupt(_too_big(chunk, f"claims {chunk.uncompressed_size} bytes uncompressed", limit))
    try:
        data = _decompress(chunk, chunk.uncompressed_size)
    except Corrupt:
        raise
    except Exception as exc:
        raise Corrupt(f"a {chunk.compression or 'plain'} chunk does not decompress ({exc})") from exc
    if len(data) > chunk.uncompressed_size:
        what = f"decompresses to more than the {chunk.uncompressed_size} bytes it claims"
        raise Corrupt(_too_big(chunk, what, limit))
    if len(data) != chunk.uncompressed_size:
        raise Corrupt(f"a chunk decompresses to {len(data)} bytes, not the {chunk.uncompressed_size} it claims")
    budget[0] -= len(data)
    if chunk.uncompressed_crc and zlib.crc32(data) != chunk.uncompressed_crc:
        raise Corrupt(f"a chunk's CRC does not match its contents (expected {chunk.uncompressed_crc})")
    stream, length = ReadDataStream(io.BytesIO(data)), len(data)
    while stream.count < length:
        opcode = stream.read1()
        size = stream.read8()
        start = stream.count
        if size > length - start:
            raise Corrupt(f"a record in a chunk runs past the chunk's end ({size} bytes, {length - start} left)")
        record: McapRecord | None = None
        if opcode == Opcode.MESSAGE:
            if size < 22:
                raise Corrupt(f"a message record of {size} bytes, shorter than its header")
            record = Message.read(stream, size)
        elif opcode == Opcode.CHANNEL:
            record = Channel.read(stream)
        elif opcode == Opcode.SCHEMA:
            record = Schema.read(stream)
        else:
            stream.read(size)
        rest = size - (stream.count - start)
        if rest < 0:
            raise Corrupt(f"a record in a chunk is longer than its length says (opcode {opcode:#x})")
        stream.read(rest)
        if record is not None:
            yield record


def _too_big(chunk: Any, what: str, limit: int) -> str:
    return (
        f"a {chunk.compression or 'plain'} chunk {what}: over the limit of {limit} bytes a chunk may "
        f"decompress to (at most {MAX_CHUNK_BYTES} each, {MAX_EXPANSION} times the file's size in all)"
    )


def _decompress(chunk: Any, claimed: int) -> bytes:
    """The chunk's data decompressed, stopping one byte past `claimed` (so a chunk that lies about its
    size, as a compression bomb does, never takes more memory than it claimed)."""
    if chunk.compression == "zstd":
        import zstandard

        out = bytearray()
        with zstandard.ZstdDecompressor().stream_reader(io.BytesIO(chunk.data), read_across_frames=True) as reader:
            while len(out) <= claimed and (piece := reader.read(min(claimed + 1 - len(out), 1 << 20))):
                out += piece
        return bytes(out)
    if chunk.compression == "lz4":
        import lz4.frame  # type: ignore[import-untyped]

        return bytes(lz4.frame.LZ4FrameDecompressor().decompress(chunk.data, max_length=claimed + 1))
    if chunk.compression:
        raise Corrupt(f"a chunk compressed with {chunk.compression!r}, which MCAP readers do not know")
    return bytes(chunk.data)


def _reason(exc: Exception, f: IO[bytes], rec: Recording, footer: bool) -> str:
    """Why the file could not be read on (for the error line)."""
    from mcap.exceptions import EndOfFile, InvalidMagic, RecordLengthLimitExceeded
    from mcap.stream_reader import CRCValidationError

    if isinstance(exc, EndOfFile) or (isinstance(exc, struct.error) and f.tell() >= rec.size):
        if footer:
            return "the file ends inside its closing magic bytes"
        if f.tell() > rec.read_bytes:
            return f"the file ends inside a record that starts at byte {rec.read_bytes}"
        return "the file ends without MCAP's footer: the recording was not closed"
    if isinstance(exc, InvalidMagic):
        return "the file does not end with MCAP's magic bytes"
    if isinstance(exc, RecordLengthLimitExceeded):
        at = rec.read_bytes
        return f"the record at byte {at} claims more bytes than the file holds: cut short, or a damaged length ({exc})"
    if isinstance(exc, UnicodeDecodeError):
        return f"a record holds a name that is not UTF-8 ({exc})"
    if isinstance(exc, Corrupt):
        return str(exc)
    if isinstance(exc, CRCValidationError):
        return f"the data section's CRC does not match its contents ({exc})"
    return f"{type(exc).__name__}: {exc}"


def scan(path: Path) -> Recording:
    """Read the whole file (Unreadable when it is not MCAP at all)."""
    rec = open_recording(path)
    for _ in messages(rec):
        pass
    return rec


def summary_text(rec: Recording) -> str:
    lines = [f"file      {rec.path} ({rec.size} bytes, {rec.library or 'no writer named'})"]
    if not rec.complete:
        lines.append(f"read      {rec.read_bytes} of {rec.size} bytes: truncated or corrupt (see the error)")
    lines.append(f"messages  {rec.messages} on {len(rec.channels)} channels")
    if rec.start_ns is not None:
        lines.append(f"time      {utc(rec.start_ns)} .. {utc(rec.end_ns)} ({rec.duration_s:.3f} s)")
    else:
        lines.append("time      - (no message)")
    if rec.channels:
        rows = [("topic", "schema", "encoding", "messages")] + [
            (c.topic, c.schema.name if c.schema else "-", c.message_encoding, str(c.messages))
            for _, c in sorted(rec.channels.items())
        ]
        widths = [max(len(r[i]) for r in rows) for i in range(3)]
        lines.append("")
        for r in rows:
            lines.append(f"{r[0]:<{widths[0]}}  {r[1]:<{widths[1]}}  {r[2]:<{widths[2]}}  {r[3]:>8}".rstrip())
    return "\n".join(lines)


def summarise(path: Path, as_json: bool) -> int:
    rec = scan(path)
    print(json.dumps(rec.as_json(), indent=2) if as_json else summary_text(rec), flush=True)
    if rec.error is not None:
        print(rec.broken(), file=sys.stderr, flush=True)
        return EXIT_BROKEN
    return EXIT_OK


# --- playback ---------------------------------------------------------------------------------------


class _Watchers:
    """Which clients are subscribed to which channels (the server's listener calls these)."""

    def __init__(self, subscribed: threading.Event) -> None:
        self.subscribed = subscribed
        self._lock = threading.Lock()
        self._subscriptions: set[tuple[int, int]] = set()
        self.last_subscribe = 0.0

    def subscribe(self, client_id: int, channel_id: int) -> None:
        with self._lock:
            self._subscriptions.add((client_id, channel_id))
            self.last_subscribe = time.monotonic()
        self.subscribed.set()

    def unsubscribe(self, client_id: int, channel_id: int) -> None:
        with self._lock:
            self._subscriptions.discard((client_id, channel_id))

    def watched(self) -> bool:
        with self._lock:
            return bool(self._subscriptions)


def open_view(listen: tuple[str, int]) -> tuple[LiveHub, _Watchers]:
    """A LiveHub with a WebSocket server on `listen` that offers Foxglove's `time` capability (the
    app's clock then follows the recording, not the wall clock)."""
    from foxglove.websocket import Capability, ChannelView, Client, ServerListener

    from drvs.live.liveview import LiveHub

    watchers = _Watchers(threading.Event())

    class Listener(ServerListener):
        # foxglove-sdk calls these from its own threads.
        def on_subscribe(self, client: Client, channel: ChannelView) -> None:
            watchers.subscribe(client.id, channel.id)

        def on_unsubscribe(self, client: Client, channel: ChannelView) -> None:
            watchers.unsubscribe(client.id, channel.id)

    hub = LiveHub(PROG, listen=listen, capabilities=[Capability.Time], listener=Listener(), backlog=BACKLOG)
    return hub, watchers


class _Channels:
    """The hub's channel for each recorded channel: same topic, message encoding, schema, metadata."""

    def __init__(self, hub: LiveHub) -> None:
        self.hub = hub
        self._by_id: dict[int, Any] = {}
        self._first: dict[str, Topic] = {}

    def channel(self, topic: Topic) -> Any:
        channel = self._by_id.get(topic.id)
        if channel is None:
            channel = self._by_id[topic.id] = self._make(topic)
        return channel

    def _make(self, topic: Topic) -> Any:
        import foxglove

        s = topic.schema
        schema = foxglove.Schema(name=s.name, encoding=s.encoding, data=s.data) if s is not None else None
        first = self._first.setdefault(topic.topic, topic)
        if first is topic or (first.message_encoding, first.schema) == (topic.message_encoding, topic.schema):
            return self.hub.channel_for(topic.topic, topic.message_encoding, schema, topic.metadata or None)
        # The same topic recorded again with another schema: a channel of its own (Foxglove shows
        # the first of a topic's channels and flags the other).
        return foxglove.Channel(
            topic.topic,
            message_encoding=topic.message_encoding,
            schema=schema,
            metadata=topic.metadata or None,
            context=self.hub.context,
        )


def play_once(rec: Recording, hub: LiveHub, channels: _Channels, speed: float) -> float:
    """Log every readable message of the file once, paced by its log times / speed (0: at once);
    the app's clock is sent as the recording's time. Returns the wall seconds from the first
    message to the last."""
    server = hub.server
    clock = -1
    t0: int | None = None
    started = time.monotonic()
    for topic, message in messages(rec):
        t = message.log_time
        if t0 is None:
            t0, started = t, time.monotonic()
        if speed > 0:
            due = started + (t - t0) / 1e9 / speed
            while (left := due - time.monotonic()) > 0:
                time.sleep(min(left, TICK_S))
                now = min(t, t0 + int((time.monotonic() - started) * speed * 1e9))
                if server is not None and now > clock:
                    clock = now
                    server.broadcast_time(clock)
        if server is not None and t > clock:
            clock = t
            server.broadcast_time(clock)
        channels.channel(topic).log(message.data, log_time=t)
    return time.monotonic() - started if t0 is not None else 0.0


def _wait_for_watchers(watchers: _Watchers) -> None:
    """Until a client has subscribed, and SETTLE_S has passed since its last subscription."""
    while not watchers.subscribed.wait(POLL_S):
        pass
    while (left := watchers.last_subscribe + SETTLE_S - time.monotonic()) > 0:
        time.sleep(left)


def play(path: Path, listen: tuple[str, int], speed: float, loop: bool, wait: bool) -> int:
    first = scan(path)
    span = f"{first.duration_s:.1f} s from {utc(first.start_ns)}" if first.messages else "no message"
    broken = "; it breaks after them (see the end)" if first.error else ""
    print(f"{PROG}: {path}: {first.messages} messages on {len(first.channels)} channels, {span}{broken}", flush=True)
    hub, watchers = open_view(listen)
    try:
        channels = _Channels(hub)
        for _, topic in sorted(first.channels.items()):
            channels.channel(topic)  # advertised before anyone connects: a client sees every topic at once
        print(f"{PROG}: live view on {hub.url}", flush=True)
        if wait:
            print(f"{PROG}: waiting for a client to subscribe (open {hub.url} in Foxglove)", flush=True)
            _wait_for_watchers(watchers)
        passes = 0
        while True:
            passes += 1
            rec = open_recording(path)
            elapsed = play_once(rec, hub, channels, speed)
            print(
                f"{PROG}: played {rec.messages} messages ({rec.duration_s:.1f} s of recording) in {elapsed:.3f} s",
                flush=True,
            )
            if rec.error is not None:
                print(rec.broken(), file=sys.stderr, flush=True)
                code = EXIT_BROKEN
                break
            if not loop or not rec.messages:
                code = EXIT_OK
                break
            print(f"{PROG}: from the start again (pass {passes + 1})", flush=True)
        if watchers.watched():
            print(f"{PROG}: the view stays open while a client watches it (Ctrl-C ends it)", flush=True)
            while watchers.watched():
                time.sleep(POLL_S)
        return code
    except KeyboardInterrupt:
        print(f"{PROG}: stopped", flush=True)
        return EXIT_OK
    finally:
        hub.close()


# --- command line -----------------------------------------------------------------------------------


def _interrupt(signum: int, frame: FrameType | None) -> None:
    raise KeyboardInterrupt


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG,
        description="Play a DRVS recording (MCAP) back into a Foxglove live view, or summarise it.",
        epilog="Exit codes: 0 done; 1 the file is truncated or corrupt (what could be read was used); "
        "2 bad flags, a missing file, or not an MCAP file.",
    )
    p.add_argument("file", type=Path, metavar="FILE.mcap", help="a recording (drvs-server --record, drvs-office)")
    p.add_argument(
        "--summary", action="store_true", help="print its channels, counts, time span and size; no live view"
    )
    p.add_argument("--json", action="store_true", help="with --summary: one JSON object (keys: see drvs.live.replay)")
    p.add_argument(
        "--foxglove",
        metavar="[HOST:]PORT",
        help=f"where the live view listens: ws://HOST:PORT (default {DEFAULT_LISTEN}; port 0 picks a free one)",
    )
    speed = "play X times as fast as recorded (default 1; 0: as fast as possible)"
    p.add_argument("--speed", type=float, default=None, metavar="X", help=speed)
    p.add_argument("--loop", action="store_true", help="start again at the end, until Ctrl-C")
    p.add_argument("--rosbag2", type=Path, metavar="OUT", help="write its fused snapshots as a rosbag2 (drvs[ros2])")
    p.add_argument(
        "--no-wait", dest="wait", action="store_false", help="start at once, not when a client first subscribes"
    )
    return p


def main(argv: list[str] | None = None) -> int:
    p = parser()
    args = p.parse_args(argv)
    if args.summary:
        extra = [
            flag
            for flag, given in (
                ("--foxglove", args.foxglove is not None),
                ("--speed", args.speed is not None),
                ("--loop", args.loop),
                ("--no-wait", not args.wait),
            )
            if given
        ]
        if extra:
            p.error(f"--summary plays nothing: {', '.join(extra)} only go with playback")
    elif args.json:
        p.error("--json goes with --summary")
    speed = 1.0 if args.speed is None else args.speed
    if not math.isfinite(speed) or speed < 0:
        p.error(f"--speed: {args.speed:g} is not a speed: 1 plays as recorded, 2 twice as fast, 0 as fast as possible")
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, _interrupt)
    try:
        if args.rosbag2:  # the ros2 extra's exporter (tests/meta/test_layers.py, LAZY_UPWARD)
            from drvs.ros2 import rosbag2

            return rosbag2(args)
        if args.summary:
            return summarise(args.file, args.json)
        from drvs.live.liveview import parse_listen, require

        require("drvs-replay")
        listen = parse_listen(args.foxglove or DEFAULT_LISTEN, "--foxglove")
        return play(args.file, listen, speed, args.loop, args.wait)
    except DrvsError as exc:  # Unreadable, a --foxglove it cannot listen on
        print(f"{PROG}: {exc}", file=sys.stderr)
        return EXIT_UNREADABLE
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # `drvs-replay --summary FILE | head`: the reader has gone
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_BROKEN
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    sys.exit(main())

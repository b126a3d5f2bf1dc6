"""drvs-replay FILE.mcap --rosbag2 OUT/: a DRVS recording as a rosbag2, so `ros2 bag play OUT/` feeds
a Nav2 stack and Foxglove opens it with ROS 2 schemas.

The recording's fused snapshots (the server records every reply, /drvs/rpc/replies; a fused
request's replies carry them) become the messages drvs-ros2 publishes, on the same topics with the
same types, each at the log time the server recorded the reply and stamped with the snapshot's time:
/drvs/objects, /drvs/obstacles, /drvs/tracks, /drvs/markers and /diagnostics (one per snapshot).
The object type of an object without a label is its request's filter (/drvs/rpc/requests).
A recording may hold several robots' tracks: each request keeps its own markers, in namespaces
ending in /<request id>, so RViz shows them side by side.

The bag is rosbag2 version 9 in MCAP storage (rosbags' writer), each message ROS 2 CDR with the
.msg definitions embedded. It is written into a hidden folder beside OUT and renamed to OUT only
when whole: on any error (OUT exists, the recording is not MCAP or breaks part way) no OUT is left.
"""

from __future__ import annotations

import os
import shutil
import sys
from collections import Counter
from pathlib import Path
from typing import Any, Literal

from rosbags.rosbag2 import StoragePlugin, Writer

from drvs.core.errors import DrvsError, InvalidArgument
from drvs.live.replay import EXIT_BROKEN, EXIT_OK, EXIT_UNREADABLE, PROG, messages, open_recording
from drvs.ros2.cdr import snapshot_payloads
from drvs.ros2.convert import MarkerState, Style, output_topics
from drvs.ros2.types import typestore
from drvs.v1 import detection_pb2
from drvs.wire.convert import polygon_from_pb, snapshot_from_pb

REQUEST_SCHEMA = "drvs.v1.DetectionRequest"
REPLY_SCHEMA = "drvs.v1.DetectionReply"
#: rosbag2's metadata.yaml version rosbags writes.
BAG_VERSION: Literal[9] = 9


class Broken(DrvsError):
    """The recording breaks part way: no bag is written."""


class _Requests:
    """Per fused request: its filter, what its first reply said is uncovered, and its markers."""

    def __init__(self, frame_id: str) -> None:
        self.frame_id = frame_id
        self.filters: dict[str, str] = {}
        self.uncovered: dict[str, list[Any]] = {}
        self.markers: dict[str, MarkerState] = {}

    def style(self, request_id: str) -> Style:
        return Style(frame_id=self.frame_id, filter_def=self.filters.get(request_id, ""))

    def marker_state(self, request_id: str) -> MarkerState:
        return self.markers.setdefault(request_id, MarkerState(ns_suffix=f"/{request_id}"))


def export(recording: Path, out: Path, *, frame_id: str = "map", prefix: str = "/drvs") -> Counter[str]:
    """Write the recording's fused snapshots to a new rosbag2 folder `out`: messages per topic.
    InvalidArgument when `out` exists, Unreadable when the recording is not MCAP, Broken when it
    breaks part way (nothing is left at `out` then)."""
    if out.exists():
        raise InvalidArgument(f"--rosbag2: {out} exists: give a folder that does not, rosbag2 makes it")
    if not out.parent.is_dir():
        raise InvalidArgument(f"--rosbag2: {out.parent} is not a folder")
    rec = open_recording(recording)
    partial = out.parent / f".{out.name}.partial-{os.getpid()}"
    shutil.rmtree(partial, ignore_errors=True)
    store = typestore()
    written: Counter[str] = Counter()
    try:
        with Writer(partial, version=BAG_VERSION, storage_plugin=StoragePlugin.MCAP) as writer:
            connections = {
                topic: writer.add_connection(topic, kind, typestore=store)
                for topic, kind in output_topics(prefix).items()
            }
            requests = _Requests(frame_id)
            for channel, message in messages(rec):
                schema = channel.schema.name if channel.schema is not None else ""
                if schema == REQUEST_SCHEMA:
                    request = detection_pb2.DetectionRequest.FromString(message.data)
                    if request.filter_def:
                        requests.filters.setdefault(request.request_id, request.filter_def)
                    continue
                if schema != REPLY_SCHEMA:
                    continue
                reply = detection_pb2.DetectionReply.FromString(message.data)
                rid = reply.request_id
                if reply.uncovered:
                    requests.uncovered[rid] = [polygon_from_pb(p, "uncovered") for p in reply.uncovered]
                if not reply.HasField("snapshot"):
                    continue
                snapshot = snapshot_from_pb(reply.snapshot, rid, requests.uncovered.get(rid, ()))
                for topic, payload in snapshot_payloads(
                    snapshot, requests.style(rid), requests.marker_state(rid), snapshot.time, prefix
                ):
                    writer.write(connections[topic], message.log_time, bytes(payload))
                    written[topic] += 1
        if rec.error is not None:
            raise Broken(rec.broken().removeprefix(f"{PROG}: ") + "; no bag written")
        partial.rename(out)
    finally:
        shutil.rmtree(partial, ignore_errors=True)
    return written


def main(recording: Path, out: Path) -> int:
    """drvs-replay --rosbag2: export, then one line saying what was written; the exit codes of
    drvs-replay (0 written, 1 the recording breaks part way, 2 OUT exists or not a recording)."""
    try:
        written = export(recording, out)
    except Broken as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return EXIT_BROKEN
    except DrvsError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return EXIT_UNREADABLE
    counts = ", ".join(f"{topic} {n}" for topic, n in sorted(written.items())) or "no fused snapshot in it"
    print(f"{PROG}: wrote {out} (rosbag2, MCAP storage): {counts}")
    return EXIT_OK

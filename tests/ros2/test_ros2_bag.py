"""drvs-replay FILE.mcap --rosbag2 OUT/: a recording a real drvs-server process made of a real camera
and a track, converted by drvs-replay as a process, read back with rosbags' own reader message by
message against the recording as mcap's reader sees it; bad input leaves no bag behind."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from mcap.reader import make_reader
from rosbags.rosbag2 import Reader

from drvs.robot import DrvsClient
from drvs.sim.scene import RecordedCamera
from drvs.tools.launch import start_server
from drvs.v1 import detection_pb2
from drvs.wire.convert import snapshot_from_pb
from tests.fakes import start_recorded_camera
from tests.helpers import CAM1_SEEN, YELLOW
from tests.ros2.test_ros2 import STORE, TOPICS

ROOT = Path(__file__).resolve().parents[2]


def replay(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "drvs.live.replay", *args], capture_output=True, text=True, timeout=120, cwd=ROOT
    )


@pytest.mark.slow
async def test_a_recorded_track_becomes_a_rosbag2_with_every_snapshot_on_the_bridges_topics(
    recorded: dict[str, RecordedCamera], tmp_path: Path
) -> None:
    path = tmp_path / "server.mcap"
    server, address = await start_server("--record", str(path), "--lease-ttl", "5")
    try:
        camera = await start_recorded_camera("cam1", recorded["cam1"], address)
        try:
            async with DrvsClient.connect(address, robot_id="bagger") as robot:
                seen = [s async for s in robot.track(YELLOW, CAM1_SEEN, rate_hz=5, duration_s=1.0)]
        finally:
            await camera.stop()
    finally:
        await server.stop()  # finishes the file
    assert len(seen) >= 5 and any(s.objects for s in seen)
    check_conversion(path, len(seen))


def check_conversion(path: Path, count: int) -> None:
    """drvs-replay --rosbag2 of the recording at `path` (holding a track of `count` snapshots)."""
    # The recording, as mcap's own reader sees it: each reply carrying a snapshot, at its log time.
    snapshots: list[tuple[int, detection_pb2.DetectionReply]] = []
    with path.open("rb") as f:
        for schema, _, message in make_reader(f).iter_messages(log_time_order=False):
            if schema is not None and schema.name == "drvs.v1.DetectionReply":
                reply = detection_pb2.DetectionReply.FromString(message.data)
                if reply.HasField("snapshot"):
                    snapshots.append((message.log_time, reply))
    assert len(snapshots) == count

    out = path.parent / "bag"
    done = replay(str(path), "--rosbag2", str(out))
    assert done.returncode == 0, done.stderr
    assert f"wrote {out} (rosbag2, MCAP storage): " in done.stdout
    assert sorted(p.name for p in path.parent.iterdir()) == ["bag", "server.mcap"]  # nothing partial left
    assert "storage_identifier: mcap" in (out / "metadata.yaml").read_text()
    assert {p.suffix for p in out.iterdir()} == {".mcap", ".yaml"}

    with Reader(out) as bag:
        assert {c.topic: c.msgtype for c in bag.connections} == TOPICS
        assert bag.message_count == len(TOPICS) * len(snapshots)
        got: dict[str, list[tuple[int, object]]] = {t: [] for t in TOPICS}
        for connection, timestamp, data in bag.messages():
            got[connection.topic].append((timestamp, STORE.deserialize_cdr(data, connection.msgtype)))
    for topic in TOPICS:
        assert [t for t, _ in got[topic]] == [t for t, _ in snapshots], topic  # one per snapshot, at its log time

    for (_, reply), (_, objects), (_, tracks), (_, markers) in zip(
        snapshots, got["/drvs/objects"], got["/drvs/tracks"], got["/drvs/markers"], strict=True
    ):
        snap = reply.snapshot
        stamp = objects.header.stamp  # type: ignore[attr-defined]
        assert (stamp.sec, stamp.nanosec) == (snap.time.seconds, snap.time.nanos)
        assert objects.header.frame_id == "map"  # type: ignore[attr-defined]
        detections = objects.detections  # type: ignore[attr-defined]
        assert [d.id for d in detections] == [str(o.track_id) for o in snap.objects]
        read = snapshot_from_pb(snap).objects
        for d, o in zip(detections, read, strict=True):
            position = d.results[0].pose.pose.position
            assert (position.x, position.y) == (pytest.approx(o.centroid_xy[0]), pytest.approx(o.centroid_xy[1]))
            assert d.results[0].hypothesis.class_id == YELLOW  # no label: the request's filter
            assert d.results[0].hypothesis.score == pytest.approx(o.score)
        obstacles = tracks.obstacles  # type: ignore[attr-defined]
        assert [(ob.velocity.x, ob.velocity.y) for ob in obstacles] == [
            (pytest.approx(o.velocity_xy[0]), pytest.approx(o.velocity_xy[1])) for o in read
        ]
        outlines = {m.id for m in markers.markers if m.ns == f"drvs/outline/{reply.request_id}"}  # type: ignore[attr-defined]
        assert outlines == {o.track_id for o in snap.objects}


def test_bad_input_leaves_no_bag(tmp_path: Path) -> None:
    not_mcap = tmp_path / "notes.mcap"
    not_mcap.write_text("hello")
    done = replay(str(not_mcap), "--rosbag2", str(tmp_path / "out"))
    assert (done.returncode, done.stdout) == (2, "")
    assert "not an MCAP file" in done.stderr and not (tmp_path / "out").exists()

    exists = tmp_path / "exists"
    exists.mkdir()
    done = replay(str(not_mcap), "--rosbag2", str(exists))
    assert done.returncode == 2 and f"--rosbag2: {exists} exists" in done.stderr

    done = replay(str(not_mcap), "--rosbag2", str(tmp_path / "out"), "--loop")
    assert done.returncode == 2 and "not with --loop" in done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exists", "notes.mcap"]


def test_a_recording_that_breaks_part_way_leaves_no_bag(tmp_path: Path) -> None:
    from tests.live.test_replay import write_recording

    whole = tmp_path / "whole.mcap"
    write_recording(whole)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    done = replay(str(cut), "--rosbag2", str(tmp_path / "out"))
    assert done.returncode == 1, done.stderr
    assert "truncated or corrupt after byte" in done.stderr and "no bag written" in done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cut.mcap", "whole.mcap"]
    done = replay(str(whole), "--rosbag2", str(tmp_path / "out"))  # whole, with no fused request in it
    assert done.returncode == 0 and "no fused snapshot in it" in done.stdout
    with Reader(tmp_path / "out") as bag:
        assert bag.message_count == 0 and {c.topic for c in bag.connections} == set(TOPICS)

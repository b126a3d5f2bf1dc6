"""The server's live view and recording, with real processes: a drvs-server with --foxglove and
--record, drvs-camera processes on recorded footage of two overlapping cameras, a robot on raw gRPC,
and a client that speaks the Foxglove WebSocket protocol as the Foxglove app does. The recording is
read back with the `mcap` library and every message decoded with the schema embedded in the file."""

from __future__ import annotations

import asyncio
import contextlib
import json
import socket
from collections import Counter
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from grpc import aio
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from drvs.core.filters import HsvRange
from drvs.live.foxglove_client import FoxgloveClient
from drvs.live.liveview import SCENE_TOPICS, foxglove_layout
from drvs.sim.scene import FloorPatch, RecordedCamera
from drvs.tools.launch import LIVE_READY, ManagedProcess, start_server
from drvs.v1 import detection_pb2, detection_pb2_grpc, geometry_pb2
from tests.fakes import start_recorded_camera
from tests.helpers import YELLOW, record_facing
from tests.live.office_view import OfficeRun, decoder

POSES = {"left": (-1.5, 0.0, 3.0), "right": (1.5, 0.0, 3.0)}
SHARED = (0.0, 4.5)
REGION = (-4.5, 2.0, 4.5, 6.5)
RPC_TOPICS = ["/drvs/rpc/cameras", "/drvs/rpc/requests", "/drvs/rpc/replies", "/drvs/rpc/reports"]
FLOOR_PLAN = """\
floor_plan:
  bounds: [-6, 0, 6, 8]
  walls:
    - [[-6, 7.5], [6, 7.5], [6, 8], [-6, 8]]
    - [[4.8, 1.0], [5.6, 1.0], [5.6, 2.0], [4.8, 2.0]]
"""


@pytest.fixture(scope="module")
def overlap(tmp_path_factory: pytest.TempPathFactory) -> dict[str, RecordedCamera]:
    yellow = HsvRange.parse(YELLOW).centre_bgr()
    return record_facing(tmp_path_factory.mktemp("liveview"), POSES, [FloorPatch.disc(SHARED, 0.3, yellow)])


def box(region: tuple[float, float, float, float]) -> geometry_pb2.Region:
    x0, y0, x1, y1 = region
    return geometry_pb2.Region(box=geometry_pb2.Box(x_lower=x0, y_lower=y0, x_upper=x1, y_upper=y1))


@dataclass
class Site:
    server: ManagedProcess
    address: str
    url: str
    cameras: dict[str, ManagedProcess]


@contextlib.asynccontextmanager
async def site(overlap: dict[str, RecordedCamera], tmp_path: Path) -> AsyncIterator[Site]:
    """A server with a live view on a free port and a recording, and both cameras; all reaped."""
    plan = tmp_path / "floor.yaml"
    plan.write_text(FLOOR_PLAN)
    server, address = await start_server(
        "--foxglove", "127.0.0.1:0", "--record", str(tmp_path / "site.mcap"), "--floor-plan", str(plan)
    )
    cameras: dict[str, ManagedProcess] = {}
    try:
        url = next(m.group(1) for line in server.lines if (m := LIVE_READY.search(line)))
        for camera_id in POSES:
            cameras[camera_id] = await start_recorded_camera(camera_id, overlap[camera_id], address)
        yield Site(server, address, url, cameras)
    finally:
        for proc in cameras.values():
            await proc.stop()
        await server.stop()


async def updates(client: FoxgloveClient, decoders: dict[str, Any], topic: str, until: Any) -> Any:
    """Decoded messages of `topic` until one satisfies `until` (returned)."""
    while True:
        message = await client.next_message(timeout=15)
        if message.channel.topic == topic:
            decoded = decoders[topic](message.data)
            if until(decoded):
                return decoded


@pytest.mark.slow
async def test_the_live_view_shows_the_site_and_the_recording_holds_every_request_reply_and_report(
    overlap: dict[str, RecordedCamera], tmp_path: Path
) -> None:
    sent = 0
    replies: list[detection_pb2.DetectionReply] = []
    async with site(overlap, tmp_path) as s:
        client = await FoxgloveClient.connect(s.url)
        try:
            assert client.server_info["op"] == "serverInfo"
            assert "clientPublish" in client.server_info["capabilities"]  # robots publish into it
            channels = await client.wait_for_topics(["/drvs/floor_plan", "/drvs/cameras", "/drvs/rpc/cameras"])
            await client.subscribe(channels.values())
            decoders = {t: decoder(c) for t, c in channels.items()}
            walls = await updates(client, decoders, "/drvs/floor_plan", lambda u: len(u.entities) >= 2)
            assert {e.id for e in walls.entities} >= {"wall/0", "wall/1", "floor"}
            assert all(e.frame_id == "map" for e in walls.entities)
            cams = await updates(
                client,
                decoders,
                "/drvs/cameras",
                lambda u: {e.id for e in u.entities} >= {"camera/left", "camera/right"},
            )
            left = next(e for e in cams.entities if e.id == "camera/left")
            assert left.triangles and left.lines and left.texts[0].text == "left"

            # A robot: two plain single shots, then a fused continuous request on its stream.
            async with aio.insecure_channel(s.address) as channel:
                stub = detection_pb2_grpc.DetectObjectBoundaryStub(channel)
                call = stub.DetectStream()
                for i in range(2):
                    await call.write(
                        detection_pb2.DetectionRequest(
                            request_id=f"shot-{i}",
                            robot_id="r",
                            filter_def=YELLOW,
                            region=box(REGION),
                            callback_address="127.0.0.1:1",
                            report_secret=b"s" * 32,
                        )
                    )
                    sent += 1
                await call.write(
                    detection_pb2.DetectionRequest(
                        request_id="track",
                        robot_id="r",
                        filter_def=YELLOW,
                        region=box(REGION),
                        continuous=detection_pb2.ContinuousMode(rate_hz=5, duration_s=1.5),
                        fusion=detection_pb2.FusionOptions(),
                    )
                )
                sent += 1
                # The region and the fused tracks appear in the view while the request runs.
                more = await client.wait_for_topics(["/drvs/requests", "/drvs/tracks", "/drvs/detections"])
                await client.subscribe(more.values())
                decoders |= {t: decoder(c) for t, c in more.items()}
                while True:
                    reply = await asyncio.wait_for(call.read(), 15)
                    assert reply is not aio.EOF
                    replies.append(reply)
                    if reply.HasField("snapshot") and reply.snapshot.final:
                        break
                await call.done_writing()
                while (reply := await asyncio.wait_for(call.read(), 15)) is not aio.EOF:
                    replies.append(reply)
            tracks = await updates(client, decoders, "/drvs/tracks", lambda u: len(u.entities) > 0)
            track = tracks.entities[0]
            assert track.id.startswith("track/track/") and track.lifetime.ToNanoseconds() > 0
            assert "left" in dict((m.key, m.value) for m in track.metadata)["cameras"]
        finally:
            await client.close()
    # The server stopped cleanly: the recording is complete. Decode every message with its schema.
    with (tmp_path / "site.mcap").open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.chunk_count >= 1
        counts: Counter[str] = Counter()
        decoded: dict[str, list[Any]] = {}
        for schema, chan, _message, proto in reader.iter_decoded_messages():
            assert schema is not None and schema.encoding == "protobuf" and chan.message_encoding == "protobuf"
            counts[chan.topic] += 1
            decoded.setdefault(chan.topic, []).append(proto)
    assert set(counts) >= {"/drvs/floor_plan", "/drvs/cameras", "/drvs/requests", "/drvs/tracks"} | set(RPC_TOPICS)
    # Every request the robot sent, every reply it got, in the project's own schemas.
    requests = decoded["/drvs/rpc/requests"]
    assert [r.request_id for r in requests] == ["shot-0", "shot-1", "track"]
    assert all(not r.report_secret and not r.report_key for r in requests)  # no secret is recorded
    assert counts["/drvs/rpc/replies"] == len(replies) == sent + sum(r.HasField("snapshot") for r in replies)
    assert [r.SerializeToString() for r in decoded["/drvs/rpc/replies"]] == [r.SerializeToString() for r in replies]
    # The cameras' reports to the server for the fused request: from both cameras, keys cleared.
    reports = decoded["/drvs/rpc/reports"]
    assert {r.camera_id for r in reports} == {"left", "right"}
    assert all(r.request_id.startswith("track:") and not r.report_key for r in reports)
    # The registry as it changed: both cameras came, then both deregistered before the server stopped.
    registries = [sorted(c.camera_id for c in r.cameras) for r in decoded["/drvs/rpc/cameras"]]
    assert ["left", "right"] in registries and registries[-1] == []


async def test_a_camera_that_leaves_is_deleted_from_the_view(
    overlap: dict[str, RecordedCamera], tmp_path: Path
) -> None:
    async with site(overlap, tmp_path) as s, await FoxgloveClient.connect(s.url) as client:
        channels = await client.wait_for_topics(["/drvs/cameras"])
        await client.subscribe(channels.values())
        decode = decoder(channels["/drvs/cameras"])
        while True:  # both drawn
            u = decode((await client.next_message()).data)
            if {e.id for e in u.entities} >= {"camera/left", "camera/right"}:
                break
        await s.cameras["right"].stop()  # it deregisters
        while True:
            u = decode((await client.next_message()).data)
            if any(d.id == "camera/right" for d in u.deletions):
                break


@pytest.mark.slow
@pytest.mark.timeout(300)  # the run is the office's whole mission, watched: over a minute on a loaded machine
async def test_the_office_live_the_way_foxglove_sees_it_and_its_recording(default_office: OfficeRun) -> None:
    """drvs-office --foxglove: a client receives the advertised channels and the office moving (the
    walls, cameras, requests, tracks, the robot's pose and paths) while the mission runs; the run's
    run.mcap holds the same channels and agrees with result.json. (The run is shared with the
    trolley's test, tests/sim/test_office_moving.py: see tests/live/office_view.py.)"""
    if default_office.live_error is not None:
        pytest.fail(default_office.live_error)
    assert default_office.seen.get("/drvs/tracks") and default_office.seen.get("/drvs/cameras")
    assert abs(default_office.pose_xs[-1] - default_office.pose_xs[0]) > 1.0 and default_office.pose_frames == ["map"]
    robot_entities = set(default_office.robot_entities)
    assert robot_entities == {"robot/sim-robot", "robot/sim-robot/planned", "robot/sim-robot/driven"}
    assert default_office.code == 0, default_office.log
    out = Path(default_office.out)
    result = json.loads((out / "result.json").read_text())
    assert result["reached_goal"] and result["recording"]["file"] == "run.mcap"
    with (out / "run.mcap").open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        counts: Counter[str] = Counter()
        last_pose = None
        tracked: set[int] = set()
        for _, channel, _, proto in reader.iter_decoded_messages():
            counts[channel.topic] += 1
            if channel.topic == "/robot/pose":
                last_pose = proto.pose.position
            if channel.topic == "/drvs/rpc/replies" and proto.HasField("snapshot"):
                tracked |= {o.track_id for o in proto.snapshot.objects}
    assert set(counts) >= set(SCENE_TOPICS) | set(RPC_TOPICS) | {"/robot/pose", "/robot/paths"}
    assert result["recording"]["bytes"] == (out / "run.mcap").stat().st_size
    # The recording ends where the robot did, and holds the tracks the robot followed.
    end = result["path"][-1]
    assert last_pose is not None and abs(last_pose.x - end[0]) < 0.05 and abs(last_pose.y - end[1]) < 0.05
    assert {t["track_id"] for t in result["tracks"]} <= tracked


@pytest.mark.parametrize(
    "what", ["busy port", "record into a folder", "record under a file", "walls that are no polygons"]
)
async def test_a_live_view_that_cannot_start_stops_the_server_before_it_serves(tmp_path: Path, what: str) -> None:
    """Exit 2 and one line naming the flag and the cause; the gRPC port was never opened."""
    plan = tmp_path / "plan.yaml"
    plan.write_text("walls: [[[0, 0], [1, 0]]]\n" if what.startswith("walls") else FLOOR_PLAN)
    under = plan / "run" / "x.mcap"  # a recording in a folder under a file
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        args = {
            "busy port": ["--foxglove", f"127.0.0.1:{port}"],
            "record into a folder": ["--record", str(tmp_path)],
            "record under a file": ["--record", str(under)],
            "walls that are no polygons": ["--foxglove", "0", "--floor-plan", str(plan)],
        }[what]
        proc = await ManagedProcess.entry_point("server", "drvs-server", "--listen", "127.0.0.1:0", *args).start()
        code = await proc.wait(timeout=30)
    output = proc.output()
    assert code == 2, output
    assert "Traceback" not in output and "listening on" not in output
    expected = {
        "busy port": f"--foxglove: cannot listen on 127.0.0.1:{port}",
        "record into a folder": f"--record: cannot write {tmp_path}",
        "record under a file": f"--record: cannot write {under}: {under.parent}: {plan} is not a folder",
        "walls that are no polygons": f"--floor-plan {plan}: walls[0]: not a simple polygon with an area",
    }[what]
    assert expected in output


def test_the_shipped_foxglove_layout_is_the_one_the_code_makes() -> None:
    """docs/foxglove-layout.json comes from drvs.live.liveview.foxglove_layout (foxglove-sdk's layouts)."""
    shipped = (Path(__file__).resolve().parents[2] / "docs" / "foxglove-layout.json").read_text()
    assert shipped == foxglove_layout(), "regenerate: python -m drvs.live.liveview > docs/foxglove-layout.json"
    panel = json.loads(shipped)["content"]["items"][0]["content"]
    assert panel["panelType"] == "ThreeDee" and set(panel["config"]["topics"]) >= set(SCENE_TOPICS)


def test_the_liveview_benchmark_takes_its_ratios_within_each_round() -> None:
    """drvs-bench liveview's figures: each ratio is a round's `live` (or `record`) over the same
    round's `off`, published as the median and [min, max] of the rounds."""
    from drvs_bench.liveview import figures

    def run(wall: float, server: float, robot: float, rec: int = 0, viewer: float = 0.0) -> dict[str, float]:
        return {"wall_s": wall, "server_cpu_s": server, "robot_cpu_s": robot, "recording_bytes": rec,
                "viewer_bytes": viewer, "viewer_channels": 11}  # fmt: skip

    runs = [
        {"off": run(20, 1.0, 0.5), "record": run(20, 1.2, 0.6, 100_000), "live": run(20, 1.5, 0.6, 100_000, 8e5)},
        {"off": run(25, 2.0, 0.5), "record": run(25, 2.2, 0.5, 125_000), "live": run(25, 2.4, 0.7, 125_000, 1e6)},
    ]
    out = figures({"runs": runs})
    assert out["live_server_cpu_s_over_off_runs"] == [1.5, 1.2]
    assert out["live_server_cpu_s_over_off_spread"] == [1.2, 1.5] and out["live_server_cpu_s_over_off"] == 1.35
    assert out["record_recording_bytes_per_s_runs"] == [5000.0, 5000.0]
    assert out["live_viewer_bytes_per_s_runs"] == [40_000.0, 40_000.0]
    assert out["record_robot_cpu_s_over_off_runs"] == [1.2, 1.0]

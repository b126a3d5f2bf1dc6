"""drvs-ros2 end to end, with no ROS installed: a real drvs-server and drvs-camera (tests/conftest.py's
office), the bridge as its own process, and a separate ROS 2 peer process (tests/fakes/ros2_peer.py) on
Cyclone DDS, all on loopback (a Cyclone configuration on `lo`, multicast off, 127.0.0.1 the only
peer; a random DDS domain per test, so nothing else on the host is heard).

What the peer receives is checked as a ROS 2 node would see it: the discovered writer's DDS topic
and type names, its QoS and data representation; and the raw sample bytes, decoded independently
with rosbags' CDR deserializer from the shipped .msg files, against the snapshots the bridge
published (drvs-ros2 --json prints each, as drvs-robot track --json does).
"""

from __future__ import annotations

import json
import math
import os
import random
import re
import socket
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from drvs.tools.launch import ManagedProcess
from tests.helpers import CAM1_SEEN, YELLOW, Office

ROOT = Path(__file__).resolve().parents[2]
MSG_DIR = ROOT / "src" / "drvs" / "ros2" / "msg"
TOPICS = {
    "/drvs/objects": "vision_msgs/msg/Detection3DArray",
    "/drvs/obstacles": "sensor_msgs/msg/PointCloud2",
    "/drvs/tracks": "nav2_dynamic_msgs/msg/ObstacleArray",
    "/drvs/markers": "visualization_msgs/msg/MarkerArray",
    "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
}
CYCLONE_LOOPBACK = """<CycloneDDS xmlns="https://cdds.io/config">
  <Domain Id="any">
    <General>
      <Interfaces><NetworkInterface name="lo"/></Interfaces>
      <AllowMulticast>false</AllowMulticast>
    </General>
    <Discovery>
      <ParticipantIndex>auto</ParticipantIndex>
      <MaxAutoParticipantIndex>32</MaxAutoParticipantIndex>
      <Peers><Peer Address="127.0.0.1"/></Peers>
    </Discovery>
  </Domain>
</CycloneDDS>
"""
HEIGHT = 0.3


def rosbags_store() -> Any:
    """A rosbags typestore of the shipped .msg files, read here on their own (not drvs.ros2.types)."""
    store = get_typestore(Stores.EMPTY)
    types: dict[str, Any] = {}
    for path in sorted(MSG_DIR.glob("*/msg/*.msg")):
        types.update(get_types_from_msg(path.read_text(), f"{path.parts[-3]}/msg/{path.stem}"))
    store.register(types)
    return store


STORE = rosbags_store()


def decode(topic: str, payload: bytes) -> Any:
    """The raw sample decoded by rosbags; serialized again by rosbags it gives the same bytes (Cyclone
    pads a sample on the wire to a multiple of 4 bytes with zeros, as rmw_cyclonedds' readers expect)."""
    assert payload[:4] == bytes([0, 1, 0, 0]), f"{topic}: not XCDR1 little-endian: {payload[:4].hex()}"
    message = STORE.deserialize_cdr(payload, TOPICS[topic])
    again = bytes(STORE.serialize_cdr(message, TOPICS[topic]))
    padding = (-len(again)) % 4
    assert payload == again + bytes(padding), f"{topic}: rosbags re-serializes differently"
    return message


@pytest.fixture
def dds(tmp_path: Path) -> Iterator[tuple[dict[str, str], int]]:
    """(environment, domain id) for every DDS process of the test."""
    config = tmp_path / "cyclonedds.xml"
    config.write_text(CYCLONE_LOOPBACK)
    env = dict(os.environ)
    env["CYCLONEDDS_URI"] = config.as_uri()
    env["PYTHONPATH"] = f"{ROOT / 'src'}:{ROOT}:{env.get('PYTHONPATH', '')}"
    env.pop("ROS_DOMAIN_ID", None)
    yield env, random.randint(100, 230)


def bridge(env: dict[str, str], *args: str) -> ManagedProcess:
    return ManagedProcess("drvs-ros2", [sys.executable, "-m", "drvs.ros2.cli", *args], env=env)


def peer(env: dict[str, str], *args: str) -> ManagedProcess:
    return ManagedProcess("ros2-peer", [sys.executable, "-m", "tests.fakes.ros2_peer", *args], env=env)


def listen_args(domain: int, count: int, topics: dict[str, str] = TOPICS) -> list[str]:
    return ["listen", "--domain", str(domain), "--count", str(count), *(f"--topic={t}={k}" for t, k in topics.items())]


def json_lines(proc: ManagedProcess) -> list[dict[str, Any]]:
    return [json.loads(line) for line in proc.lines if line.startswith("{")]


def seconds(stamp: Any) -> float:
    return float(stamp.sec + stamp.nanosec * 1e-9)


def box_args(region: tuple[float, float, float, float]) -> str:
    return ",".join(str(v) for v in region)


@pytest.mark.slow
@pytest.mark.office_cameras("cam1")
async def test_a_peer_process_sees_the_track_on_ros2_topics_as_rmw_cyclonedds_writes_them(
    office: Office, dds: tuple[dict[str, str], int]
) -> None:
    env, domain = dds
    async with peer(env, *listen_args(domain, 3)) as listener:
        await listener.wait_for_line('"ready"', timeout=30)
        async with bridge(
            env, "--server", office.address, "--filter", YELLOW, "--region", box_args(CAM1_SEEN), "--rate", "5",
            "--domain-id", str(domain), "--height", f"{YELLOW}={HEIGHT}", "--json",
        ) as ros2:  # fmt: skip
            try:
                assert await listener.wait(timeout=60) == 0, listener.tail()
            finally:
                await ros2.stop()
                print(ros2.tail())
    # Stopped (SIGTERM), the bridge closed its track: the camera stops the request (its forward id
    # is the robot's request id, ':' and a counter).
    request_id = (await ros2.wait_for_line(r"track (\S+) over POLYGON", timeout=1)).group(1)
    await office.cameras["cam1"].wait_for_line(rf"request {re.escape(request_id)}:[0-9a-f]+ cancelled", timeout=10)
    published = {round(s["time"] * 1e9): s for s in json_lines(ros2) if "objects" in s}
    assert published, ros2.tail()
    lines = json_lines(listener)

    writers = {w["writer"]["topic"]: w["writer"] for w in lines if "writer" in w}
    assert set(writers) == {"rt" + t for t in TOPICS}
    for topic, kind in TOPICS.items():
        w = writers["rt" + topic]
        package, _, name = kind.split("/")
        assert w["type"] == f"{package}::msg::dds_::{name}_"
        assert w["qos"]["Reliability"].startswith("Policy.Reliability.Reliable")
        assert w["qos"]["History"] == "Policy.History.KeepLast(depth=10)"
        assert w["qos"]["Durability"] == "Policy.Durability.Volatile"
        assert w["qos"]["DataRepresentation"] == (
            "Policy.DataRepresentation(use_cdrv0_representation=True, use_xcdrv2_representation=False)"
        )

    samples: dict[str, list[Any]] = {t: [] for t in TOPICS}
    for line in lines:
        if "topic" in line:
            samples[line["topic"]].append(decode(line["topic"], bytes.fromhex(line["payload"])))
    assert all(len(v) == 3 for v in samples.values()), {t: len(v) for t, v in samples.items()}

    for message in samples["/drvs/objects"]:
        assert message.header.frame_id == "map"
        snapshot = published[round(seconds(message.header.stamp) * 1e9)]
        objects = {str(o["track_id"]): o for o in snapshot["objects"]}
        assert len(objects) == 2 and [d.id for d in message.detections] == list(objects)
        for d in message.detections:
            o = objects[d.id]
            (result,) = d.results
            assert result.hypothesis.class_id == YELLOW and result.hypothesis.score == pytest.approx(
                o["score"], abs=1e-3
            )
            p = result.pose.pose.position
            assert (p.x, p.y, p.z) == (
                pytest.approx(o["centroid"][0], abs=1e-4),
                pytest.approx(o["centroid"][1], abs=1e-4),
                0,
            )
            assert math.sqrt(result.pose.covariance[0]) == pytest.approx(o["uncertainty_m"], abs=1e-4)
            assert result.pose.covariance[7] == result.pose.covariance[0]
            x0, y0, x1, y1 = o["bounds"]
            c, s = d.bbox.center.position, d.bbox.size
            assert (c.x, c.y, c.z) == (
                pytest.approx((x0 + x1) / 2, abs=1e-4),
                pytest.approx((y0 + y1) / 2, abs=1e-4),
                HEIGHT / 2,
            )
            assert (s.x, s.y, s.z) == (pytest.approx(x1 - x0, abs=1e-4), pytest.approx(y1 - y0, abs=1e-4), HEIGHT)

    for cloud in samples["/drvs/obstacles"]:
        snapshot = published[round(seconds(cloud.header.stamp) * 1e9)]
        assert [(f.name, f.offset, f.datatype, f.count) for f in cloud.fields] == [
            ("x", 0, 7, 1),
            ("y", 4, 7, 1),
            ("z", 8, 7, 1),
        ]
        assert cloud.point_step == 12 and cloud.height == 1 and cloud.row_step == 12 * cloud.width and cloud.width > 16
        points = [tuple(cloud.data[i : i + 12].view("<f4")) for i in range(0, len(cloud.data), 12)]
        near = {o["track_id"]: 0 for o in snapshot["objects"]}
        for x, y, z in points:
            assert z == pytest.approx(HEIGHT / 2)
            inside = [
                o["track_id"]
                for o in snapshot["objects"]
                if o["bounds"][0] - 1e-3 <= x <= o["bounds"][2] + 1e-3
                and o["bounds"][1] - 1e-3 <= y <= o["bounds"][3] + 1e-3
            ]
            assert len(inside) == 1, (x, y)
            near[inside[0]] += 1
        assert all(n >= 8 for n in near.values()), near  # an outline each, every 5 cm

    uuids = set()
    for tracks in samples["/drvs/tracks"]:
        snapshot = published[round(seconds(tracks.header.stamp) * 1e9)]
        assert len(tracks.obstacles) == len(snapshot["objects"])
        for ob, o in zip(tracks.obstacles, snapshot["objects"], strict=True):
            uuids.add(bytes(ob.uuid.uuid))
            assert (ob.position.x, ob.position.y) == (
                pytest.approx(o["centroid"][0], abs=1e-4),
                pytest.approx(o["centroid"][1], abs=1e-4),
            )
            assert (ob.velocity.x, ob.velocity.y) == (
                pytest.approx(o["velocity"][0], abs=1e-4),
                pytest.approx(o["velocity"][1], abs=1e-4),
            )
            assert ob.size.z == HEIGHT and ob.score == pytest.approx(o["score"], abs=1e-3)
    assert len(uuids) == 2  # one per track, the same in every snapshot

    for array in samples["/drvs/markers"]:
        shown = {(m.ns, m.id): m for m in array.markers}
        stamp = round(seconds(array.markers[0].header.stamp) * 1e9)
        ids = {o["track_id"] for o in published[stamp]["objects"]}
        assert {i for ns, i in shown if ns == "drvs/outline"} == ids == {i for ns, i in shown if ns == "drvs/label"}
        assert {shown[("drvs/label", i)].text for i in ids} == {f"#{i} {YELLOW}" for i in ids}
        assert all(m.action == 0 for m in array.markers)  # nothing ended

    answered = 0
    for diagnostics in samples["/diagnostics"]:
        levels = {s.name: (s.level, s.message) for s in diagnostics.status}
        assert levels.pop("drvs: region") == (0, "the whole region is seen")
        # cam1 answered, or (a period its report came too late for) is not named: never a WARN.
        assert levels in ({"drvs: camera cam1": (0, "answered")}, {}), levels
        answered += bool(levels)
    assert answered


@pytest.mark.slow
@pytest.mark.timeout(180)
async def test_the_region_topic_moves_the_track_ended_tracks_are_deleted_and_blindness_is_a_warning(
    office: Office, dds: tuple[dict[str, str], int]
) -> None:
    """Around both of cam1's discs, then (by /drvs/region) around one, then along a strip reaching
    into cam2's floor over a gap no camera sees; then cam2 crashes."""
    env, domain = dds
    wanted = {t: TOPICS[t] for t in ("/drvs/objects", "/drvs/markers", "/diagnostics")}
    async with peer(env, *listen_args(domain, 100_000, wanted)) as listener:
        await listener.wait_for_line('"ready"', timeout=30)
        async with bridge(
            env, "--server", office.address, "--filter", YELLOW, "--region", box_args(CAM1_SEEN), "--rate", "5",
            "--domain-id", str(domain),
        ) as ros2:  # fmt: skip

            async def until(topic: str, check: Callable[[Any], bool], timeout: float = 30, start: int = -1) -> Any:
                """The first sample on `topic` that passes `check`, from the peer's line `start` (default: now)."""
                pattern = f'"topic": "{topic}"'

                def scan(line: str) -> Any:
                    if pattern in line:
                        message = decode(topic, bytes.fromhex(json.loads(line)["payload"]))
                        return message if check(message) else None
                    return None

                begin = len(listener.lines) if start < 0 else start
                return await listener.wait_for(scan, f"a {topic} sample as wanted", timeout, start=begin)

            first = await until("/drvs/objects", lambda m: len(m.detections) == 2)
            before = {d.id for d in first.detections}

            # Not a polygon: refused, logged, and the track goes on over the old region.
            async with peer(env, "region", "--domain", str(domain), "--points", "1,1,2,2") as bad:
                assert await bad.wait(timeout=30) == 0, bad.tail()
            await ros2.wait_for_line(r"/drvs/region: refused.*at least three points", timeout=10)
            await until("/drvs/objects", lambda m: len(m.detections) == 2)

            changed = len(listener.lines)
            async with peer(
                env, "region", "--domain", str(domain), "--points", "1.0,2.5,2.0,2.5,2.0,3.5,1.0,3.5"
            ) as ok:
                assert await ok.wait(timeout=30) == 0, ok.tail()
            await ros2.wait_for_line("region changed to POLYGON", timeout=10)
            one = await until("/drvs/objects", lambda m: len(m.detections) == 1, start=changed)
            p = one.detections[0].results[0].pose.pose.position
            assert math.dist((p.x, p.y), (1.5, 3.0)) < 0.05
            # The tracks of the old region are deleted from RViz: each id of theirs no longer shown.
            deleting = await until("/drvs/markers", lambda m: any(k.action == 2 for k in m.markers), start=changed)
            deleted = {(k.ns, k.id) for k in deleting.markers if k.action == 2}
            still = {(k.ns, k.id) for k in deleting.markers if k.action == 0}
            assert deleted and not deleted & still and {str(i) for _, i in deleted} <= before

            # A strip from cam1's floor over the gap to cam2's: the gap is a WARN, both cameras OK.
            async with peer(
                env, "region", "--domain", str(domain), "--points", "1.0,2.5,21.0,2.5,21.0,3.5,1.0,3.5"
            ) as strip:
                assert await strip.wait(timeout=30) == 0, strip.tail()

            def gap(m: Any) -> bool:
                by = {s.name: s for s in m.status}
                return "drvs: camera cam2" in by and by["drvs: region"].level == 1

            warned = await until("/diagnostics", gap)
            by_name = {s.name: s for s in warned.status}
            unseen = {kv.key: kv.value for kv in by_name["drvs: region"].values}["uncovered_m2"]
            assert 8.0 < float(unseen) < 17.0, unseen  # the gap between the floors, x 3.8 .. 16.2 at most
            assert by_name["drvs: camera cam1"].level == 0 and by_name["drvs: camera cam2"].level == 0

            office.cameras["cam2"].kill()  # a crash: the server hears nothing more from it
            blind = await until(
                "/diagnostics", lambda m: any(s.name == "drvs: camera cam2" and s.level == 1 for s in m.status)
            )
            cam2 = next(s for s in blind.status if s.name == "drvs: camera cam2")
            assert cam2.hardware_id == "cam2" and cam2.message.split(":")[0] in ("DEADLINE_EXCEEDED", "UNAVAILABLE")
            await ros2.stop()
        await listener.stop()


@pytest.mark.slow
@pytest.mark.office_cameras("cam1")
async def test_sim_time_stamps_with_the_clock_topic_and_a_sensor_data_subscriber_matches(
    office: Office, dds: tuple[dict[str, str], int]
) -> None:
    """--use-sim-time: the stamps follow /clock (a simulator's, from 1000 s on), not the wall clock;
    a best-effort subscriber (rclcpp's SensorDataQoS) matches the reliable writers."""
    env, domain = dds
    wanted = {"/drvs/objects": TOPICS["/drvs/objects"]}
    async with (
        peer(env, "clock", "--domain", str(domain), "--start", "1000") as sim,
        peer(env, *listen_args(domain, 3, wanted), "--sensor") as listener,
    ):
        await sim.wait_for_line('"clock"', timeout=30)
        await listener.wait_for_line('"ready"', timeout=30)
        async with bridge(
            env, "--server", office.address, "--filter", YELLOW, "--region", box_args(CAM1_SEEN), "--rate", "5",
            "--domain-id", str(domain), "--use-sim-time",
        ) as ros2:  # fmt: skip
            try:
                assert await listener.wait(timeout=60) == 0, listener.tail()
            finally:
                await ros2.stop()
        await sim.stop()
    stamps = [
        seconds(decode("/drvs/objects", bytes.fromhex(line["payload"])).header.stamp)
        for line in json_lines(listener)
        if "payload" in line
    ]
    assert len(stamps) == 3
    # The first may predate the first /clock message (wall time, with a warning); the rest are sim time.
    assert all(1000 <= t < 1000 + 120 for t in stamps[1:]), stamps  # the clock's start plus this test's run
    assert stamps[1:] == sorted(stamps[1:])


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.parametrize(
    ("args", "code", "message"),
    [
        (["--filter", "zebra_stripes", "--region", "0,0,1,1"], 2, "filter_def: unknown object type 'zebra'"),
        (["--filter", "hsv_nope", "--region", "0,0,1,1"], 2, "hsv_nope"),
        (["--filter", YELLOW, "--region", "0,0,1"], 2, "--region: 3 numbers"),
        (["--filter", YELLOW, "--region", "0,0,1,1,1,0,0,1"], 2, "--region: not a simple polygon"),
        (["--filter", YELLOW, "--region", "0,0,1,1", "--height", "person"], 2, "--height: 'person'"),
        (["--filter", YELLOW, "--region", "0,0,1,1", "--topic-prefix", "drvs"], 2, "--topic-prefix"),
        (["--filter", YELLOW, "--region", "0,0,1,1", "--domain-id", "300"], 2, "--domain-id"),
    ],
)
async def test_bad_input_exits_2_naming_what_is_wrong(
    args: list[str], code: int, message: str, dds: tuple[dict[str, str], int]
) -> None:
    env, _ = dds
    async with bridge(env, "--server", f"127.0.0.1:{free_port()}", *args) as ros2:
        assert await ros2.wait(timeout=30) == code, ros2.tail()
    assert any(line.startswith("drvs-ros2: ") and message in line for line in ros2.lines), ros2.tail()
    assert not any("Traceback" in line for line in ros2.lines), ros2.tail()


async def test_a_dds_configuration_cyclone_refuses_exits_2_before_any_network_wait(
    dds: tuple[dict[str, str], int],
) -> None:
    env, domain = dds
    env = {**env, "CYCLONEDDS_URI": CYCLONE_LOOPBACK.replace('name="lo"', 'name="nosuch0"')}
    async with bridge(
        env,
        "--server",
        f"127.0.0.1:{free_port()}",
        "--filter",
        YELLOW,
        "--region",
        "0,0,1,1",
        "--domain-id",
        str(domain),
    ) as ros2:
        assert await ros2.wait(timeout=30) == 2, ros2.tail()
    assert any("drvs-ros2: Cyclone DDS would not start" in line and "CYCLONEDDS_URI" in line for line in ros2.lines)
    assert not any("not reachable" in line for line in ros2.lines)  # it never tried the server


async def test_a_server_that_is_down_exits_4(dds: tuple[dict[str, str], int]) -> None:
    env, domain = dds
    port = free_port()
    async with bridge(
        env, "--server", f"127.0.0.1:{port}", "--filter", YELLOW, "--region", "0,0,1,1", "--domain-id", str(domain)
    ) as ros2:
        assert await ros2.wait(timeout=60) == 4, ros2.tail()
    assert any(line.startswith("drvs-ros2: ") and f"127.0.0.1:{port}" in line for line in ros2.lines), ros2.tail()


def test_the_bridge_makes_only_the_topics_a_subscriber_reads(
    dds: tuple[dict[str, str], int], monkeypatch: pytest.MonkeyPatch
) -> None:
    from cyclonedds._clayer import ddspy_take
    from cyclonedds.core import InstanceState, ReadCondition, SampleState, ViewState, WaitSet
    from cyclonedds.util import duration
    from shapely.geometry import box

    from drvs.core.model import Snapshot, WorldObject
    from drvs.ros2.bridge import Publisher
    from drvs.ros2.convert import Style
    from drvs.ros2.dds import Node

    env, domain = dds
    monkeypatch.setenv("CYCLONEDDS_URI", env["CYCLONEDDS_URI"])  # read when the domain is made
    ANY = SampleState.Any | ViewState.Any | InstanceState.Any
    publisher = Publisher(Node(domain), Style())
    subscriber = Node(domain)
    waitset = WaitSet(subscriber.participant)
    readers: dict[str, Any] = {}

    def read(topic: str) -> None:
        readers[topic] = subscriber.reader(topic, TOPICS[topic])
        waitset.attach(ReadCondition(readers[topic], ANY))
        for _ in range(50):  # the bridge's writer sees the new reader (its publication-matched status)
            if publisher.matched[topic]:
                return
            waitset.wait(duration(milliseconds=100))
        raise AssertionError(f"{topic}: the bridge's writer never matched the reader")

    def published(t: float, *track_ids: int) -> dict[str, Any]:
        objects = tuple(WorldObject(i, box(i, 0, i + 1, 1), (i, 0, i + 1, 1), (i + 0.5, 0.5)) for i in track_ids)
        publisher.publish(Snapshot(t, objects, {}, ("cam1",), 0, False, "req"))
        taken: dict[str, Any] = {}
        for _ in range(50):
            for topic, reader in readers.items():
                taken.update(
                    (topic, decode(topic, payload))
                    for payload, info in ddspy_take(reader._ref, ANY, 8)
                    if info.valid_data
                )
            if len(taken) == len(readers):
                return taken
            waitset.wait(duration(milliseconds=100))
        raise AssertionError(f"only {sorted(taken)} arrived")

    assert not any(publisher.matched.values())
    read("/drvs/objects")
    assert [t for t, n in publisher.matched.items() if n] == ["/drvs/objects"]
    assert [d.id for d in published(1.0, 1, 2)["/drvs/objects"].detections] == ["1", "2"]
    read("/drvs/markers")  # joins late: the markers of track 2, ended meanwhile unread, are deleted
    markers = published(2.0, 1)["/drvs/markers"].markers
    assert [(m.ns, m.id) for m in markers if m.action == 2] == [("drvs/label", 2), ("drvs/outline", 2)]
    assert not [t for t, n in publisher.matched.items() if n and t not in readers]

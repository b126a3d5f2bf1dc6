"""A ROS 2 peer for tests/ros2/test_ros2.py, run as its own process (`python -m tests.fakes.ros2_peer`), that
speaks plain Cyclone DDS as rmw_cyclonedds does and knows nothing of the bridge:

    listen  --domain N --topic /drvs/objects=vision_msgs/msg/Detection3DArray ... --count K
        prints {"ready": true} once its readers exist, then a JSON line per writer discovered on
        those topics ({"writer": {topic, type, qos}}, from DDS's built-in DCPSPublication topic)
        and per sample ({"topic", "payload": hex of the raw serialized bytes, taken undecoded});
        exits once every topic gave K samples.
    region  --domain N --frame-id F --points X0,Y0,X1,Y1,...
        publishes one geometry_msgs/PolygonStamped on /drvs/region once a reader matches, waits
        for it to be acknowledged, prints {"sent": true} and exits.
    clock   --domain N --start S
        publishes rosgraph_msgs/Clock on /clock as a simulator does, S, S+1, ... s, until stopped.

The readers' types are drvs.ros2.types' (a DDS reader needs the type to match the writer); the
bytes are printed raw, for the test to decode with rosbags.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

from cyclonedds._clayer import ddspy_take
from cyclonedds.builtin import BuiltinDataReader, BuiltinTopicDcpsPublication
from cyclonedds.core import DDSStatus, InstanceState, ReadCondition, SampleState, ViewState, WaitSet
from cyclonedds.domain import DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.qos import Policy, Qos
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

from drvs.ros2.types import idl

ANY = SampleState.Any | ViewState.Any | InstanceState.Any
#: What ROS 2's default subscription asks for (reliable, keep last 10, volatile, XCDR1).
DEFAULT_QOS = Qos(
    Policy.Reliability.Reliable(duration(milliseconds=100)),
    Policy.History.KeepLast(10),
    Policy.Durability.Volatile,
    Policy.DataRepresentation(use_cdrv0_representation=True),
)
#: rclcpp's SensorDataQoS: best effort, keep last 5.
SENSOR_QOS = Qos(
    Policy.Reliability.BestEffort,
    Policy.History.KeepLast(5),
    Policy.Durability.Volatile,
    Policy.DataRepresentation(use_cdrv0_representation=True),
)


def qos_json(qos: Qos) -> dict[str, str]:
    return {policy.__name__: repr(qos[policy]) for policy in (
        Policy.Reliability, Policy.History, Policy.Durability, Policy.DataRepresentation
    ) if policy in qos}  # fmt: skip


def emit(line: dict[str, Any]) -> None:
    print(json.dumps(line), flush=True)


def listen(args: argparse.Namespace) -> int:
    participant = DomainParticipant(args.domain)
    wanted = dict(item.split("=", 1) for item in args.topic)
    qos = SENSOR_QOS if args.sensor else DEFAULT_QOS
    readers = {
        topic: DataReader(participant, Topic(participant, "rt" + topic, idl(kind)), qos)
        for topic, kind in wanted.items()
    }
    publications = BuiltinDataReader(participant, BuiltinTopicDcpsPublication)
    waitset = WaitSet(participant)
    for reader in [*readers.values(), publications]:
        waitset.attach(ReadCondition(reader, ANY))
    counts = dict.fromkeys(readers, 0)
    emit({"ready": True})
    seen: set[str] = set()
    while min(counts.values()) < args.count:
        waitset.wait(duration(seconds=1))
        for endpoint in publications.take(64):
            topic_name = getattr(endpoint, "topic_name", None)  # None: a writer gone (disposed)
            if topic_name and topic_name.removeprefix("rt") in wanted and str(endpoint.key) not in seen:
                seen.add(str(endpoint.key))
                topic = endpoint.topic_name
                emit({"writer": {"topic": topic, "type": endpoint.type_name, "qos": qos_json(endpoint.qos)}})
        for topic, reader in readers.items():
            for payload, info in ddspy_take(reader._ref, ANY, 64):
                if info.valid_data and counts[topic] < args.count:
                    counts[topic] += 1
                    emit({"topic": topic, "payload": bytes(payload).hex()})
    return 0


def region(args: argparse.Namespace) -> int:
    participant = DomainParticipant(args.domain)
    kind = idl("geometry_msgs/msg/PolygonStamped")
    writer = DataWriter(participant, Topic(participant, "rt/drvs/region", kind), DEFAULT_QOS)
    values = [float(v) for v in args.points.split(",")]
    point = idl("geometry_msgs/msg/Point32")
    message = kind()
    message.header.frame_id = args.frame_id
    message.polygon.points = [point(x=values[i], y=values[i + 1]) for i in range(0, len(values) - 1, 2)]
    writer.set_status_mask(DDSStatus.PublicationMatched)
    waitset = WaitSet(participant)
    waitset.attach(writer)
    while not writer.get_publication_matched_status().current_count:  # type: ignore[no-untyped-call]
        waitset.wait(duration(seconds=1))
    writer.write(message)
    writer.wait_for_acks(duration(seconds=10))
    emit({"sent": True})
    return 0


def clock(args: argparse.Namespace) -> int:
    """Publish rosgraph_msgs/Clock on /clock, best effort as a simulator does, from --start seconds
    on, a tick about every 10 ms, at a real-time factor of 1, until stopped."""
    participant = DomainParticipant(args.domain)
    kind = idl("rosgraph_msgs/msg/Clock")
    writer = DataWriter(participant, Topic(participant, "rt/clock", kind), SENSOR_QOS)
    emit({"clock": True})
    began = time.monotonic_ns()
    while True:
        ns = round(args.start * 1e9) + time.monotonic_ns() - began
        message = kind()
        message.clock.sec, message.clock.nanosec = divmod(ns, 1_000_000_000)
        writer.write(message)
        time.sleep(0.01)  # a simulator's tick: pacing, not synchronisation


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="ros2_peer")
    sub = p.add_subparsers(dest="command", required=True)
    a = sub.add_parser("listen")
    a.add_argument("--domain", type=int, required=True)
    a.add_argument("--topic", action="append", required=True, metavar="TOPIC=TYPE")
    a.add_argument("--count", type=int, default=3)
    a.add_argument("--sensor", action="store_true", help="subscribe best effort, as SensorDataQoS")
    b = sub.add_parser("region")
    b.add_argument("--domain", type=int, required=True)
    b.add_argument("--frame-id", default="map")
    b.add_argument("--points", required=True)
    c = sub.add_parser("clock")
    c.add_argument("--domain", type=int, required=True)
    c.add_argument("--start", type=float, default=1000.0)
    args = p.parse_args(argv)
    return {"listen": listen, "region": region, "clock": clock}[args.command](args)


if __name__ == "__main__":
    sys.exit(main())

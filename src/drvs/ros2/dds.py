"""Cyclone DDS as a ROS 2 node's rmw_cyclonedds uses it: topics named rt/<ros topic>, types named
pkg::msg::dds_::Name_, data in XCDR1, and the two QoS profiles drvs-ros2 offers.

Cyclone reads its configuration from CYCLONEDDS_URI (an XML file or inline XML), as every ROS 2
node on rmw_cyclonedds does; docs/ros2.md gives a loopback-only and a LAN configuration.
"""

from __future__ import annotations

from typing import Any

from cyclonedds._clayer import ddspy_write  # the call DataWriter.write makes with what it serialized
from cyclonedds.core import DDSException, Listener
from cyclonedds.domain import DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.qos import Policy, Qos
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

from drvs.ros2.types import dds_topic_name, idl

#: --qos: reliable (what ROS 2's default profile asks: a default and a sensor-data subscriber both
#: match it) or sensor (best effort, as rclcpp's SensorDataQoS).
QOS_PROFILES = ("reliable", "sensor")
#: ROS 2's history depth for both.
DEPTH = 10


def qos(profile: str = "reliable") -> Qos:
    """The writers' and readers' QoS: `profile` reliability, keep last 10, volatile, XCDR1 only."""
    if profile not in QOS_PROFILES:
        raise ValueError(f"QoS profile {profile!r}: one of {', '.join(QOS_PROFILES)}")
    reliability = (
        Policy.Reliability.Reliable(max_blocking_time=duration(milliseconds=100))
        if profile == "reliable"
        else Policy.Reliability.BestEffort
    )
    return Qos(
        reliability,
        Policy.History.KeepLast(DEPTH),
        Policy.Durability.Volatile,
        # ROS 2 speaks XCDR1 (plain CDR): a writer offering XCDR2 would not match rmw_cyclonedds' readers.
        Policy.DataRepresentation(use_cdrv0_representation=True),
    )


class Node:
    """One DDS participant on `domain_id` (ROS_DOMAIN_ID) with the writers and readers of a ROS 2 node."""

    def __init__(self, domain_id: int = 0) -> None:
        self.participant = DomainParticipant(domain_id)
        self._topics: dict[str, Topic[Any]] = {}

    def _topic(self, ros_topic: str, ros_type: str) -> Topic[Any]:
        name = dds_topic_name(ros_topic)
        if name not in self._topics:
            self._topics[name] = Topic(self.participant, name, idl(ros_type))
        return self._topics[name]

    def writer(
        self, ros_topic: str, ros_type: str, profile: str = "reliable", listener: Listener | None = None
    ) -> DataWriter[Any]:
        return DataWriter(self.participant, self._topic(ros_topic, ros_type), qos(profile), listener)

    def reader(self, ros_topic: str, ros_type: str, profile: str = "reliable") -> DataReader[Any]:
        return DataReader(self.participant, self._topic(ros_topic, ros_type), qos(profile))


def cdr_padding(length: int) -> bytes:
    """The zeros Cyclone pads a serialized sample of `length` bytes with, to a multiple of 4."""
    return bytes(-length % 4)


def write_cdr(writer: DataWriter[Any], payload: bytes | bytearray) -> None:
    """Publish a message already serialized as ROS 2 CDR (encapsulation header first: to_cdr,
    drvs.ros2.cdr), handed to Cyclone as it is: what DataWriter.write does after serializing (with
    Cyclone's pure-Python serializer, several times slower), padded to 4 bytes as it pads (a
    bytearray in place: += extends it)."""
    payload += cdr_padding(len(payload))
    code = ddspy_write(writer._ref, payload)
    if code < 0:
        raise DDSException(code, f"writing on {writer.topic.name}")

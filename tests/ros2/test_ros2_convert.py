"""drvs.ros2's messages without DDS: the IDL structs made from the shipped .msg files serialize
exactly as rosbags does from the same files, and a Snapshot becomes the messages docs/ros2.md
describes (markers deleted when tracks end, velocity arrows only while moving, regions checked)."""

from __future__ import annotations

import math
import struct
import time
from collections.abc import Sequence
from typing import Any

import pytest
from shapely.geometry import Point, Polygon, box

from drvs.core.errors import InvalidArgument
from drvs.core.model import CameraError, Snapshot, WorldObject
from drvs.ros2.bridge import SimClock
from drvs.ros2.convert import (
    ADD,
    ARROW_MIN_MPS,
    DELETE,
    LABEL_NS,
    OUTLINE_NS,
    VELOCITY_NS,
    MarkerState,
    Style,
    header,
    output_topics,
    region_from_msg,
    snapshot_messages,
    track_uuid,
)
from drvs.ros2.types import dds_topic_name, dds_type_name, idl, idl_types, msg_files, to_cdr, typestore


def thing(track_id: int, x: float, y: float, vx: float = 0.0, label: str = "") -> WorldObject:
    outline = box(x - 0.2, y - 0.1, x + 0.2, y + 0.1)
    return WorldObject(
        track_id=track_id,
        outline=outline,
        bounds=outline.bounds,
        centroid_xy=(x, y),
        velocity_xy=(vx, 0.0),
        uncertainty_m=0.05,
        camera_ids=("cam1",),
        label=label,
        score=0.75,
    )


def snap(*objects: WorldObject, t: float = 1_700_000_000.25, **kw: Any) -> Snapshot:
    return Snapshot(time=t, objects=objects, camera_ids=("cam1",), request_id="req", **kw)


def test_the_names_follow_rmw_cyclonedds() -> None:
    assert dds_topic_name("/drvs/objects") == "rt/drvs/objects"
    assert dds_type_name("vision_msgs/msg/Detection3DArray") == "vision_msgs::msg::dds_::Detection3DArray_"
    assert idl("sensor_msgs/msg/PointCloud2").__idl_typename__ == "sensor_msgs::msg::dds_::PointCloud2_"
    for bad in ("drvs/objects", "/drvs/", "/a//b"):
        with pytest.raises(ValueError, match="not an absolute ROS 2 topic"):
            dds_topic_name(bad)
    with pytest.raises(KeyError, match="not among the shipped"):
        idl("nav_msgs/msg/Odometry")


def test_every_shipped_type_serializes_as_rosbags_does() -> None:
    store = typestore()
    assert set(idl_types()) == set(msg_files()) and len(msg_files()) == 31
    for name, cls in idl_types().items():
        payload = to_cdr(cls())
        assert payload[:4] == bytes([0, 1, 0, 0])
        assert bytes(store.serialize_cdr(store.deserialize_cdr(payload, name), name)) == payload, name


def test_a_snapshot_becomes_every_topics_message_and_rosbags_reads_them() -> None:
    style = Style(heights={"person": 1.8}, filter_def="people", cloud_step_m=0.1)
    messages = dict(
        snapshot_messages(
            snap(thing(3, 1.0, 2.0, vx=0.5, label="person"), thing(4, -1.0, 0.0)), style, MarkerState(), 12.5, "/x"
        )
    )
    assert (
        set(messages)
        == set(output_topics("/x"))
        == {"/x/objects", "/x/obstacles", "/x/tracks", "/x/markers", "/diagnostics"}
    )
    store = typestore()
    decoded: dict[str, Any] = {t: store.deserialize_cdr(to_cdr(m), output_topics("/x")[t]) for t, m in messages.items()}
    objects = decoded["/x/objects"]
    assert (objects.header.stamp.sec, objects.header.stamp.nanosec, objects.header.frame_id) == (12, 500_000_000, "map")
    person, other = objects.detections
    assert (person.id, person.results[0].hypothesis.class_id, person.bbox.size.z) == ("3", "person", 1.8)
    assert (other.results[0].hypothesis.class_id, other.bbox.size.z) == ("people", 1.0)  # no label: the filter
    assert person.results[0].pose.covariance[0] == pytest.approx(0.05**2)
    cloud = decoded["/x/obstacles"]
    points = list(struct.iter_unpack("<3f", bytes(cloud.data)))
    assert cloud.width == len(points) and cloud.row_step == 12 * len(points)
    placed = 0
    for o, z in ((thing(3, 1.0, 2.0), 0.9), (thing(4, -1.0, 0.0), 0.5)):  # half of each one's height
        on = [p for p in points if o.outline.exterior.distance(Point(p[0], p[1])) < 1e-5 and abs(p[2] - z) < 1e-6]
        assert 12 <= len(on) <= 16  # a 0.4 x 0.2 m outline, a point every 0.1 m at most
        placed += len(on)
    assert placed == len(points)  # every point on one of the outlines
    tracks = decoded["/x/tracks"].obstacles
    assert bytes(tracks[0].uuid.uuid) == track_uuid("req", 3) != track_uuid("req", 4) == bytes(tracks[1].uuid.uuid)
    assert (tracks[0].velocity.x, tracks[0].size.x, tracks[0].size.y) == (0.5, pytest.approx(0.4), pytest.approx(0.2))


def test_markers_of_ended_tracks_and_stopped_motion_are_deleted() -> None:
    state, style, hdr = MarkerState(), Style(), header(1.0, "map")
    first = state.markers(snap(thing(1, 0, 0, vx=1.0), thing(2, 3, 3)), style, hdr)
    assert {(m.ns, m.id) for m in first.markers} == {
        (OUTLINE_NS, 1),
        (LABEL_NS, 1),
        (VELOCITY_NS, 1),
        (OUTLINE_NS, 2),
        (LABEL_NS, 2),
    }
    arrow = next(m for m in first.markers if m.ns == VELOCITY_NS)
    assert [(p.x, p.y) for p in arrow.points] == [(0.0, 0.0), (1.0, 0.0)]  # one second of motion
    second = state.markers(snap(thing(1, 0, 0)), style, hdr)  # 1 stopped, 2 ended
    deleted = {(m.ns, m.id) for m in second.markers if m.action == DELETE}
    assert deleted == {(VELOCITY_NS, 1), (OUTLINE_NS, 2), (LABEL_NS, 2)}
    assert state.markers(snap(thing(1, 0, 0)), style, hdr).markers[-1].action != DELETE  # nothing more to delete


def test_a_standing_objects_jitter_draws_no_arrow() -> None:
    """A tracked object that stands still reports a few mm/s of jitter, now and then exactly 0: it
    gets no arrow to flicker on and off (nor a DELETE each time its speed reads 0)."""
    state, style, hdr = MarkerState(), Style(), header(1.0, "map")
    for vx in (0.004, 0.0, 0.003, ARROW_MIN_MPS / 2, 0.0):
        shown = state.markers(snap(thing(1, 0, 0, vx=vx)), style, hdr).markers
        assert {(m.ns, m.action) for m in shown} == {(OUTLINE_NS, ADD), (LABEL_NS, ADD)}, vx
    walking = state.markers(snap(thing(1, 0, 0, vx=ARROW_MIN_MPS)), style, hdr).markers
    assert (VELOCITY_NS, ADD) in {(m.ns, m.action) for m in walking}


def test_diagnostics_warn_per_missing_camera_and_for_floor_no_camera_sees() -> None:
    blind = snap(
        camera_errors={"cam2": CameraError("UNAVAILABLE", "camera cam2: gone", "cam2")}, uncovered=(box(0, 0, 2, 1),)
    )
    (array,) = [m for t, m in snapshot_messages(blind, Style(), MarkerState(), 1.0, "/drvs") if t == "/diagnostics"]
    levels = {s.name: (s.level, s.message) for s in array.status}
    assert levels == {
        "drvs: camera cam2": (1, "UNAVAILABLE: camera cam2: gone"),
        "drvs: camera cam1": (0, "answered"),
        "drvs: region": (1, "2.0 m² of the region no camera sees"),
    }


def polygon_stamped(points: Sequence[tuple[float, float]], frame_id: str = "map") -> Any:
    message = idl("geometry_msgs/msg/PolygonStamped")()
    message.header.frame_id = frame_id
    message.polygon.points = [idl("geometry_msgs/msg/Point32")(x=x, y=y) for x, y in points]
    return message


def test_a_region_message_is_a_polygon_in_the_bridges_frame_or_refused() -> None:
    square = [(0.0, 0.0), (2.0, 0.0), (2.0, 2.0), (0.0, 2.0)]
    assert region_from_msg(polygon_stamped(square), "map").equals(Polygon(square))
    assert region_from_msg(polygon_stamped(square, ""), "map").area == 4  # no frame: the bridge's
    cases: list[tuple[list[tuple[float, float]], str, str]] = [
        (square, "odom", "in frame 'odom'"),
        ([(0, 0), (1, 1)], "map", "at least three points"),
        ([(0, 0), (1, 1), (1, 0), (0, 1)], "map", "not a simple polygon"),
        ([(0, 0), (1, 0), (2, 0)], "map", "not a simple polygon"),
        ([(0, 0), (math.inf, 0), (1, 1)], "map", "not a finite number"),
    ]
    for points, frame, why in cases:
        with pytest.raises(InvalidArgument, match=why):
            region_from_msg(polygon_stamped(points, frame), "map")


def test_sim_time_stamps_with_the_clock_topic_plus_the_wall_time_since() -> None:
    clock = SimClock()
    now = time.time()
    assert clock.stamp(now) == now  # no /clock yet: the wall clock
    message = idl("rosgraph_msgs/msg/Clock")()
    message.clock.sec, message.clock.nanosec = 100, 500_000_000
    clock.take(message)
    _, arrived = clock.latest or (0.0, 0.0)
    assert clock.stamp(arrived - 0.2) == pytest.approx(100.3)

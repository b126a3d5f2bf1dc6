"""The bridge's hot topics encoded straight to ROS 2 CDR bytes from a snapshot: the same bytes
rosbags' serialize_cdr gives for the messages drvs.ros2.convert builds, made without the ~150
Python message objects a snapshot of 20 objects needs there.

Why by hand: building those objects and walking them with rosbags' generated serializer cost about
2.5 ms of CPU a snapshot (docs/benchmarks.md, "drvs-bench ros2"), five times the bridge's budget.
The per-object layouts of /drvs/objects, /drvs/obstacles, /drvs/tracks and /drvs/markers are fixed
but for strings and point sequences, so each is written here as a few byte strings per object:
an object's numbers in one precompiled struct, the outlines' points of all objects at once with
shapely's vectorised functions and numpy, constant parts (default fields, a marker kind's scale and
colour) packed once. Cyclone DDS is handed the finished bytes (drvs.ros2.dds.write_cdr). /diagnostics, sent about
once a second, stays with rosbags (convert.diagnostics + types.to_cdr).

How it is checked: convert.py's rosbags messages are the definition. tests/ros2/test_ros2_cdr.py
compares these bytes with rosbags' serialize_cdr of them, byte for byte, over varied snapshots (no
object, one, 20, long and degenerate outlines, unicode ids and types, ended tracks and stopped
motion), and the bridge's tests decode what goes over DDS with rosbags' deserializer.

XCDR1 (plain CDR), little-endian: after the 4-byte encapsulation header every number sits at a
multiple of its size counted from the end of that header (8 for float64, 4 for int32, uint32, float32,
a sequence's or string's length); a string is its uint32 length with the NUL, its UTF-8 and the NUL.
"""

from __future__ import annotations

import functools
import itertools
import struct
from collections.abc import Container, Iterator, Sequence
from typing import Any

import numpy as np
import shapely

from drvs.core.model import Snapshot
from drvs.ros2.convert import (
    ADD,
    ARROW,
    ARROW_LOOK,
    DELETE,
    DIAGNOSTICS_TOPIC,
    FLOAT32,
    LABEL_LOOK,
    LABEL_RAISE_M,
    LINE_STRIP,
    OUTLINE_LOOK,
    OUTLINE_Z_M,
    TEXT_VIEW_FACING,
    MarkerState,
    Style,
    diagnostics,
    header,
    label_text,
    moving,
    outline,
    stamp_parts,
    track_uuid,
)
from drvs.ros2.types import to_cdr

#: XCDR1, little-endian: the encapsulation header every payload starts with.
ENCAPSULATION = b"\x00\x01\x00\x00"
#: Padding by length; `_ZEROS[(4 - len(buf)) & 7]` pads a payload `buf` (header included) to 8.
_ZEROS = tuple(bytes(n) for n in range(8))
_U32 = struct.Struct("<I").pack
_F32 = struct.Struct("<f").pack
_STAMP = struct.Struct("<iI").pack
_ONE = _U32(1)


@functools.lru_cache(maxsize=4096)
def cdr_string(text: str) -> bytes:
    """A string's CDR: its uint32 length with the NUL, its UTF-8, the NUL (4-aligned where it goes)."""
    data = text.encode()
    return _U32(len(data) + 1) + data + b"\0"


def _aligned(parts: Sequence[bytes], start: int = 0) -> bytes:
    """Parts joined, each padded to 4 from an offset of `start` (mod 4): the constant runs of
    4-aligned fields (strings, uint32s) below."""
    out = bytearray()
    for part in parts:
        out += _ZEROS[(-start - len(out)) & 3]
        out += part
    return bytes(out)


def header_cdr(at: float, frame_id: str) -> bytes:
    """std_msgs/Header stamped `at` seconds (as convert.stamp), 4-aligned where it goes."""
    return _STAMP(*stamp_parts(at)) + cdr_string(frame_id)


_uuid = functools.lru_cache(maxsize=4096)(track_uuid)


#: Per detection every float64 after its class id: the score, the pose (centroid at z 0, identity
#: orientation), its covariance (uncertainty² at [0] and [7]), the box's centre pose and size.
_DETECTION = struct.Struct("<3d32xdd48xd224x3d24xd3d").pack
#: Per obstacle after its UUID and score: position, velocity (z 0), size, position covariance
#: (uncertainty² at [0] and [4]) and velocity covariance (zeros).
_OBSTACLE = struct.Struct("<5d8x3dd24xd32x72x").pack


class Geometry:
    """What several topics use of a snapshot's objects: heights, object types, and the outline
    rings of all of them (shapely's vectorised functions: one call for all objects).

    Paced at 50 Hz the bridge wakes onto cold caches, where each distinct numpy or shapely code
    path costs tens of microseconds the first time however little it does: the points are taken
    with few of them, and a path once taken is reused (the rings' coordinate counts, from which
    empty rings and where each object's points start are both read, rather than an emptiness
    test, a search and masks). The rings are made when a topic first asks for them."""

    def __init__(self, snapshot: Snapshot, style: Style) -> None:
        self.objects = snapshot.objects
        self.heights = [style.height(o) for o in self.objects]
        self.types = [style.object_type(o) for o in self.objects]
        self.moving = [moving(o) for o in self.objects]

    @functools.cached_property
    def _rings(self) -> tuple[np.ndarray[Any, Any], list[int]]:
        """The outlines' exterior rings, and how many points each has."""
        rings = shapely.get_exterior_ring([o.outline for o in self.objects])
        counts: list[int] = shapely.get_num_coordinates(rings).tolist()
        if 0 in counts:  # outlines left out (an empty ring): their bounds (convert.outline)
            rings = shapely.get_exterior_ring([outline(o) for o in self.objects])
            counts = shapely.get_num_coordinates(rings).tolist()
        return rings, counts

    def ring_points(self, step_m: float | None) -> tuple[np.ndarray[Any, Any], list[int]]:
        """Every object's outline ring as one (k, 2) array of x, y, closing points included (every
        `step_m` metres along it when given: LinearRing.segmentize), and where each object's points
        start (and, last, where they end)."""
        rings, counts = self._rings
        if step_m is not None:
            rings = shapely.segmentize(rings, step_m)
            counts = shapely.get_num_coordinates(rings).tolist()
        return shapely.get_coordinates(rings), list(itertools.accumulate(counts, initial=0))


def detections_cdr(snapshot: Snapshot, geo: Geometry, hdr: bytes) -> bytearray:
    """vision_msgs/Detection3DArray as convert.detections builds it."""
    buf = bytearray(ENCAPSULATION)
    buf += hdr
    buf += _ZEROS[(4 - len(buf)) & 3]
    buf += _U32(len(snapshot.objects))
    head = _aligned([hdr, _ONE])  # each detection's header and its one result's start
    for o, h, kind in zip(snapshot.objects, geo.heights, geo.types, strict=True):
        x0, y0, x1, y1 = o.bounds
        cx, cy = o.centroid_xy
        variance = o.uncertainty_m**2
        buf += _ZEROS[(4 - len(buf)) & 3]
        buf += head
        buf += cdr_string(kind)
        buf += _ZEROS[(4 - len(buf)) & 7]
        buf += _DETECTION(float(o.score), cx, cy, 1.0, variance, variance, (x0 + x1) / 2, (y0 + y1) / 2, h / 2, 1.0,
                          x1 - x0, y1 - y0, h)  # fmt: skip
        buf += cdr_string(str(o.track_id))
    return buf


#: sensor_msgs/PointField x, y, z (float32, 4 bytes apart), 4-aligned where they go.
_CLOUD_FIELDS = _aligned([_U32(3)] + [
    _aligned([cdr_string(name), _U32(4 * i), bytes([FLOAT32]), _U32(1)]) for i, name in enumerate("xyz")
])  # fmt: skip


def obstacle_cloud_cdr(geo: Geometry, hdr: bytes, step_m: float) -> bytearray:
    """sensor_msgs/PointCloud2 as convert.obstacle_cloud builds it."""
    xy, starts = geo.ring_points(step_m)
    points = np.empty((len(xy), 3), dtype="<f4")
    points[:, :2] = xy
    for h, (start, end) in zip(geo.heights, itertools.pairwise(starts), strict=True):
        points[start:end, 2] = h / 2
    # Each ring's last point, its first again, is left out.
    data = b"".join([points[start : end - 1].tobytes() for start, end in itertools.pairwise(starts)])
    buf = bytearray(ENCAPSULATION)
    buf += hdr
    buf += _ZEROS[(4 - len(buf)) & 3]
    buf += _STAMP(1, len(data) // 12)  # height, width
    buf += _CLOUD_FIELDS
    buf += b"\0"  # is_bigendian
    buf += _ZEROS[(4 - len(buf)) & 3]
    buf += struct.pack("<III", 12, len(data), len(data))  # point_step, row_step, len(data)
    buf += data
    buf += b"\1"  # is_dense
    return buf


def obstacles_cdr(snapshot: Snapshot, geo: Geometry, hdr: bytes) -> bytearray:
    """nav2_dynamic_msgs/ObstacleArray as convert.obstacles builds it."""
    buf = bytearray(ENCAPSULATION)
    buf += hdr
    buf += _ZEROS[(4 - len(buf)) & 3]
    buf += _U32(len(snapshot.objects))
    for o, h in zip(snapshot.objects, geo.heights, strict=True):
        x0, y0, x1, y1 = o.bounds
        cx, cy = o.centroid_xy
        vx, vy = o.velocity_xy
        variance = o.uncertainty_m**2
        buf += _uuid(snapshot.request_id, o.track_id)  # 16 bytes from a 4-aligned place
        buf += _F32(float(o.score))
        buf += _ZEROS[(4 - len(buf)) & 7]
        buf += _OBSTACLE(cx, cy, h / 2, vx, vy, x1 - x0, y1 - y0, h, variance, variance)
    return buf


def _look(scale: tuple[float, float, float], color: tuple[float, float, float, float]) -> bytes:
    """A marker's scale, colour, lifetime (0) and frame_locked (false), after its pose."""
    return struct.pack("<3d4f2i?", *scale, *color, 0, 0, False)


_ORIGIN = struct.pack("<7d", 0, 0, 0, 0, 0, 0, 1)
#: A marker's fields from colors to uv_coordinates (all unset), 4-aligned where they go:
#: colors [], texture_resource "", texture (header 0 "", format "", data []), uv_coordinates [].
_UNSET_MIDDLE = _aligned([_U32(0), cdr_string(""), _STAMP(0, 0), cdr_string(""), cdr_string(""), _U32(0), _U32(0)])
#: And after its text: mesh_resource "", mesh_file ("", []), mesh_use_embedded_materials false.
_UNSET_TAIL = _aligned([cdr_string(""), cdr_string(""), _U32(0), b"\0"])
#: Everything after the points of a marker with no text.
_NO_TEXT_END = _aligned([_UNSET_MIDDLE, cdr_string(""), _UNSET_TAIL])
#: A pose (from an 8-aligned place), scale, colour, lifetime and frame_locked are 105 bytes: the
#: points' length then starts after 3 bytes of padding and ends 8-aligned, where points start.
_AFTER_LOOK = bytes(3)
_OUTLINE_BODY = _ORIGIN + _look(*OUTLINE_LOOK) + _AFTER_LOOK  # then the points' length and points
_ARROW_BODY = _ORIGIN + _look(*ARROW_LOOK) + _AFTER_LOOK + _U32(2)  # then the two points
#: A label's pose after its position, no points, and the fields before its text.
_LABEL_BODY = struct.pack("<4d", 0, 0, 0, 1) + _look(*LABEL_LOOK) + _AFTER_LOOK + _U32(0) + _UNSET_MIDDLE
_DELETE_BODY = bytes(56) + _look((0, 0, 0), (0, 0, 0, 0)) + _AFTER_LOOK + _U32(0) + _NO_TEXT_END  # defaults


@functools.lru_cache(maxsize=4096)
def _label_tail(track_id: int, object_type: str) -> bytes:
    """A label marker from its orientation on: the constant fields, its text ("#ID TYPE") and the
    fields after the text. The text starts 4-aligned (the fields before it end so), so the
    padding after it follows from its length alone."""
    text = cdr_string(label_text(track_id, object_type))
    return _LABEL_BODY + text + _ZEROS[-len(text) & 3] + _UNSET_TAIL


@functools.lru_cache(maxsize=64)
def _marker_starts(head_len: int, then: str) -> tuple[struct.Struct, ...]:
    """By a marker's offset mod 8 (from the end of the encapsulation header) where it starts: how
    its start packs: padding to 4, its header and namespace (an `s` of `head_len` bytes, padded to
    4 already), its id, type and action, padding to 8 for the pose, then `then`. One pack a marker
    in place of a handful of appends (the markers are most of the bridge's Python per snapshot)."""
    starts = []
    for at in range(8):
        to4 = -at & 3
        to8 = -(at + to4 + head_len + 12) & 7
        starts.append(struct.Struct(f"<{to4}x{head_len}s3i{to8}x{then}"))
    return tuple(starts)


def markers_cdr(snapshot: Snapshot, geo: Geometry, hdr: bytes, state: MarkerState) -> bytearray:
    """visualization_msgs/MarkerArray as MarkerState.markers builds it (it updates `state` alike)."""
    ended = state.ended(snapshot, geo.moving)
    # A marker's header and namespace from a 4-aligned place, padded for the id after them.
    heads = {ns: _aligned([hdr, cdr_string(ns), b""]) for ns in (state.outline_ns, state.label_ns, state.velocity_ns)}
    outline_head, label_head, arrow_head = heads[state.outline_ns], heads[state.label_ns], heads[state.velocity_ns]
    # Each kind's start by where it starts (mod 8), with what follows its id in the same pack.
    outline_at = _marker_starts(len(outline_head), f"{len(_OUTLINE_BODY)}sI")  # the body, the points' count
    label_at = _marker_starts(len(label_head), "3d")  # its position
    arrow_at = _marker_starts(len(arrow_head), f"{len(_ARROW_BODY)}s6d")  # the body, the two points
    xy, starts = geo.ring_points(None)
    ring = np.full((len(xy), 3), OUTLINE_Z_M)
    ring[:, :2] = xy
    ring_blob = ring.tobytes()
    buf = bytearray(ENCAPSULATION)
    buf += _U32(2 * len(snapshot.objects) + sum(geo.moving) + len(ended))
    for o, h, kind, moves, (start, end) in zip(
        snapshot.objects, geo.heights, geo.types, geo.moving, itertools.pairwise(starts), strict=True
    ):
        track_id = o.track_id
        cx, cy = o.centroid_xy
        # The outline: a LINE_STRIP of the ring's points.
        buf += outline_at[(len(buf) + 4) & 7].pack(outline_head, track_id, LINE_STRIP, ADD, _OUTLINE_BODY, end - start)
        buf += ring_blob[24 * start : 24 * end]
        buf += _NO_TEXT_END
        # The label: TEXT_VIEW_FACING above the object.
        buf += label_at[(len(buf) + 4) & 7].pack(label_head, track_id, TEXT_VIEW_FACING, ADD, cx, cy, h + LABEL_RAISE_M)
        buf += _label_tail(track_id, kind)
        if moves:  # an ARROW: one second of motion at half the height
            vx, vy = o.velocity_xy
            buf += arrow_at[(len(buf) + 4) & 7].pack(arrow_head, track_id, ARROW, ADD, _ARROW_BODY,
                                                     cx, cy, h / 2, cx + vx, cy + vy, h / 2)  # fmt: skip
            buf += _NO_TEXT_END
    for ns, track_id in ended:
        head = heads[ns]
        buf += _marker_starts(len(head), f"{len(_DELETE_BODY)}s")[(len(buf) + 4) & 7].pack(
            head, track_id, ARROW, DELETE, _DELETE_BODY
        )
    return buf


def snapshot_payloads(
    snapshot: Snapshot,
    style: Style,
    markers: MarkerState,
    at: float,
    prefix: str,
    *,
    with_diagnostics: bool = True,
    topics: Container[str] | None = None,
) -> Iterator[tuple[str, bytes | bytearray]]:
    """(topic, CDR payload) for everything one snapshot publishes: the bytes of
    convert.snapshot_messages' messages serialized by rosbags, in the same order, each made when
    asked for (objects first). With `topics`, only those are made (`markers` follows the snapshot
    all the same, so the deletions stay right when /markers is read again)."""
    names = [f"{prefix}/{name}" for name in ("objects", "obstacles", "tracks", "markers")]
    made = [topics is None or name in topics for name in names]
    if any(made):
        hdr = header_cdr(at, style.frame_id)
        geo = Geometry(snapshot, style)
        if made[0]:
            yield names[0], detections_cdr(snapshot, geo, hdr)
        if made[1]:
            yield names[1], obstacle_cloud_cdr(geo, hdr, style.cloud_step_m)
        if made[2]:
            yield names[2], obstacles_cdr(snapshot, geo, hdr)
        if made[3]:
            yield names[3], markers_cdr(snapshot, geo, hdr, markers)
    if not made[3]:
        markers.ended(snapshot)
    if with_diagnostics and (topics is None or DIAGNOSTICS_TOPIC[0] in topics):  # about once a second: rosbags
        yield DIAGNOSTICS_TOPIC[0], to_cdr(diagnostics(snapshot, header(at, style.frame_id)))

"""A DRVS Snapshot as the ROS 2 messages drvs-ros2 publishes (docs/ros2.md, "Topics"), and a
geometry_msgs/PolygonStamped as a region. Pure functions of their inputs, but for MarkerState,
which remembers what RViz shows so ended tracks are deleted; the bridge and the rosbag2 export
both build their messages here.
"""

from __future__ import annotations

import functools
import math
import uuid
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from shapely.geometry import Polygon
from shapely.geometry.polygon import orient

from drvs.core.errors import InvalidArgument
from drvs.core.model import Snapshot, WorldObject
from drvs.ros2.types import message_class, ros

#: Height of an object whose type --height does not name, metres (the floor outline has none).
DEFAULT_HEIGHT_M = 1.0
#: Spacing of the obstacle cloud's points along an outline, metres (a costmap cell or finer).
DEFAULT_CLOUD_STEP_M = 0.05
#: sensor_msgs/PointField.FLOAT32
FLOAT32 = 7
#: visualization_msgs/Marker's type and action constants used here.
ARROW, LINE_STRIP, TEXT_VIEW_FACING = 0, 4, 9
ADD, DELETE = 0, 2
#: The marker namespaces: one marker of each per track, its id the track id.
OUTLINE_NS, LABEL_NS, VELOCITY_NS = "drvs/outline", "drvs/label", "drvs/velocity"
#: Each marker kind's scale (x, y, z) and colour (r, g, b, a); outlines are drawn this high, metres,
#: and labels this far above the object's height.
OUTLINE_LOOK = ((0.03, 0.0, 0.0), (0.1, 0.9, 0.2, 1.0))
LABEL_LOOK = ((0.0, 0.0, 0.2), (1.0, 1.0, 1.0, 1.0))
ARROW_LOOK = ((0.05, 0.1, 0.1), (1.0, 0.6, 0.0, 1.0))
OUTLINE_Z_M, LABEL_RAISE_M = 0.02, 0.1
#: diagnostic_msgs/DiagnosticStatus levels.
OK, WARN = 0, 1
#: Where a track's UUID (nav2_dynamic_msgs/Obstacle.uuid) is made: uuid5 of "<request_id>/<track_id>".
TRACK_UUID_NAMESPACE = uuid.UUID("5f1c1f38-6d0a-4f43-9c0e-2f0c1c0a7a31")


@dataclass(frozen=True)
class Style:
    """How snapshots become messages: the frame, heights by object type, the cloud's spacing, and
    the object type of objects whose cameras gave no label (the filter asked for)."""

    frame_id: str = "map"
    heights: dict[str, float] = field(default_factory=dict)
    default_height_m: float = DEFAULT_HEIGHT_M
    cloud_step_m: float = DEFAULT_CLOUD_STEP_M
    filter_def: str = ""

    def object_type(self, o: WorldObject) -> str:
        return o.label or self.filter_def

    def height(self, o: WorldObject) -> float:
        kind = self.object_type(o)
        return self.heights.get(kind, self.heights.get(self.filter_def, self.default_height_m))


def stamp_parts(t: float) -> tuple[int, int]:
    """builtin_interfaces/Time's sec and nanosec for `t` seconds (to the nearest nanosecond)."""
    return divmod(round(t * 1e9), 1_000_000_000)


def stamp(t: float) -> Any:
    """builtin_interfaces/Time for `t` seconds."""
    sec, nanosec = stamp_parts(t)
    return ros("builtin_interfaces/msg/Time", sec=sec, nanosec=nanosec)


def header(t: float, frame_id: str) -> Any:
    return ros("std_msgs/msg/Header", stamp=stamp(t), frame_id=frame_id)


def track_uuid(request_id: str, track_id: int) -> bytes:
    """The 16 bytes of nav2_dynamic_msgs/Obstacle.uuid for a track (stable while the track is)."""
    return uuid.uuid5(TRACK_UUID_NAMESPACE, f"{request_id}/{track_id}").bytes


# The hottest small messages are made by their rosbags classes directly, every field given
# (ros() fills in defaults: a step a snapshot's hundreds of points need not take).
def _point(x: float, y: float, z: float = 0.0) -> Any:
    return message_class("geometry_msgs/msg/Point")(x=float(x), y=float(y), z=float(z))


def _vector(x: float, y: float, z: float = 0.0) -> Any:
    return message_class("geometry_msgs/msg/Vector3")(x=float(x), y=float(y), z=float(z))


def _pose(x: float, y: float, z: float) -> Any:
    identity = message_class("geometry_msgs/msg/Quaternion")(x=0.0, y=0.0, z=0.0, w=1.0)
    return message_class("geometry_msgs/msg/Pose")(position=_point(x, y, z), orientation=identity)


def outline(o: WorldObject) -> Polygon:
    """The object's floor outline, or its bounds when outlines were left out."""
    if not o.outline.is_empty:
        return o.outline
    x0, y0, x1, y1 = o.bounds
    return Polygon([(x0, y0), (x1, y0), (x1, y1), (x0, y1)])


def detections(snapshot: Snapshot, style: Style, hdr: Any) -> Any:
    """vision_msgs/Detection3DArray: per object its track id, its type and score, the centroid at
    z 0 with the variance uncertainty_m² in x and y, and a box from the bounds, as tall as its type."""
    out = []
    for o in snapshot.objects:
        x0, y0, x1, y1 = o.bounds
        h = style.height(o)
        covariance = np.zeros(36)
        covariance[0] = covariance[7] = o.uncertainty_m**2
        result = ros(
            "vision_msgs/msg/ObjectHypothesisWithPose",
            hypothesis=ros("vision_msgs/msg/ObjectHypothesis", class_id=style.object_type(o), score=float(o.score)),
            pose=ros(
                "geometry_msgs/msg/PoseWithCovariance",
                pose=_pose(o.centroid_xy[0], o.centroid_xy[1], 0.0),
                covariance=covariance,
            ),
        )
        bbox = ros(
            "vision_msgs/msg/BoundingBox3D",
            center=_pose((x0 + x1) / 2, (y0 + y1) / 2, h / 2),
            size=_vector(x1 - x0, y1 - y0, h),
        )
        out.append(ros("vision_msgs/msg/Detection3D", header=hdr, results=[result], bbox=bbox, id=str(o.track_id)))
    return ros("vision_msgs/msg/Detection3DArray", header=hdr, detections=out)


def outline_points(o: WorldObject, step_m: float) -> np.ndarray[Any, np.dtype[np.float64]]:
    """Points every `step_m` metres (or closer) along the object's outline, corners included,
    the closing point left out: an (n, 2) array of x, y."""
    return np.asarray(outline(o).exterior.segmentize(step_m).coords)[:-1, :2]


def obstacle_cloud(snapshot: Snapshot, style: Style, hdr: Any) -> Any:
    """sensor_msgs/PointCloud2 of x, y, z float32 points along every outline, at half the object's
    height: what Nav2's obstacle and voxel layers mark (docs/ros2.md)."""
    parts = [np.zeros((0, 3))]
    for o in snapshot.objects:
        xy = outline_points(o, style.cloud_step_m)
        parts.append(np.column_stack([xy, np.full(len(xy), style.height(o) / 2)]))
    points = np.concatenate(parts).astype("<f4")
    fields = [
        ros("sensor_msgs/msg/PointField", name=n, offset=4 * i, datatype=FLOAT32, count=1) for i, n in enumerate("xyz")
    ]
    data = points.reshape(-1).view(np.uint8)
    return ros(
        "sensor_msgs/msg/PointCloud2",
        header=hdr,
        height=1,
        width=len(points),
        fields=fields,
        is_bigendian=False,
        point_step=12,
        row_step=12 * len(points),
        data=data,
        is_dense=True,
    )


def obstacles(snapshot: Snapshot, style: Style, hdr: Any) -> Any:
    """nav2_dynamic_msgs/ObstacleArray: per track its UUID (track_uuid), score, centre (z half its
    height), velocity, size and position covariance (uncertainty_m² in x and y)."""
    out = []
    for o in snapshot.objects:
        x0, y0, x1, y1 = o.bounds
        h = style.height(o)
        covariance = np.zeros(9)
        covariance[0] = covariance[4] = o.uncertainty_m**2
        out.append(
            ros(
                "nav2_dynamic_msgs/msg/Obstacle",
                uuid=ros(
                    "unique_identifier_msgs/msg/UUID",
                    uuid=np.frombuffer(track_uuid(snapshot.request_id, o.track_id), np.uint8),
                ),
                score=float(o.score),
                position=_point(o.centroid_xy[0], o.centroid_xy[1], h / 2),
                velocity=_vector(*o.velocity_xy),
                size=_vector(x1 - x0, y1 - y0, h),
                position_covariance=covariance,
            )
        )
    return ros("nav2_dynamic_msgs/msg/ObstacleArray", header=hdr, obstacles=out)


def _color(r: float, g: float, b: float, a: float) -> Any:
    return message_class("std_msgs/msg/ColorRGBA")(r=r, g=g, b=b, a=a)


class MarkerState:
    """visualization_msgs/MarkerArray for RViz, snapshot after snapshot: per track an outline
    (LINE_STRIP), a label (TEXT_VIEW_FACING "#id type") and, while it moves, a velocity arrow (one
    second of motion); a DELETE for each marker shown before whose track (or motion) has ended.
    `ns_suffix` follows each namespace (the rosbag2 export keeps each request's apart)."""

    def __init__(self, ns_suffix: str = "") -> None:
        self.shown: set[tuple[str, int]] = set()
        self.outline_ns, self.label_ns, self.velocity_ns = (
            ns + ns_suffix for ns in (OUTLINE_NS, LABEL_NS, VELOCITY_NS)
        )
        # The fields no marker here sets, made once and shared (messages are serialized, never
        # changed): a marker made field by field from defaults costs several times more.
        self._unset = {
            name: value
            for name, value in vars(ros("visualization_msgs/msg/Marker")).items()
            if name in ("lifetime", "frame_locked", "colors", "texture_resource", "texture", "uv_coordinates",
                        "mesh_resource", "mesh_file", "mesh_use_embedded_materials")
        }  # fmt: skip
        self._defaults = {**vars(ros("visualization_msgs/msg/Marker")), **self._unset}
        # And the constant poses, scales and colours of each kind of marker.
        self._origin = _pose(0, 0, 0)
        self._outline, self._label, self._arrow = (
            {"scale": _vector(*scale), "color": _color(*color)}
            for scale, color in (OUTLINE_LOOK, LABEL_LOOK, ARROW_LOOK)
        )

    def _marker(self, **fields: Any) -> Any:
        return message_class("visualization_msgs/msg/Marker")(**{**self._defaults, **fields})

    def ended(self, snapshot: Snapshot, moves: Sequence[bool] | None = None) -> list[tuple[str, int]]:
        """(namespace, id) of every marker shown before that `snapshot` no longer has, sorted (each
        gets a DELETE); what is shown becomes `snapshot`'s markers. Both encoders of /drvs/markers
        (markers() here, drvs.ros2.cdr) call it once a snapshot; `moves`: moving() of each object,
        when the caller has it already."""
        if moves is None:
            moves = [moving(o) for o in snapshot.objects]
        now: set[tuple[str, int]] = set()
        for o, moves_now in zip(snapshot.objects, moves, strict=True):
            now.add((self.outline_ns, o.track_id))
            now.add((self.label_ns, o.track_id))
            if moves_now:
                now.add((self.velocity_ns, o.track_id))
        ended = sorted(self.shown - now)
        self.shown = now
        return ended

    def markers(self, snapshot: Snapshot, style: Style, hdr: Any) -> Any:
        marker = self._marker
        out = []
        for o in snapshot.objects:
            h = style.height(o)
            ring = [_point(x, y, OUTLINE_Z_M) for x, y in outline(o).exterior.coords]
            out.append(
                marker(header=hdr, ns=self.outline_ns, id=o.track_id, type=LINE_STRIP, action=ADD, pose=self._origin,
                       points=ring, **self._outline)
            )  # fmt: skip
            cx, cy = o.centroid_xy
            out.append(
                marker(header=hdr, ns=self.label_ns, id=o.track_id, type=TEXT_VIEW_FACING, action=ADD,
                       pose=_pose(cx, cy, h + LABEL_RAISE_M), text=label_text(o.track_id, style.object_type(o)),
                       **self._label)
            )  # fmt: skip
            if moving(o):
                vx, vy = o.velocity_xy
                out.append(
                    marker(header=hdr, ns=self.velocity_ns, id=o.track_id, type=ARROW, action=ADD, pose=self._origin,
                           points=[_point(cx, cy, h / 2), _point(cx + vx, cy + vy, h / 2)], **self._arrow)
                )  # fmt: skip
        for ns, track_id in self.ended(snapshot):
            out.append(marker(header=hdr, ns=ns, id=track_id, action=DELETE))
        return ros("visualization_msgs/msg/MarkerArray", markers=out)


#: The least speed that gets a velocity arrow: a standing object's tracked velocity jitters by a
#: few mm/s (and, as millimetre integers on the wire, is now and then exactly 0), which would make
#: its arrow, one second of motion long and so a few millimetres, flicker on and off in RViz.
ARROW_MIN_MPS = 0.05


def moving(o: WorldObject) -> bool:
    """Whether the object gets a velocity arrow: it moves at ARROW_MIN_MPS or faster."""
    return o.speed_mps >= ARROW_MIN_MPS


def label_text(track_id: int, object_type: str) -> str:
    """A label marker's text: "#<track id> <object type>"."""
    return f"#{track_id} {object_type}"


def diagnostics(snapshot: Snapshot, hdr: Any, name: str = "drvs") -> Any:
    """diagnostic_msgs/DiagnosticArray: a WARN per camera missing from the snapshot (its code and
    why), an OK per camera that answered, and one for the region: WARN with the square metres no
    camera sees when some floor is uncovered, else OK."""
    kv = functools.partial(ros, "diagnostic_msgs/msg/KeyValue")
    status = functools.partial(ros, "diagnostic_msgs/msg/DiagnosticStatus")
    out = [
        status(level=WARN, name=f"{name}: camera {m.camera_id}", hardware_id=m.camera_id,
               message=f"{m.code}: {m.message}", values=[kv(key="code", value=m.code)])
        for m in snapshot.camera_errors.values()
    ]  # fmt: skip
    out += [
        status(level=OK, name=f"{name}: camera {c}", hardware_id=c, message="answered") for c in snapshot.camera_ids
    ]
    unseen = sum(p.area for p in snapshot.uncovered)
    region_values = [
        kv(key="objects", value=str(len(snapshot.objects))),
        kv(key="missing_cameras", value=str(len(snapshot.camera_errors))),
        kv(key="uncovered_m2", value=f"{unseen:.3f}"),
        kv(key="request_id", value=snapshot.request_id),
    ]
    message = f"{unseen:.1f} m² of the region no camera sees" if snapshot.uncovered else "the whole region is seen"
    level = WARN if snapshot.uncovered else OK
    out.append(status(level=level, name=f"{name}: region", message=message, values=region_values))
    return ros("diagnostic_msgs/msg/DiagnosticArray", header=hdr, status=out)


def region_from_points(points: Iterable[tuple[float, float]], what: str) -> Polygon:
    """A region from a polygon's corners, or InvalidArgument saying why it is none."""
    corners = [(float(x), float(y)) for x, y in points]
    if len(corners) >= 2 and corners[0] == corners[-1]:
        corners.pop()
    if len(corners) < 3:
        raise InvalidArgument(f"{what}: a region needs at least three points, got {len(corners)}")
    if not all(math.isfinite(v) for c in corners for v in c):
        raise InvalidArgument(f"{what}: a point is not a finite number")
    polygon = Polygon(corners)
    if not polygon.is_valid or polygon.area <= 0:
        raise InvalidArgument(f"{what}: not a simple polygon with an area (it crosses itself or is flat)")
    return orient(polygon)


def region_from_msg(message: Any, frame_id: str) -> Polygon:
    """A geometry_msgs/PolygonStamped as the region, in `frame_id` (an empty header.frame_id counts
    as it); InvalidArgument when it is in another frame or is not a polygon."""
    given = message.header.frame_id
    if given and given != frame_id:
        raise InvalidArgument(f"region in frame {given!r}: the bridge publishes in {frame_id!r}")
    return region_from_points(((p.x, p.y) for p in message.polygon.points), "region")


#: The bridge's topics under its prefix, and their types (docs/ros2.md, "Topics").
PREFIXED_TOPICS = {
    "objects": "vision_msgs/msg/Detection3DArray",
    "obstacles": "sensor_msgs/msg/PointCloud2",
    "tracks": "nav2_dynamic_msgs/msg/ObstacleArray",
    "markers": "visualization_msgs/msg/MarkerArray",
}
DIAGNOSTICS_TOPIC = ("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")
REGION_TYPE = "geometry_msgs/msg/PolygonStamped"
CLOCK_TOPIC = ("/clock", "rosgraph_msgs/msg/Clock")


def output_topics(prefix: str) -> dict[str, str]:
    """ROS 2 topic -> type of everything the bridge publishes, under `prefix` (e.g. /drvs)."""
    topics = {f"{prefix}/{name}": kind for name, kind in PREFIXED_TOPICS.items()}
    topics[DIAGNOSTICS_TOPIC[0]] = DIAGNOSTICS_TOPIC[1]
    return topics


def snapshot_messages(
    snapshot: Snapshot, style: Style, markers: MarkerState, at: float, prefix: str, *, with_diagnostics: bool = True
) -> Iterator[tuple[str, Any]]:
    """(topic, message) for everything one snapshot publishes, stamped `at` (seconds in the robot's
    clock), each made when it is asked for (the bridge writes one before it makes the next):
    objects first, then obstacles, tracks, markers and, `with_diagnostics`, /diagnostics."""
    hdr = header(at, style.frame_id)
    yield f"{prefix}/objects", detections(snapshot, style, hdr)
    yield f"{prefix}/obstacles", obstacle_cloud(snapshot, style, hdr)
    yield f"{prefix}/tracks", obstacles(snapshot, style, hdr)
    yield f"{prefix}/markers", markers.markers(snapshot, style, hdr)
    if with_diagnostics:
        yield DIAGNOSTICS_TOPIC[0], diagnostics(snapshot, hdr)

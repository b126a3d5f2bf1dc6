"""The one module that converts between wire messages (drvs.v1) and domain objects."""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import shapely
from shapely.geometry import Polygon

from drvs.core.errors import InvalidArgument
from drvs.core.geometry import MAX_REGION_VERTICES, Homography, box_region, polygon_coords, polygon_region
from drvs.core.model import (
    DEFAULT_FRAME,
    CameraError,
    ContinuousMode,
    Detection,
    DetectionReport,
    DetectionRequest,
    FusionOptions,
    PixelBox,
    Pose2,
    Snapshot,
    WorldObject,
    check_frame,
    errors_by_camera,
)
from drvs.v1 import detection_pb2, geometry_pb2, registry_pb2


def polygon_to_pb(poly: Polygon) -> geometry_pb2.Polygon:
    return geometry_pb2.Polygon(points=[geometry_pb2.Point2(x=x, y=y) for x, y in polygon_coords(poly)])


def _check_vertices(msg: geometry_pb2.Polygon, name: str) -> None:
    if len(msg.points) > MAX_REGION_VERTICES:
        raise InvalidArgument(f"{name}: {len(msg.points)} points; at most {MAX_REGION_VERTICES}, simplify the region")


def polygon_from_pb(msg: geometry_pb2.Polygon, name: str) -> Polygon:
    _check_vertices(msg, name)
    return polygon_region(((p.x, p.y) for p in msg.points), name)


def region_to_pb(region: Polygon) -> geometry_pb2.Region:
    """A rectangle travels as the paper's box, anything else as a polygon."""
    if region.equals(region.envelope):
        x0, y0, x1, y1 = region.bounds
        return geometry_pb2.Region(box=geometry_pb2.Box(x_lower=x0, y_lower=y0, x_upper=x1, y_upper=y1))
    return geometry_pb2.Region(polygon=polygon_to_pb(region))


#: A region's encoded size: 1000 points take about 20 000 bytes; the rest is room for unknown
#: fields, which a sender could otherwise use to make every forward of its request megabytes long.
MAX_REGION_BYTES = 24 * 1024
#: Decoded regions kept, by count and by (estimated) memory: a region is at most MAX_REGION_BYTES,
#: so the cache holds either many small regions or a few large ones, never a gigabyte.
REGION_CACHE_SIZE = 1024
REGION_CACHE_BYTES = 8 * 1024 * 1024
#: Memory of a decoded polygon per byte of its encoding (GEOS coordinates, the prepared index,
#: the key), measured roughly; a fixed cost per entry on top.
_DECODED_PER_BYTE = 4
_ENTRY_BYTES = 1024


class RegionCache:
    """Decoded regions by their wire bytes, least recently used first out, within both a count and
    a byte budget. Thread-safe (robot code may convert regions from threads)."""

    def __init__(self, size: int = REGION_CACHE_SIZE, budget_bytes: int = REGION_CACHE_BYTES) -> None:
        self.size = size
        self.budget_bytes = budget_bytes
        self.bytes = 0
        self._entries: OrderedDict[tuple[bytes, str], Polygon] = OrderedDict()
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._entries)

    @staticmethod
    def cost(data: bytes) -> int:
        return _ENTRY_BYTES + len(data) * _DECODED_PER_BYTE

    def get(self, data: bytes, name: str) -> Polygon:
        key = (data, name)
        with self._lock:
            hit = self._entries.get(key)
            if hit is not None:
                self._entries.move_to_end(key)
                return hit
        region = _region(geometry_pb2.Region.FromString(data), name)  # a bad region raises every time
        cost = self.cost(data)
        with self._lock:
            if key not in self._entries and cost <= self.budget_bytes:
                self._entries[key] = region
                self.bytes += cost
                while len(self._entries) > self.size or self.bytes > self.budget_bytes:
                    (old, _name), _polygon = self._entries.popitem(last=False)
                    self.bytes -= self.cost(old)
        return region

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()
            self.bytes = 0


REGIONS = RegionCache()


def region_from_pb(msg: geometry_pb2.Region, name: str = "region") -> Polygon:
    """The validated region. Robots ask about the same regions again and again, so a region's
    polygon (immutable, and prepared once for the routing test) is kept by its wire bytes."""
    if msg.HasField("polygon"):
        _check_vertices(msg.polygon, f"{name}.polygon")
    size = msg.ByteSize()
    if size > MAX_REGION_BYTES:
        raise InvalidArgument(f"{name}: {size} bytes encoded; at most {MAX_REGION_BYTES}")
    return REGIONS.get(msg.SerializeToString(deterministic=True), name)


def _region(msg: geometry_pb2.Region, name: str) -> Polygon:
    shape = msg.WhichOneof("shape")
    if shape == "box":
        b = msg.box
        return box_region(b.x_lower, b.y_lower, b.x_upper, b.y_upper, name)
    if shape == "polygon":
        return polygon_from_pb(msg.polygon, f"{name}.polygon")
    raise InvalidArgument(f"{name}: missing; give a box or a polygon")


def request_to_pb(
    req: DetectionRequest, *, region: geometry_pb2.Region | None = None
) -> detection_pb2.DetectionRequest:
    """`region`: the request's region already encoded (a client that keeps its regions encoded)."""
    return detection_pb2.DetectionRequest(
        request_id=req.request_id,
        robot_id=req.robot_id,
        filter_def=req.filter_def,
        region=region if region is not None else region_to_pb(req.region),
        callback_address=req.callback_address,
        continuous=None
        if req.continuous.single_shot
        else detection_pb2.ContinuousMode(rate_hz=req.continuous.rate_hz, duration_s=req.continuous.duration_s),
        omit_outlines=req.omit_outlines,
        fusion=None
        if req.fusion is None
        else detection_pb2.FusionOptions(
            deadline_s=req.fusion.deadline_s,
            drop_after_s=req.fusion.drop_after_s,
            compact_geometry=req.fusion.compact_geometry,
        ),
        frame="" if req.frame == DEFAULT_FRAME else req.frame,
    )


def request_from_pb(msg: detection_pb2.DetectionRequest, *, require_request_id: bool = True) -> DetectionRequest:
    """Validate every field; InvalidArgument names the first one that is wrong."""
    req = DetectionRequest(
        request_id=msg.request_id,
        robot_id=msg.robot_id,
        filter_def=msg.filter_def,
        region=region_from_pb(msg.region) if msg.HasField("region") else _missing_region(),
        callback_address=msg.callback_address,
        continuous=ContinuousMode(msg.continuous.rate_hz, msg.continuous.duration_s),
        omit_outlines=msg.omit_outlines,
        report_key=msg.report_key,
        fusion=FusionOptions(msg.fusion.deadline_s, msg.fusion.drop_after_s, msg.fusion.compact_geometry)
        if msg.HasField("fusion")
        else None,
        report_to_server=msg.report_to_server,
        report_address=msg.report_address,
        frame=check_frame(msg.frame),
    )
    req.validate(require_request_id=require_request_id)
    return req


def _missing_region() -> Polygon:
    raise InvalidArgument("region: missing; give a box or a polygon")


def detection_to_pb(d: Detection, outline: bool = True) -> detection_pb2.Detection:
    """outline=False: the paper's bounding box, with centroid and ground contact, and nothing else."""
    x0, y0, x1, y1 = d.bounds
    msg = detection_pb2.Detection(
        bounds=geometry_pb2.FloorBox(x_lower=x0, y_lower=y0, x_upper=x1, y_upper=y1),
        centroid=geometry_pb2.FloorPoint(x=d.centroid_xy[0], y=d.centroid_xy[1]),
        ground_contact=geometry_pb2.FloorPoint(x=d.ground_contact_xy[0], y=d.ground_contact_xy[1]),
    )
    if outline:
        msg.outline_xy.extend(v for xy in polygon_coords(d.outline) for v in xy)
        msg.pixel_box.x, msg.pixel_box.y = d.pixel_box.x, d.pixel_box.y
        msg.pixel_box.width, msg.pixel_box.height = d.pixel_box.width, d.pixel_box.height
        msg.area_m2, msg.area_px, msg.score = d.area_m2, d.area_px, d.score
    # What a marker or a class is travels even without outlines: it is what the robot asked for.
    if d.marker_id is not None:
        msg.marker_id = d.marker_id
    if d.heading_deg is not None:
        msg.heading_deg = d.heading_deg
    if d.label:
        msg.label = d.label
    return msg


#: Shapely geometries are immutable: one empty outline serves every boxes-only detection
#: (building Polygon() per detection was a sixth of a robot's CPU at 30 requests a second).
_NO_OUTLINE = Polygon()


def detection_from_pb(msg: detection_pb2.Detection, camera_id: str, capture_time: float, filter_def: str) -> Detection:
    """`filter_def` is the request's: detections do not repeat it on the wire."""
    b = msg.bounds
    xy = msg.outline_xy
    # shapely.polygons straight from the coordinates (what Polygon(coords) ends in, less its checks
    # on what else it could be given), read by np.fromiter (faster than np.asarray on a repeated field).
    n = len(xy)
    outline = shapely.polygons(np.fromiter(xy, dtype=float, count=n).reshape(-1, 2)) if n >= 6 else _NO_OUTLINE
    return Detection(
        outline=outline,
        bounds=(b.x_lower, b.y_lower, b.x_upper, b.y_upper),
        centroid_xy=(msg.centroid.x, msg.centroid.y),
        ground_contact_xy=(msg.ground_contact.x, msg.ground_contact.y),
        pixel_box=PixelBox(msg.pixel_box.x, msg.pixel_box.y, msg.pixel_box.width, msg.pixel_box.height),
        area_m2=msg.area_m2,
        area_px=msg.area_px,
        score=msg.score,
        filter_def=filter_def,
        camera_id=camera_id,
        capture_time=capture_time,
        marker_id=msg.marker_id if msg.HasField("marker_id") else None,
        heading_deg=msg.heading_deg if msg.HasField("heading_deg") else None,
        label=msg.label,
    )


def report_to_pb(r: DetectionReport, outlines: bool = True) -> detection_pb2.DetectionReport:
    msg = detection_pb2.DetectionReport(
        request_id=r.request_id,
        camera_id=r.camera_id,
        sequence=r.sequence,
        final=r.final,
        detections=[detection_to_pb(d, outlines) for d in r.detections],
        error=r.error,
        error_code=r.error_code,
    )
    if r.capture_time:
        msg.capture_time.FromNanoseconds(round(r.capture_time * 1e9))
    if r.camera_pose is not None:
        msg.camera_pose.CopyFrom(pose_to_pb(r.camera_pose))
    return msg


def pose_to_pb(p: Pose2) -> geometry_pb2.Pose2:
    return geometry_pb2.Pose2(x=p.x, y=p.y, yaw=p.yaw)


def pose_from_pb(msg: geometry_pb2.Pose2, name: str = "pose") -> Pose2:
    """InvalidArgument naming `name` when a value is not finite."""
    return Pose2(msg.x, msg.y, msg.yaw).check(name)


def report_from_pb(msg: detection_pb2.DetectionReport, filter_def: str) -> DetectionReport:
    """`filter_def`: the filter the report's request asked for."""
    capture_time = msg.capture_time.ToNanoseconds() / 1e9 if msg.HasField("capture_time") else 0.0
    return DetectionReport(
        request_id=msg.request_id,
        camera_id=msg.camera_id,
        capture_time=capture_time,
        sequence=msg.sequence,
        final=msg.final,
        detections=tuple(detection_from_pb(d, msg.camera_id, capture_time, filter_def) for d in msg.detections),
        error=msg.error,
        error_code=msg.error_code,
        camera_pose=pose_from_pb(msg.camera_pose, "camera_pose") if msg.HasField("camera_pose") else None,
    )


def homography_to_pb(h: Homography) -> registry_pb2.Homography:
    return registry_pb2.Homography(m=h.to_list())


def homography_from_pb(msg: registry_pb2.Homography) -> Homography:
    return Homography.from_values(list(msg.m), "homography")


def _timestamp(ts: Any, seconds: float) -> None:
    if seconds:
        ts.FromNanoseconds(round(seconds * 1e9))


def _seconds(msg: Any, name: str) -> float:
    return getattr(msg, name).ToNanoseconds() / 1e9 if msg.HasField(name) else 0.0


#: The oldest `last_seen` (seconds before the snapshot's time) written as `last_seen_age_s`: a
#: float32 is within 2 us up to here; older (never in a track, dropped after 60 s at most) is a
#: Timestamp.
MAX_LAST_SEEN_AGE_S = 64.0


#: The largest magnitude a WorldObject.geometry_mm value holds (a sint32): about 2 000 km in millimetres.
_MAX_MM = 2**31 - 1


def _geometry_mm(o: WorldObject) -> list[int] | None:
    """WorldObject.geometry_mm's eight values (see the .proto): the centroid in millimetres, the
    bounds as offsets from it, the velocity in mm/s; None when one is not finite or too large."""
    try:
        cx, cy = round(o.centroid_xy[0] * 1000.0), round(o.centroid_xy[1] * 1000.0)
        x0, y0, x1, y1 = (round(v * 1000.0) for v in o.bounds)
        values = [cx, cy, x0 - cx, y0 - cy, x1 - cx, y1 - cy, round(o.velocity_xy[0] * 1000.0)]
        values.append(round(o.velocity_xy[1] * 1000.0))
    except (ValueError, OverflowError):  # NaN, infinity
        return None
    return values if all(-_MAX_MM <= v <= _MAX_MM for v in values) else None


def world_object_to_pb(
    o: WorldObject,
    outline: bool = True,
    into: detection_pb2.WorldObject | None = None,
    *,
    time: float = 0.0,
    cameras: Mapping[str, int] | None = None,
    compact: bool = False,
) -> detection_pb2.WorldObject:
    """`into`: a message to fill in place (a snapshot's `objects.add()`), instead of a new one.
    `time`: the snapshot's time as its message carries it, which `last_seen` is said relative to;
    `cameras`: the position of each camera in the snapshot's `camera_ids`, by which the object
    names its cameras (`camera_index`) when it names none outside it. Both are what make a snapshot
    small: 8-9 B an object less than an absolute Timestamp, 2 B (one camera) to 7 B (two) less
    than the cameras' names. `compact` (the robot's request set `FusionOptions.compact_geometry`:
    it reads them): the centroid, bounds and velocity go as millimetre integers (`geometry_mm`),
    about 27 B an object less than three messages of 32-bit floats; else as those floats, which a
    robot older than geometry_mm reads.

    Filled field by field rather than through the constructor: the constructor copies each
    sub-message it is given, and a snapshot's objects were copied again into the snapshot and the
    snapshot into its reply; together that was most of a fused request's conversion cost."""
    msg = detection_pb2.WorldObject() if into is None else into
    msg.track_id = o.track_id
    geometry = _geometry_mm(o) if compact else None
    if geometry is not None:
        msg.geometry_mm.extend(geometry)
    else:  # beyond what a millimetre integer holds: as 32-bit floats
        b = msg.bounds
        b.x_lower, b.y_lower, b.x_upper, b.y_upper = o.bounds
        c = msg.centroid
        c.x, c.y = o.centroid_xy
        v = msg.velocity
        v.x, v.y = o.velocity_xy
    msg.uncertainty_m = o.uncertainty_m
    if cameras is not None and all(c in cameras for c in o.camera_ids):
        msg.camera_index.extend([cameras[c] for c in o.camera_ids])
    else:  # alone, or naming a camera its snapshot does not list: by name
        msg.camera_ids.extend(o.camera_ids)
    msg.label = o.label
    msg.score = o.score
    msg.area_m2 = o.area_m2
    if outline and not o.outline.is_empty:
        # The exterior ring without its closing point (geometry.polygon_coords), as one array.
        msg.outline_xy.extend(shapely.get_coordinates(o.outline.exterior)[:-1].ravel().tolist())
    if o.course_deg is not None:
        msg.heading_deg = o.course_deg
    if o.marker_id is not None:
        msg.marker_id = o.marker_id
    if o.marker_heading_deg is not None:
        msg.marker_heading_deg = o.marker_heading_deg
    age = time - o.last_seen
    if o.last_seen and 0.0 <= age <= MAX_LAST_SEEN_AGE_S:
        msg.last_seen_age_s = age  # 0: nothing on the wire
    else:
        # Not an age (seen after the snapshot's time, long before it, the time is not known, or
        # last_seen is not): set, even when empty (0, not known), so that it is not read as an age.
        msg.last_seen.SetInParent()
        _timestamp(msg.last_seen, o.last_seen)
    return msg


def world_object_from_pb(
    msg: detection_pb2.WorldObject, snapshot: detection_pb2.WorldSnapshot | None = None, name: str = "object"
) -> WorldObject:
    """`snapshot`: the message `msg` came in. A current server's objects need it: their
    `last_seen_age_s` counts back from its `time`, their `camera_index` points into its
    `camera_ids`; without it only an object that carries `last_seen` and `camera_ids` itself (an
    older server's) is read, and any other is refused (InvalidArgument). `name` names the object in
    errors."""
    if snapshot is None:
        if not msg.HasField("last_seen") or msg.camera_index:
            raise InvalidArgument(
                f"{name}: its last_seen_age_s and camera_index refer to its snapshot's time and camera_ids; "
                "read it with its snapshot (snapshot_from_pb)"
            )
        return _world_object(msg, 0.0, (), name)
    return _world_object(msg, _seconds(snapshot, "time"), snapshot.camera_ids, name)


def _world_object(msg: detection_pb2.WorldObject, time: float, cameras: Sequence[str], name: str | int) -> WorldObject:
    """`name`: the object's name in errors, or its index in its snapshot (named only on an error:
    reading a snapshot formats no name per object). Reads each field once: a robot following a
    track at 30 Hz does this for every object of every snapshot."""
    geometry = msg.geometry_mm[:]  # a list in one call (unpacking the container reads value by value)
    if geometry:
        if len(geometry) != 8:
            raise InvalidArgument(f"{_object_name(name)}.geometry_mm: {len(geometry)} values; there must be 8 or none")
        cx, cy, x0, y0, x1, y1, vx, vy = geometry
        bounds = ((cx + x0) / 1000.0, (cy + y0) / 1000.0, (cx + x1) / 1000.0, (cy + y1) / 1000.0)
        centroid_xy = (cx / 1000.0, cy / 1000.0)
        velocity_xy = (vx / 1000.0, vy / 1000.0)
    else:  # an older server's, or one no millimetre integer holds
        b, c, v = msg.bounds, msg.centroid, msg.velocity
        bounds = (b.x_lower, b.y_lower, b.x_upper, b.y_upper)
        centroid_xy = (c.x, c.y)
        velocity_xy = (v.x, v.y)
    if msg.HasField("last_seen"):  # an older server's, or one the age cannot say
        last_seen = _seconds(msg, "last_seen")
    else:
        age = msg.last_seen_age_s
        if not 0.0 <= age < math.inf:  # NaN fails too
            raise InvalidArgument(
                f"{_object_name(name)}.last_seen_age_s: {age!r} must be a finite number of seconds >= 0"
            )
        last_seen = time - age
    names = msg.camera_ids
    if names:  # an older server's
        camera_ids: tuple[str, ...] = tuple(names)
    else:
        index = msg.camera_index[:]
        if index and max(index) >= len(cameras):
            j, k = next((j, k) for j, k in enumerate(index) if k >= len(cameras))
            raise InvalidArgument(
                f"{_object_name(name)}.camera_index[{j}]: {k} is out of range: the snapshot's camera_ids "
                f"lists {len(cameras)} camera(s)"
            )
        camera_ids = tuple([cameras[k] for k in index])
    xy = msg.outline_xy
    return WorldObject(
        msg.track_id,
        Polygon(np.asarray(xy, dtype=float).reshape(-1, 2)) if len(xy) >= 6 else _NO_OUTLINE,
        bounds,
        centroid_xy,
        velocity_xy,
        msg.heading_deg if msg.HasField("heading_deg") else None,
        msg.uncertainty_m,
        camera_ids,
        last_seen,
        msg.marker_id if msg.HasField("marker_id") else None,
        msg.marker_heading_deg if msg.HasField("marker_heading_deg") else None,
        msg.label,
        msg.score,
        msg.area_m2,
    )


def _object_name(name: str | int) -> str:
    return f"snapshot.objects[{name}]" if isinstance(name, int) else name


def snapshot_to_pb(
    s: Snapshot,
    outlines: bool = True,
    into: detection_pb2.WorldSnapshot | None = None,
    *,
    compact: bool = False,
) -> detection_pb2.WorldSnapshot:
    """`into`: a message to fill in place (a reply's `snapshot`, cleared first), instead of a new one
    to copy there. `compact`: objects' geometry as millimetre integers (see world_object_to_pb)."""
    if into is None:
        msg = detection_pb2.WorldSnapshot()
    else:
        msg = into
        msg.Clear()
    msg.sequence = s.sequence
    msg.final = s.final
    _timestamp(msg.time, s.time)
    time = _seconds(msg, "time")  # as a reader will see it: ages count back from this
    cameras = {c: i for i, c in enumerate(s.camera_ids)}
    for o in s.objects:
        world_object_to_pb(o, outlines, msg.objects.add(), time=time, cameras=cameras, compact=compact)
    for m in s.camera_errors.values():
        msg.missing_cameras.add(camera_id=m.camera_id, code=m.code, message=m.message)
    msg.camera_ids.extend(s.camera_ids)
    return msg


def snapshot_from_pb(
    msg: detection_pb2.WorldSnapshot, request_id: str = "", uncovered: Sequence[Polygon] = ()
) -> Snapshot:
    """Reads a current server's objects (`last_seen_age_s`, `camera_index`) and an older one's
    (`last_seen`, `camera_ids`) alike; a malformed one is InvalidArgument naming the field.
    `uncovered`: what the request's reply said no camera sees."""
    t = msg.time  # as _seconds, without its checks: unset is 0, as it says
    time = (t.seconds * 1_000_000_000 + t.nanos) / 1e9
    cameras = tuple(msg.camera_ids)
    missing = msg.missing_cameras
    return Snapshot(
        time,
        tuple([_world_object(o, time, cameras, i) for i, o in enumerate(msg.objects)]),
        errors_by_camera(CameraError(m.code, m.message, m.camera_id) for m in missing) if missing else {},
        cameras,
        msg.sequence,
        msg.final,
        request_id,
        uncovered if isinstance(uncovered, tuple) else tuple(uncovered),
    )

"""Wire messages <-> domain objects: round trips, and request validation naming the bad field."""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest
from shapely.geometry import Point, Polygon

from drvs.core.errors import InvalidArgument
from drvs.core.geometry import box_region, homography_from_pose, polygon_coords, polygon_region
from drvs.core.model import (
    MAX_RATE_HZ,
    ContinuousMode,
    Detection,
    DetectionReport,
    DetectionRequest,
    FusionOptions,
    PixelBox,
    Snapshot,
    WorldObject,
)
from drvs.v1 import detection_pb2, geometry_pb2, registry_pb2
from drvs.wire.convert import (
    detection_from_pb,
    detection_to_pb,
    homography_from_pb,
    homography_to_pb,
    region_from_pb,
    region_to_pb,
    report_from_pb,
    report_to_pb,
    request_from_pb,
    request_to_pb,
    snapshot_from_pb,
    snapshot_to_pb,
    world_object_from_pb,
)

YELLOW = "hsv_014110130035225200"
GREEN = "hsv_040080080080255255"


def request(region: Polygon, continuous: ContinuousMode | None = None) -> DetectionRequest:
    return DetectionRequest(
        request_id="req-1",
        robot_id="robot.7",
        filter_def=YELLOW,
        region=region,
        callback_address="10.0.0.5:50070",
        continuous=continuous or ContinuousMode(),
    )


def valid_message() -> detection_pb2.DetectionRequest:
    return detection_pb2.DetectionRequest(
        request_id="req-1",
        robot_id="robot.7",
        filter_def=YELLOW,
        region=geometry_pb2.Region(box=geometry_pb2.Box(x_lower=-1.0, y_lower=0.0, x_upper=2.0, y_upper=3.5)),
        callback_address="127.0.0.1:50070",
    )


def detection(x: float, y: float, filter_def: str = YELLOW) -> Detection:
    outline = Point(x, y).buffer(0.25, quad_segs=4)
    return Detection(
        outline=outline,
        bounds=outline.bounds,
        centroid_xy=(outline.centroid.x, outline.centroid.y),
        ground_contact_xy=(x, y - 0.25),
        pixel_box=PixelBox(181, 194, 57, 34),
        area_m2=float(outline.area),
        area_px=1456.0,
        score=0.875,
        filter_def=filter_def,
        camera_id="cam1",
        capture_time=1_700_000_000.123456,
    )


# --- requests --------------------------------------------------------------------------------------


def test_box_request_round_trips_as_a_box() -> None:
    req = request(box_region(-1.0, 0.5, 2.0, 3.5), ContinuousMode(10.0, 2.5))
    msg = request_to_pb(req)
    assert msg.region.WhichOneof("shape") == "box"
    b = msg.region.box
    assert (b.x_lower, b.y_lower, b.x_upper, b.y_upper) == (-1.0, 0.5, 2.0, 3.5)
    back = request_from_pb(detection_pb2.DetectionRequest.FromString(msg.SerializeToString()))
    assert back.request_id == "req-1"
    assert back.robot_id == "robot.7"
    assert back.filter_def == YELLOW
    assert back.callback_address == "10.0.0.5:50070"
    assert back.continuous == ContinuousMode(10.0, 2.5)
    assert back.region.equals(req.region)
    assert back.region.bounds == (-1.0, 0.5, 2.0, 3.5)
    assert request_to_pb(back) == msg


def test_polygon_request_round_trips_as_a_polygon() -> None:
    points = [(0.0, 0.0), (4.0, 0.0), (4.0, 3.0), (2.0, 5.0), (0.0, 3.0)]
    req = request(polygon_region(points))
    msg = request_to_pb(req)
    assert msg.region.WhichOneof("shape") == "polygon"
    assert [(p.x, p.y) for p in msg.region.polygon.points] == points
    back = request_from_pb(detection_pb2.DetectionRequest.FromString(msg.SerializeToString()))
    assert back.region.equals(req.region)
    assert polygon_coords(back.region) == points
    assert back.continuous.single_shot
    assert request_to_pb(back) == msg


def test_region_round_trip() -> None:
    tri = polygon_region([(0.0, 0.0), (1.0, 0.0), (0.0, 1.0)])
    assert region_from_pb(region_to_pb(tri)).equals(tri)
    rect = box_region(3.0, 4.0, 5.0, 6.0)
    assert region_to_pb(rect).WhichOneof("shape") == "box"
    assert region_from_pb(region_to_pb(rect)).equals(rect)


def _with(**changes: object) -> detection_pb2.DetectionRequest:
    msg = valid_message()
    for key, value in changes.items():
        if key == "region":
            msg.ClearField("region")
            if value is not None:
                assert isinstance(value, geometry_pb2.Region)
                msg.region.CopyFrom(value)
        elif key in ("rate_hz", "duration_s"):
            setattr(msg.continuous, key, value)
        else:
            setattr(msg, key, value)
    return msg


def test_valid_message_is_accepted() -> None:
    req = request_from_pb(valid_message())
    assert req.region.bounds == (-1.0, 0.0, 2.0, 3.5)
    assert req.kind == "hsv"


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"region": None}, r"^region: missing"),
        ({"region": geometry_pb2.Region()}, r"^region: missing"),
        (
            {"region": geometry_pb2.Region(box=geometry_pb2.Box(x_lower=2.0, x_upper=1.0, y_upper=1.0))},
            r"^region\.box: x_lower 2 must be less than x_upper 1",
        ),
        (
            {"region": geometry_pb2.Region(box=geometry_pb2.Box(x_lower=math.nan, x_upper=1.0, y_upper=1.0))},
            r"^region\.box\.x_lower: nan is not finite",
        ),
        (
            {
                "region": geometry_pb2.Region(
                    polygon=geometry_pb2.Polygon(points=[geometry_pb2.Point2(x=0, y=0), geometry_pb2.Point2(x=1, y=1)])
                )
            },
            r"^region\.polygon: needs at least 3",
        ),
        ({"callback_address": "robot"}, r"^callback_address: 'robot' is not host:port"),
        ({"callback_address": ""}, r"^callback_address: empty"),
        ({"callback_address": "robot:0"}, r"^callback_address: port 0 is out of range"),
        ({"callback_address": "bad host:50070"}, r"^callback_address: 'bad host' is not a valid host"),
        ({"rate_hz": 10.0}, r"^continuous: rate_hz and duration_s must both be > 0"),
        ({"duration_s": 5.0}, r"^continuous: rate_hz and duration_s must both be > 0"),
        ({"rate_hz": -1.0, "duration_s": 1.0}, r"^continuous\.rate_hz: -1\.0 must be a finite number >= 0"),
        ({"rate_hz": math.nan, "duration_s": 1.0}, r"^continuous\.rate_hz: nan must be a finite number"),
        ({"rate_hz": math.inf, "duration_s": 1.0}, r"^continuous\.rate_hz: inf must be a finite number"),
        ({"rate_hz": 1e9, "duration_s": 1.0}, r"^continuous\.rate_hz: 1e\+09 exceeds the limit of 100"),
        ({"rate_hz": 1.0, "duration_s": 1e5}, r"^continuous\.duration_s: 100000 exceeds the limit of 3600"),
        ({"rate_hz": 1.0, "duration_s": -2.0}, r"^continuous\.duration_s: -2\.0 must be a finite number"),
        ({"request_id": ""}, r"^request_id: empty"),
        ({"request_id": "req 1"}, r"^request_id: 'req 1' may hold only"),
        ({"request_id": "r" * 129}, r"^request_id: longer than 128"),
        ({"robot_id": "robot/7"}, r"^robot_id: 'robot/7' may hold only"),
        ({"filter_def": ""}, r"^filter_def: empty"),
        ({"filter_def": "hsv_180110130035225200"}, r"^filter_def: H low = 180"),
        ({"filter_def": "rgb_1"}, r"^filter_def: unknown object type"),
    ],
)
def test_request_from_pb_names_the_bad_field(changes: dict[str, object], message: str) -> None:
    with pytest.raises(InvalidArgument, match=message):
        request_from_pb(_with(**changes))


def test_empty_request_id_allowed_when_not_required() -> None:
    # The server fills in the request id when the robot leaves it empty.
    req = request_from_pb(_with(request_id=""), require_request_id=False)
    assert req.request_id == ""
    # ... but a malformed one is still refused.
    with pytest.raises(InvalidArgument, match=r"^request_id: "):
        request_from_pb(_with(request_id="a b"), require_request_id=False)


def test_rate_at_the_limit_is_accepted() -> None:
    req = request_from_pb(_with(rate_hz=MAX_RATE_HZ, duration_s=1.0))
    assert req.continuous == ContinuousMode(MAX_RATE_HZ, 1.0)


# --- reports ---------------------------------------------------------------------------------------


def test_report_round_trip_with_detections() -> None:
    report = DetectionReport(
        request_id="req-1",
        camera_id="cam1",
        capture_time=1_700_000_000.123456,
        sequence=3,
        final=True,
        detections=(detection(-1.0, 4.0), detection(1.5, 3.0)),
    )
    msg = report_to_pb(report)
    assert msg.capture_time.seconds == 1_700_000_000
    assert abs(msg.capture_time.nanos - 123_456_000) < 1000
    back = report_from_pb(detection_pb2.DetectionReport.FromString(msg.SerializeToString()), YELLOW)
    assert back.request_id == "req-1"
    assert back.camera_id == "cam1"
    assert back.sequence == 3
    assert back.final is True
    assert back.error == ""
    assert abs(back.capture_time - report.capture_time) < 1e-6
    assert len(back.detections) == 2
    # Floor values travel as 32-bit floats: within a micrometre at these distances.
    um = 1e-6
    for got, sent in zip(back.detections, report.detections, strict=True):
        assert got.outline.equals_exact(sent.outline, um)
        assert np.allclose(got.bounds, sent.bounds, atol=um)
        assert got.centroid.equals_exact(sent.centroid, um)
        assert got.ground_contact.equals_exact(sent.ground_contact, um)
        assert got.pixel_box == sent.pixel_box
        assert got.area_m2 == pytest.approx(sent.area_m2, rel=1e-6)
        assert got.area_px == sent.area_px
        assert got.score == sent.score
        # The filter travels once, in the request; the robot fills it in.
        assert got.filter_def == YELLOW
        # Camera and capture time travel once per report and are copied into each detection.
        assert got.camera_id == "cam1"
        assert got.capture_time == back.capture_time


def test_boxes_only_detection_carries_bounds_centroid_and_contact_only() -> None:
    sent = detection(2.0, 1.0)
    full = detection_to_pb(sent)
    box = detection_to_pb(sent, outline=False)
    assert box.ByteSize() < full.ByteSize() / 3
    assert not box.outline_xy and not box.HasField("pixel_box")
    assert box.area_m2 == box.area_px == box.score == 0.0
    got = detection_from_pb(box, "cam1", 0.0, GREEN)
    assert got.outline.is_empty
    assert np.allclose(got.bounds, sent.bounds, atol=1e-6)
    assert got.centroid.equals_exact(sent.centroid, 1e-6)
    assert got.ground_contact.equals_exact(sent.ground_contact, 1e-6)
    assert got.filter_def == GREEN


def test_single_shot_request_sends_no_continuous_field() -> None:
    req = request_from_pb(_with())
    assert not request_to_pb(req).HasField("continuous")
    cont = dataclasses.replace(req, continuous=ContinuousMode(5.0, 2.0))
    assert request_from_pb(request_to_pb(cont)).continuous == ContinuousMode(5.0, 2.0)


def test_report_without_capture_time_or_detections() -> None:
    report = DetectionReport(
        request_id="req-2", camera_id="cam9", capture_time=0.0, sequence=0, final=True, error="camera unreachable"
    )
    msg = report_to_pb(report)
    assert not msg.HasField("capture_time")
    back = report_from_pb(msg, YELLOW)
    assert back == report


def test_homography_round_trip() -> None:
    h = homography_from_pose((1.0, 2.0, 3.0), 45.0, 35.0, 70.0, (800, 600))
    msg = registry_pb2.Homography.FromString(homography_to_pb(h).SerializeToString())
    assert len(msg.m) == 9
    assert homography_from_pb(msg).to_list() == h.to_list()
    with pytest.raises(InvalidArgument, match=r"^homography: expected 9 numbers"):
        homography_from_pb(registry_pb2.Homography(m=[1.0, 2.0]))


# --- continuous mode -------------------------------------------------------------------------------


def test_single_shot_report_times() -> None:
    mode = ContinuousMode()
    assert mode.single_shot
    assert mode.report_times() == [0.0]


def test_ten_hertz_for_one_second() -> None:
    times = ContinuousMode(10.0, 1.0).report_times()
    assert len(times) == 11
    assert times[0] == 0.0
    assert times[-1] == 1.0
    assert all(abs(b - a - 0.1) < 1e-12 for a, b in itertools.pairwise(times))


@pytest.mark.parametrize(
    ("rate", "duration", "count", "last"),
    [
        (1.0, 5.0, 6, 5.0),
        (3.0, 1.0, 4, 1.0),
        (2.0, 1.25, 3, 1.0),
        (100.0, 3600.0, 360_001, 3600.0),
    ],
)
def test_report_times_count_and_last(rate: float, duration: float, count: int, last: float) -> None:
    times = ContinuousMode(rate, duration).report_times()
    assert len(times) == count
    assert abs(times[-1] - last) < 1e-9
    assert times[-1] <= duration + 1e-9


# --- fused snapshots -------------------------------------------------------------------------------

T = 1_700_000_000.5  # a snapshot's time; the times and ages below are exact in float32 and float64


def world_object(
    track_id: int, x: float, cameras: tuple[str, ...] = ("cam1", "cam2"), last_seen: float = T, outline: bool = False
) -> WorldObject:
    shape = Polygon([(x, 2.0), (x + 0.5, 2.0), (x + 0.5, 2.5), (x, 2.5)])
    return WorldObject(
        track_id=track_id,
        outline=shape if outline else Polygon(),
        bounds=shape.bounds,
        centroid_xy=(x + 0.25, 2.25),
        velocity_xy=(0.375, -0.125),
        heading_deg=-18.5,
        uncertainty_m=0.03125,
        camera_ids=cameras,
        last_seen=last_seen,
        label="person",
        score=0.875,
        area_m2=0.25,
    )


def fused(*objects: WorldObject, time: float = T, cameras: tuple[str, ...] = ("cam1", "cam2")) -> Snapshot:
    return Snapshot(time=time, objects=objects, camera_ids=cameras, sequence=17, final=False, request_id="track-1")


def wire(snapshot: Snapshot, outlines: bool = True, compact: bool = True) -> detection_pb2.WorldSnapshot:
    """What a robot reads: the server's encoding, serialised and parsed (`compact`: for a robot that
    asked for geometry_mm, as every DrvsClient does)."""
    data = snapshot_to_pb(snapshot, outlines, compact=compact).SerializeToString()
    return detection_pb2.WorldSnapshot.FromString(data)


def old_style(
    msg: detection_pb2.WorldSnapshot, snapshot: Snapshot, geometry: bool = True
) -> detection_pb2.WorldSnapshot:
    """`msg` as a server before last_seen_age_s and camera_index wrote it: each object's absolute
    last_seen and its cameras' names; `geometry`: and before geometry_mm, its bounds, centroid and
    velocity as 32-bit floats."""
    old = detection_pb2.WorldSnapshot()
    old.CopyFrom(msg)
    for pb, o in zip(old.objects, snapshot.objects, strict=True):
        pb.ClearField("last_seen_age_s")
        pb.ClearField("camera_index")
        pb.camera_ids.extend(o.camera_ids)
        if o.last_seen:
            pb.last_seen.FromNanoseconds(round(o.last_seen * 1e9))
        if geometry:
            floats(pb, o)
    return old


def floats(pb: detection_pb2.WorldObject, o: WorldObject) -> None:
    """`pb`'s bounds, centroid and velocity as three messages of 32-bit floats, no geometry_mm."""
    pb.ClearField("geometry_mm")
    pb.bounds.x_lower, pb.bounds.y_lower, pb.bounds.x_upper, pb.bounds.y_upper = o.bounds
    pb.centroid.x, pb.centroid.y = o.centroid_xy
    pb.velocity.x, pb.velocity.y = o.velocity_xy


def assert_same(got: Snapshot, sent: Snapshot, within_s: float) -> None:
    """Equal, but for the objects' last_seen, which is within `within_s`: an absolute Timestamp is
    whole nanoseconds (their float64 quotient can be a 0.24 us step off), an age a float32."""
    assert len(got.objects) == len(sent.objects)
    for a, b in zip(got.objects, sent.objects, strict=True):
        assert abs(a.last_seen - b.last_seen) <= within_s, (a.last_seen, b.last_seen)
    fixed = tuple(dataclasses.replace(a, last_seen=b.last_seen) for a, b in zip(got.objects, sent.objects, strict=True))
    assert dataclasses.replace(got, objects=fixed) == sent


def test_snapshot_round_trips_with_ages_and_camera_indices() -> None:
    snapshot = fused(
        world_object(1, 1.0),  # seen by both cameras at the snapshot's time
        world_object(2, 3.0, ("cam2",), last_seen=T - 0.25, outline=True),  # one camera, earlier
        world_object(3, 5.0, (), last_seen=T - 0.5),  # predicted: no camera this period
        world_object(4, 7.0, ("cam1", "cam2", "cam3"), last_seen=T - 0.125),  # several cameras
        cameras=("cam1", "cam2", "cam3"),
    )
    msg = wire(snapshot)
    assert snapshot_from_pb(msg, "track-1") == snapshot
    # Ages and indices on the wire, no absolute times and no names in the objects.
    assert [o.last_seen_age_s for o in msg.objects] == [0.0, 0.25, 0.5, 0.125]
    assert [list(o.camera_index) for o in msg.objects] == [[0, 1], [1], [], [0, 1, 2]]
    assert not any(o.HasField("last_seen") or o.camera_ids for o in msg.objects)
    assert list(msg.camera_ids) == ["cam1", "cam2", "cam3"]


@pytest.mark.parametrize("age", [0.0166, 0.3, 1.0, 59.9, 64.0])
def test_an_age_is_a_float32_within_two_microseconds(age: float) -> None:
    time = 1_712_345_678.123456
    o = world_object(1, 1.0, last_seen=time - age)
    msg = wire(fused(o, time=time))
    assert not msg.objects[0].HasField("last_seen")
    assert_same(snapshot_from_pb(msg), dataclasses.replace(fused(o, time=time), request_id=""), 2e-6)


@pytest.mark.parametrize(
    ("last_seen", "time"),
    [
        (T + 0.25, T),  # after the snapshot's time: a camera whose clock runs ahead
        (T - 65.0, T),  # longer before it than an age says precisely
        (0.0, T),  # not known
        (T, 0.0),  # the snapshot's time not known
    ],
)
def test_a_last_seen_that_no_age_says_travels_as_a_timestamp(last_seen: float, time: float) -> None:
    snapshot = fused(world_object(1, 1.0, last_seen=last_seen), time=time)
    msg = wire(snapshot)
    assert msg.objects[0].HasField("last_seen") and msg.objects[0].last_seen_age_s == 0.0
    assert_same(snapshot_from_pb(msg, "track-1"), snapshot, 1e-6)


def test_an_object_naming_a_camera_its_snapshot_does_not_list_names_its_cameras() -> None:
    snapshot = fused(world_object(1, 1.0, ("cam1", "scout")), world_object(2, 3.0, ("cam2",)))
    msg = wire(snapshot)
    assert list(msg.objects[0].camera_ids) == ["cam1", "scout"] and not msg.objects[0].camera_index
    assert list(msg.objects[1].camera_index) == [1] and not msg.objects[1].camera_ids
    assert snapshot_from_pb(msg, "track-1") == snapshot


def test_an_older_servers_snapshot_is_read_as_before() -> None:
    snapshot = fused(
        world_object(1, 1.0),
        world_object(2, 3.0, ("cam2",), last_seen=T - 0.25),
        world_object(3, 5.0, (), last_seen=T - 0.5),
    )
    old = detection_pb2.WorldSnapshot.FromString(old_style(wire(snapshot), snapshot).SerializeToString())
    assert all(o.HasField("last_seen") and not o.camera_index for o in old.objects)
    assert_same(snapshot_from_pb(old, "track-1"), snapshot, 1e-6)
    # Its objects also read alone, as they always did.
    assert_same(fused(world_object_from_pb(old.objects[1])), fused(snapshot.objects[1]), 1e-6)


def test_a_current_object_reads_with_its_snapshot_only() -> None:
    snapshot = fused(world_object(1, 1.0), world_object(2, 3.0, ("cam2",), last_seen=T - 0.25))
    msg = wire(snapshot)
    assert world_object_from_pb(msg.objects[1], msg) == snapshot.objects[1]
    with pytest.raises(InvalidArgument, match=r"object: its last_seen_age_s and camera_index refer to its snapshot"):
        world_object_from_pb(msg.objects[1])


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"camera_index": [0, 2]}, r"snapshot.objects\[1\].camera_index\[1\]: 2 is out of range: .* 2 camera\(s\)"),
        ({"camera_index": [4_294_967_295]}, r"snapshot.objects\[1\].camera_index\[0\]: 4294967295 is out of range"),
        ({"last_seen_age_s": -0.5}, r"snapshot.objects\[1\].last_seen_age_s: -0.5 must be a finite number"),
        ({"last_seen_age_s": math.nan}, r"snapshot.objects\[1\].last_seen_age_s: nan must be a finite number"),
        ({"last_seen_age_s": math.inf}, r"snapshot.objects\[1\].last_seen_age_s: inf must be a finite number"),
        ({"geometry_mm": [1, 2, 3]}, r"snapshot.objects\[1\].geometry_mm: 3 values; there must be 8 or none"),
    ],
)
def test_a_malformed_object_is_refused_naming_the_field(change: dict[str, object], message: str) -> None:
    msg = wire(fused(world_object(1, 1.0), world_object(2, 3.0)))
    bad = msg.objects[1]
    for name, value in change.items():
        bad.ClearField(name)
        if isinstance(value, list):
            getattr(bad, name).extend(value)
        else:
            setattr(bad, name, value)
    with pytest.raises(InvalidArgument, match=message):
        snapshot_from_pb(detection_pb2.WorldSnapshot.FromString(msg.SerializeToString()))


def test_a_three_object_two_camera_snapshot_is_48_bytes_smaller() -> None:
    """The drvs_track case: three boxes seen by both cameras, a continuous request's ages. Each
    object saves 9 B on its time (a Timestamp of 5-byte seconds and 5-byte nanos, with its tag and
    length: 14 B, against a float's 5) and 7 B on its cameras (two names of 4 letters: 12 B,
    against 2 B of tag, 1 of length and 2 indices)."""
    time = 1_712_345_678.875
    snapshot = fused(*(world_object(i + 1, 2.0 * i, last_seen=time - 0.0166 - 0.01 * i) for i in range(3)), time=time)
    new = wire(snapshot, outlines=False)
    old = old_style(new, snapshot, geometry=False)
    assert all(o.last_seen.nanos >= 2**28 for o in old.objects)  # 5 varint bytes each
    assert old.ByteSize() - new.ByteSize() == 3 * (9 + 7) == 48
    # The same on the robot's stream, and the same objects either way.
    old_reply = detection_pb2.DetectionReply(request_id="track-1", snapshot=old)
    new_reply = detection_pb2.DetectionReply(request_id="track-1", snapshot=new)
    assert old_reply.ByteSize() - new_reply.ByteSize() == 48
    assert_same(snapshot_from_pb(new), snapshot_from_pb(old), 1e-6)


def test_centroid_bounds_and_velocity_travel_as_millimetre_integers() -> None:
    """Eight zig-zag varints (the bounds less the centroid), not three messages of floats: 27 B an
    object less here (field 17's tag is 2 B), each value within half a millimetre."""
    o = dataclasses.replace(
        world_object(1, 18.7013),
        bounds=(18.7013, -4.19595, 19.2977, 4.80298),
        centroid_xy=(18.99867, 4.49879),
        velocity_xy=(0.0037, -0.01283),
    )
    msg = wire(fused(o))
    pb = msg.objects[0]
    assert list(pb.geometry_mm) == [18999, 4499, -298, -8695, 299, 304, 4, -13]
    assert not (pb.HasField("bounds") or pb.HasField("centroid") or pb.HasField("velocity"))
    got = snapshot_from_pb(msg, "track-1").objects[0]
    assert got.centroid_xy == (18.999, 4.499) and got.velocity_xy == (0.004, -0.013)
    assert got.bounds == (18.701, -4.196, 19.298, 4.803)
    sent = (*o.bounds, *o.centroid_xy, *o.velocity_xy)
    assert max(abs(a - b) for a, b in zip((*got.bounds, *got.centroid_xy, *got.velocity_xy), sent, strict=True)) <= 5e-4
    assert dataclasses.replace(got, bounds=o.bounds, centroid_xy=o.centroid_xy, velocity_xy=o.velocity_xy) == o
    as_floats = detection_pb2.WorldSnapshot()
    as_floats.CopyFrom(msg)
    floats(as_floats.objects[0], o)
    assert as_floats.ByteSize() - msg.ByteSize() == 27


def test_a_robot_that_did_not_ask_for_millimetre_integers_gets_floats() -> None:
    """An older robot reads only the three messages: a request without compact_geometry gets them,
    and this package reads them the same."""
    o = world_object(1, 18.7013)
    msg = wire(fused(o), compact=False)
    pb = msg.objects[0]
    assert not pb.geometry_mm and pb.HasField("bounds") and pb.HasField("centroid") and pb.HasField("velocity")
    assert (pb.centroid.x, pb.centroid.y) == pytest.approx(o.centroid_xy, rel=1e-7)
    assert msg.ByteSize() - wire(fused(o)).ByteSize() >= 20  # what geometry_mm saves: 26 B here
    assert snapshot_from_pb(msg, "track-1").objects[0].centroid_xy == pytest.approx(o.centroid_xy, rel=1e-7)


def test_the_request_says_whether_the_robot_reads_millimetre_integers() -> None:
    """A DrvsClient's fused request says so on the wire; an older robot's FusionOptions (the flag
    unset) reads back as not asking."""
    req = dataclasses.replace(request(box_region(0, 0, 1, 1)), callback_address="", fusion=FusionOptions())
    pb = request_to_pb(req)
    assert pb.fusion.compact_geometry
    back = request_from_pb(pb)
    assert back.fusion is not None and back.fusion.compact_geometry
    pb.fusion.compact_geometry = False
    back = request_from_pb(pb)
    assert back.fusion is not None and not back.fusion.compact_geometry


@pytest.mark.parametrize(
    "change",
    [
        {"centroid_xy": (2_200_000.0, 2.25)},  # past 2 000 km: no sint32 of millimetres holds it
        {"bounds": (1.0, 2.0, 1.5, math.inf)},
        {"velocity_xy": (math.nan, 0.0)},
    ],
)
def test_a_value_no_millimetre_integer_holds_travels_as_floats(change: dict[str, object]) -> None:
    o = dataclasses.replace(world_object(1, 1.0), **change)
    msg = wire(fused(o))
    pb = msg.objects[0]
    assert not pb.geometry_mm and pb.HasField("bounds") and pb.HasField("centroid") and pb.HasField("velocity")
    got = snapshot_from_pb(msg, "track-1").objects[0]
    sent = (*o.bounds, *o.centroid_xy, *o.velocity_xy)
    for a, b in zip((*got.bounds, *got.centroid_xy, *got.velocity_xy), sent, strict=True):
        assert a == b or (math.isnan(a) and math.isnan(b)) or abs(a - b) <= 1e-7 * abs(b)

"""drvs.server.fusion on real camera geometry: ground sampling distance from real homographies, merging of
one object seen by several cameras, what must never merge, precision weighting, and the whole path
on real pixels (two overlapping simulated cameras, the HSV detector the camera node runs, fuse)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray
from shapely.geometry import Point, Polygon
from shapely.geometry import box as floor_box

from drvs.core.errors import InvalidArgument
from drvs.core.filters import HsvRange, object_type
from drvs.core.geometry import FieldOfView, Homography, homography_from_pose
from drvs.core.model import Detection, DetectionReport
from drvs.detectors import CameraView, FrameAnalysis, HsvDetector
from drvs.detectors import Frame as DetFrame
from drvs.detectors.base import REGISTRY
from drvs.server.fusion import PIXEL_SIGMA, fuse, ground_sampling_distance
from drvs.sim.render import CameraRenderer
from drvs.sim.scenario import parse_scenario
from drvs.sim.scene import FloorPatch, render_view
from tests.helpers import GREEN, IMAGE_SIZE, YELLOW

T0 = 1_700_000_000.0
#: Two cameras 3 m up on opposite walls of a 12 m room, looking at each other 40 degrees down:
#: both see the middle (y about 2.5 .. 9.5) at different distances.
SOUTH = homography_from_pose((0.0, 0.0, 3.0), 90.0, 40.0, 60.0, IMAGE_SIZE)
NORTH = homography_from_pose((0.0, 12.0, 3.0), -90.0, 40.0, 60.0, IMAGE_SIZE)
CAMERAS = {"south": SOUTH, "north": NORTH}


def view(camera_id: str) -> CameraView:
    h = CAMERAS[camera_id]
    return CameraView(h, FieldOfView.compute(h, IMAGE_SIZE, 15.0), IMAGE_SIZE, camera_id=camera_id)


def seen(
    camera_id: str,
    shape: Polygon,
    *,
    shift_px: tuple[float, float] = (0.0, 0.0),
    filter_def: str = YELLOW,
    marker_id: int | None = None,
    label: str = "",
    t: float = T0,
) -> Detection:
    """The detection a camera makes of a floor shape: its outline projected into the image (through
    the real homography), moved by shift_px (the detector's error, pixels), mapped back to the floor."""
    v = view(camera_id)
    floor = np.asarray(shape.exterior.coords)[:-1]
    pixels = v.homography.inverse().apply(floor) + np.asarray(shift_px)
    d = v.detection(pixels, filter_def, t, score=0.9, marker_id=marker_id, label=label)
    assert d is not None
    return d


def report(camera_id: str, *detections: Detection, t: float = T0, error: str = "") -> DetectionReport:
    return DetectionReport("r1", camera_id, t, 0, True, tuple(detections), error=error)


def square(x: float, y: float, side: float = 0.4) -> Polygon:
    return floor_box(x - side / 2, y - side / 2, x + side / 2, y + side / 2)


# --- ground sampling distance ------------------------------------------------------------------


def pixel_footprint(h: Homography, floor_xy: tuple[float, float]) -> float:
    """The floor area one pixel covers at floor_xy, measured: the pixel's four corners mapped with
    OpenCV's perspectiveTransform and the quadrilateral's area (shapely)."""
    u, v = h.inverse().apply([floor_xy])[0]
    corners = np.array([[[u - 0.5, v - 0.5], [u + 0.5, v - 0.5], [u + 0.5, v + 0.5], [u - 0.5, v + 0.5]]])
    floor = cv2.perspectiveTransform(corners, h.matrix)[0]
    return float(Polygon(floor).area)


@pytest.mark.parametrize("xy", [(0.0, 2.5), (1.0, 5.0), (-2.0, 8.0), (0.5, 9.5)])
def test_gsd_is_the_side_of_the_floor_a_pixel_covers(xy: tuple[float, float]) -> None:
    assert ground_sampling_distance(SOUTH, xy) == pytest.approx(math.sqrt(pixel_footprint(SOUTH, xy)), rel=1e-3)


def test_a_far_spot_is_resolved_worse_than_a_near_one() -> None:
    near, far = ground_sampling_distance(SOUTH, (0.0, 3.0)), ground_sampling_distance(SOUTH, (0.0, 9.0))
    assert far > 3 * near
    # The camera on the other wall sees the same two spots the other way round.
    assert ground_sampling_distance(NORTH, (0.0, 3.0)) > 3 * ground_sampling_distance(NORTH, (0.0, 9.0))


def test_gsd_of_a_top_down_camera_is_its_scale() -> None:
    # A camera looking straight down, 100 pixels per metre: the four image corners of a 640 x 480
    # image map to a 6.4 x 4.8 m rectangle (cv2.getPerspectiveTransform).
    image = np.array([[0, 0], [640, 0], [640, 480], [0, 480]], dtype=np.float32)
    floor = np.array([[1, 1], [7.4, 1], [7.4, 5.8], [1, 5.8]], dtype=np.float32)
    h = Homography.from_values(cv2.getPerspectiveTransform(image, floor))
    for xy in [(1.5, 1.5), (4.0, 3.0), (7.0, 5.5)]:
        assert ground_sampling_distance(h, xy) == pytest.approx(0.01, rel=1e-6)


def test_gsd_on_the_horizon_is_infinite_and_bad_points_are_refused() -> None:
    # The south camera looks along +y: the floor point that would be at its horizon is infinitely far.
    horizon_px = SOUTH.inverse().apply([(0.0, 1e9)])[0]
    assert ground_sampling_distance(SOUTH, tuple(SOUTH.apply([horizon_px])[0])) > 1.0
    with pytest.raises(InvalidArgument, match=r"^floor_xy: \(nan, 1.0\) must be finite"):
        ground_sampling_distance(SOUTH, (math.nan, 1.0))
    with pytest.raises(InvalidArgument, match=r"^floor_xy: expected two numbers"):
        ground_sampling_distance(SOUTH, (1.0,))  # type: ignore[arg-type]


# --- merging -----------------------------------------------------------------------------------


def test_two_cameras_seeing_one_box_give_one_object_more_precise_than_either() -> None:
    truth = square(0.5, 6.0)
    a = seen("south", truth, shift_px=(1.0, -1.0), t=T0)
    b = seen("north", truth, shift_px=(-1.0, 1.5), t=T0 + 0.03)
    [obj] = fuse([report("south", a), report("north", b, t=T0 + 0.03)], CAMERAS.get)
    sigma_a = PIXEL_SIGMA * ground_sampling_distance(SOUTH, a.centroid_xy)
    sigma_b = PIXEL_SIGMA * ground_sampling_distance(NORTH, b.centroid_xy)
    assert obj.uncertainty_m < min(sigma_a, sigma_b)
    # (Within 2 %: the two views' floor areas differ a little, which widens the smaller one a little.)
    assert obj.uncertainty_m == pytest.approx(1 / math.sqrt(sigma_a**-2 + sigma_b**-2), rel=0.02)
    assert obj.camera_ids == ("north", "south")
    assert obj.track_id == 1
    assert obj.last_seen == T0 + 0.03
    assert obj.velocity_xy == (0.0, 0.0) and obj.course_deg is None
    assert obj.score == pytest.approx(0.9)
    # The union of the two views: it covers both, and its bounds and area are the outline's.
    assert obj.outline.covers(a.outline.buffer(-1e-9)) and obj.outline.covers(b.outline.buffer(-1e-9))
    assert obj.bounds == pytest.approx(obj.outline.bounds)
    assert obj.area_m2 == pytest.approx(obj.outline.area)
    error = math.dist(obj.centroid_xy, (0.5, 6.0))
    assert error < max(math.dist(a.centroid_xy, (0.5, 6.0)), math.dist(b.centroid_xy, (0.5, 6.0)))


def test_weighting_favours_the_camera_that_is_near() -> None:
    # At y = 3 the south camera is near (fine pixels), the north one 9 m away (coarse pixels).
    # Both are off by the same two pixels: the fused centroid lies near the south camera's.
    truth = square(0.0, 3.0)
    a = seen("south", truth, shift_px=(2.0, 0.0))
    b = seen("north", truth, shift_px=(2.0, 0.0))
    [obj] = fuse([report("south", a), report("north", b)], CAMERAS.get)
    sa = ground_sampling_distance(SOUTH, a.centroid_xy)
    sb = ground_sampling_distance(NORTH, b.centroid_xy)
    assert sb > 2.5 * sa
    wa, wb = sa**-2, sb**-2
    expected = (np.array(a.centroid_xy) * wa + np.array(b.centroid_xy) * wb) / (wa + wb)
    assert obj.centroid_xy == pytest.approx(tuple(expected), abs=1e-9)
    assert math.dist(obj.centroid_xy, a.centroid_xy) < 0.2 * math.dist(obj.centroid_xy, b.centroid_xy)


def test_a_camera_that_sees_part_of_an_object_counts_for_little() -> None:
    # The north camera sees only the southern fifth of the box (the rest beyond its image's edge or
    # hidden): its centroid is 16 cm off. The south camera sees all of it. The fused centroid
    # stays with the full view instead of being pulled halfway by the sliver.
    truth = square(0.0, 6.0, 0.4)
    full = seen("south", truth)
    sliver = seen("north", floor_box(-0.2, 5.8, 0.2, 5.88))
    [obj] = fuse([report("south", full), report("north", sliver)], CAMERAS.get)
    assert obj.camera_ids == ("north", "south")
    assert math.dist(sliver.centroid_xy, (0.0, 6.0)) > 0.15
    assert math.dist(obj.centroid_xy, (0.0, 6.0)) < 0.01


def test_two_distinct_boxes_close_together_stay_two() -> None:
    # 0.4 m boxes 0.1 m apart, seen by both cameras with a pixel of error each.
    left, right = square(-0.25, 6.0), square(0.25, 6.0)
    south = report("south", seen("south", left, shift_px=(1, 0)), seen("south", right, shift_px=(-1, 1)))
    north = report("north", seen("north", left, shift_px=(0, 1)), seen("north", right, shift_px=(1, -1)))
    objects = fuse([south, north], CAMERAS.get)
    assert len(objects) == 2
    assert [o.camera_ids for o in objects] == [("north", "south")] * 2
    # Numbered by x: the left box is 1.
    assert [o.track_id for o in objects] == [1, 2]
    assert objects[0].centroid_xy[0] < 0 < objects[1].centroid_xy[0]
    for o, x in zip(objects, (-0.25, 0.25), strict=True):
        assert math.dist(o.centroid_xy, (x, 6.0)) < 0.05


def test_two_detections_of_one_camera_never_merge() -> None:
    # One camera sees two overlapping blobs (two objects, or a split one): they stay two, even
    # though a second camera's single detection overlaps both.
    a1, a2 = seen("south", square(0.0, 6.0)), seen("south", square(0.15, 6.0))
    assert a1.outline.intersects(a2.outline)
    b = seen("north", square(0.05, 6.0))
    objects = fuse([report("south", a1, a2), report("north", b)], CAMERAS.get)
    assert len(objects) == 2
    assert sorted(o.camera_ids for o in objects) == [("north", "south"), ("south",)]
    alone = fuse([report("south", a1, a2)], CAMERAS.get)
    assert len(alone) == 2


def test_markers_merge_by_id_and_different_ids_never_merge() -> None:
    marker = square(1.0, 5.0, 0.2)
    # Same id from two cameras, 0.5 m apart (a camera badly calibrated): the id says it is one marker.
    seven_s = seen("south", marker, filter_def="aruco_4x4_50_7", marker_id=7)
    seven_n = seen("north", square(1.5, 5.0, 0.2), filter_def="aruco_4x4_50_7", marker_id=7)
    # A different id exactly where 7 is: never the same object.
    eight = seen("north", marker, filter_def="aruco_4x4_50", marker_id=8)
    objects = fuse([report("south", seven_s), report("north", seven_n, eight)], CAMERAS.get)
    by_id = {o.marker_id or 0: o for o in objects}
    assert sorted(by_id) == [7, 8] and len(objects) == 2
    assert by_id[7].camera_ids == ("north", "south")
    assert by_id[8].camera_ids == ("north",)


def test_labels_never_cross() -> None:
    spot = square(0.0, 6.0, 0.5)
    person = seen("south", spot, filter_def="people", label="person")
    chair = seen("north", spot, filter_def="model_x", label="chair")
    objects = fuse([report("south", person), report("north", chair)], CAMERAS.get)
    assert sorted(o.label for o in objects) == ["chair", "person"]
    assert all(len(o.camera_ids) == 1 for o in objects)


def test_a_camera_that_failed_contributes_nothing() -> None:
    truth = square(0.0, 6.0)
    failed = DetectionReport(
        "r1", "north", T0, 0, True, (seen("north", truth),), error="gone", error_code="UNAVAILABLE"
    )
    [obj] = fuse([report("south", seen("south", truth)), failed], CAMERAS.get)
    assert obj.camera_ids == ("south",)
    assert fuse([failed], CAMERAS.get) == []
    assert fuse([], CAMERAS.get) == []


def test_of_a_cameras_several_reports_only_the_newest_counts() -> None:
    # A continuous request: the south camera reported twice in the period (the box moved 5 cm).
    older = DetectionReport("r1", "south", T0, 4, False, (seen("south", square(0.0, 6.0), t=T0),))
    newer = DetectionReport("r1", "south", T0 + 0.05, 5, False, (seen("south", square(0.05, 6.0), t=T0 + 0.05),))
    north = report("north", seen("north", square(0.05, 6.0), t=T0 + 0.04), t=T0 + 0.04)
    failed_later = DetectionReport("r1", "south", T0 + 0.09, 6, False, error="no frame", error_code="UNAVAILABLE")
    for reports in ([older, newer, north], [newer, north, older, failed_later]):
        [obj] = fuse(reports, CAMERAS.get)
        assert obj.camera_ids == ("north", "south")
        assert obj.last_seen == T0 + 0.05
        assert math.dist(obj.centroid_xy, (0.05, 6.0)) < 0.01


def test_without_outlines_bounds_and_centroids_fuse() -> None:
    # A request with omit_outlines: detections carry bounds and centroids, no outline, no areas.
    truth = square(0.0, 6.0)

    def bare(d: Detection) -> Detection:
        return Detection(
            Polygon(),
            d.bounds,
            d.centroid_xy,
            d.ground_contact_xy,
            d.pixel_box,
            0.0,
            0.0,
            0.0,
            YELLOW,
            d.camera_id,
            d.capture_time,
        )

    a, b = bare(seen("south", truth, shift_px=(1, 0))), bare(seen("north", truth, shift_px=(0, 1)))
    [obj] = fuse([report("south", a), report("north", b)], CAMERAS.get)
    assert obj.outline.is_empty
    assert obj.bounds == pytest.approx(
        (
            min(a.bounds[0], b.bounds[0]),
            min(a.bounds[1], b.bounds[1]),
            max(a.bounds[2], b.bounds[2]),
            max(a.bounds[3], b.bounds[3]),
        )
    )
    assert math.dist(obj.centroid_xy, (0.0, 6.0)) < 0.03


def test_a_camera_without_a_known_homography_uses_its_detections_own_scale() -> None:
    truth = square(0.0, 6.0)
    a, b = seen("south", truth), seen("north", truth)
    known = fuse([report("south", a), report("north", b)], CAMERAS.get)
    unknown = fuse([report("south", a), report("north", b)], lambda _camera_id: None)
    assert len(known) == len(unknown) == 1
    # The blob's own floor area per pixel is the GSD averaged over it: close to the point value.
    assert unknown[0].uncertainty_m == pytest.approx(known[0].uncertainty_m, rel=0.3)


def test_detections_with_non_finite_coordinates_are_skipped() -> None:
    good = seen("south", square(0.0, 6.0))
    bad = Detection(
        Polygon(), (math.nan, 0, 1, 1), (math.nan, 1.0), (0.0, 0.0), good.pixel_box, 0.0, 0.0, 0.5, YELLOW, "north", T0
    )
    [obj] = fuse([report("south", good), report("north", bad)], CAMERAS.get)
    assert obj.camera_ids == ("south",)


@pytest.mark.parametrize("sigma", [0.0, -1.0, math.nan, math.inf])
def test_pixel_sigma_must_be_positive(sigma: float) -> None:
    with pytest.raises(InvalidArgument, match=r"^pixel_sigma: .* must be a positive finite number of pixels"):
        fuse([], CAMERAS.get, pixel_sigma=sigma)


def test_track_ids_follow_x_then_y_whatever_the_report_order() -> None:
    spots = [(1.0, 4.0), (-1.0, 7.0), (-1.0, 5.0), (0.5, 8.0)]
    dets = [seen("south", square(x, y, 0.3)) for x, y in spots]
    forward = fuse([report("south", *dets)], CAMERAS.get)
    backward = fuse([report("south", *reversed(dets))], CAMERAS.get)
    order = [o.centroid_xy for o in forward]
    assert order == sorted(order)
    assert [o.track_id for o in forward] == [1, 2, 3, 4]
    assert [(o.track_id, o.centroid_xy) for o in forward] == [(o.track_id, o.centroid_xy) for o in backward]


# --- real pixels -------------------------------------------------------------------------------

#: Flat objects lying in both cameras' views: two yellow boxes, one close to the other, a yellow
#: disc, and a green box where a yellow one also lies near (type must keep them apart).
SCENE: list[tuple[str, Polygon]] = [
    (YELLOW, square(-1.0, 4.5, 0.5)),
    (YELLOW, square(-0.3, 4.5, 0.5)),
    (YELLOW, Point(1.2, 6.5).buffer(0.3, quad_segs=32)),
    (YELLOW, square(0.0, 8.0, 0.45)),
    (GREEN, square(1.2, 8.0, 0.45)),
]


def frame_of(camera_id: str, seed: int) -> NDArray[np.uint8]:
    patches = [FloorPatch(shape, HsvRange.parse(f).centre_bgr()) for f, shape in SCENE]
    return render_view(CAMERAS[camera_id], IMAGE_SIZE, patches, noise_sigma=6.0, rng=np.random.default_rng(seed))


def detect(camera_id: str, filter_def: str, seed: int) -> DetectionReport:
    detector = HsvDetector(view(camera_id))
    found = detector.detect(FrameAnalysis(DetFrame(frame_of(camera_id, seed), T0, seed)), filter_def)
    return DetectionReport("r1", camera_id, T0, 0, True, tuple(found))


@pytest.mark.parametrize("filter_def", [YELLOW, GREEN])
def test_real_pixels_two_cameras_one_object_per_physical_object(filter_def: str) -> None:
    truths = [shape for f, shape in SCENE if f == filter_def]
    reports = [detect("south", filter_def, 1), detect("north", filter_def, 2)]
    # Each camera sees every object once (the scene lies in both views).
    for r in reports:
        assert len(r.detections) == len(truths), (r.camera_id, [d.centroid_xy for d in r.detections])
    objects = fuse(reports, CAMERAS.get)
    assert len(objects) == len(truths), [o.centroid_xy for o in objects]
    for truth in truths:
        c = (truth.centroid.x, truth.centroid.y)
        [obj] = [o for o in objects if o.outline.contains(Point(c))]
        assert obj.camera_ids == ("north", "south")
        singles = [min(r.detections, key=lambda d: math.dist(d.centroid_xy, c)) for r in reports]
        errors = [math.dist(d.centroid_xy, c) for d in singles]
        fused_error = math.dist(obj.centroid_xy, c)
        # Better than the worse camera, and within 3 sigma of the truth by its own uncertainty.
        assert fused_error <= max(errors)
        assert fused_error < 3 * obj.uncertainty_m + 0.01, (fused_error, obj.uncertainty_m)
        assert obj.uncertainty_m < 0.03


# --- the simulator's own rendering: texture, lighting, noise, printed markers ------------------

OVERLAP_SCENARIO = """
name: fusion-overlap
floor_plan: {bounds: [0, 0, 12, 6], walls: []}
colors:
  yellow: {filter_def: hsv_014110130035225200, bgr: [57, 143, 165]}
  blue:   {filter_def: hsv_100120080130255255, bgr: [167, 100, 42]}
cameras:
  - {id: cam-a, position: [3.0, -1.0, 4.0], yaw_deg: 60, pitch_deg: 45, hfov_deg: 75,
     resolution: [640, 480], fps: 20, max_range_m: 9}
  - {id: cam-b, position: [9.0, -1.0, 4.0], yaw_deg: 120, pitch_deg: 45, hfov_deg: 75,
     resolution: [640, 480], fps: 20, max_range_m: 9}
objects:
  - {kind: obstacle, color: yellow, polygon: [[3.7, 1.7], [4.3, 1.7], [4.3, 2.3], [3.7, 2.3]]}
  - {kind: obstacle, color: yellow, polygon: [[7.2, 4.2], [7.8, 4.2], [7.8, 4.8], [7.2, 4.8]]}
  # Two boxes 15 cm apart: two objects, not one.
  - {kind: obstacle, color: yellow, polygon: [[5.25, 3.25], [5.75, 3.25], [5.75, 3.75], [5.25, 3.75]]}
  - {kind: obstacle, color: yellow, polygon: [[5.9, 3.25], [6.4, 3.25], [6.4, 3.75], [5.9, 3.75]]}
  - {kind: marker, aruco: 3, center: [6.0, 1.5], size: 0.25, heading: 30}
  - {kind: marker, aruco: 5, center: [4.5, 4.5], size: 0.25}
robot: {start: [1.0, 1.0], goal: [11.0, 5.0], radius: 0.2, color: blue, speed_mps: 1.0}
mission: navigate
"""


def test_real_pixels_from_the_simulators_renderer_boxes_and_markers() -> None:
    """Two of the simulator's cameras (floor texture, lighting, sensor noise) see four boxes and two
    printed ArUco markers; the camera node's detectors (hsv, aruco) find them in each frame; fuse
    gives one object per box and per marker, each seen by both cameras, near the truth."""
    scenario = parse_scenario(OVERLAP_SCENARIO, "fusion-overlap")
    homographies = {cam.id: cam.homography for cam in scenario.cameras}
    boxes: dict[str, list[Detection]] = {}
    markers: dict[str, list[Detection]] = {}
    for seed, cam in enumerate(scenario.cameras):
        view = CameraView(cam.homography, cam.field_of_view, cam.resolution, camera_id=cam.id)
        image = CameraRenderer(scenario, cam, seed=seed).render(None, 0)
        analysis = FrameAnalysis(DetFrame(image, T0, 0))
        boxes[cam.id] = list(REGISTRY["hsv"](view, None).find(analysis, object_type(YELLOW)))
        markers[cam.id] = list(REGISTRY["aruco"](view, None).find(analysis, object_type("aruco_4x4_50")))
    truth_boxes = [o.shape for o in scenario.objects if o.kind == "obstacle"]
    truth_markers = {m.id: m.center for m in scenario.aruco_markers}
    for cam_id in homographies:
        assert len(boxes[cam_id]) == 4, (cam_id, [d.centroid_xy for d in boxes[cam_id]])
        assert sorted(d.marker_id or 0 for d in markers[cam_id]) == [3, 5]

    fused = fuse([report(c, *ds) for c, ds in boxes.items()], homographies.get)
    assert len(fused) == 4, [o.centroid_xy for o in fused]
    for shape in truth_boxes:
        c = (shape.centroid.x, shape.centroid.y)
        [obj] = [o for o in fused if o.outline.contains(Point(c))]
        assert obj.camera_ids == ("cam-a", "cam-b")
        singles = [
            math.dist(min(ds, key=lambda d: math.dist(d.centroid_xy, c)).centroid_xy, c) for ds in boxes.values()
        ]
        assert math.dist(obj.centroid_xy, c) <= max(singles)
        assert math.dist(obj.centroid_xy, c) < 0.03

    fused_markers = fuse([report(c, *ds) for c, ds in markers.items()], homographies.get)
    assert sorted(o.marker_id or 0 for o in fused_markers) == [3, 5]
    for o in fused_markers:
        assert o.camera_ids == ("cam-a", "cam-b")
        assert o.marker_id is not None
        assert math.dist(o.centroid_xy, truth_markers[o.marker_id]) < 0.03
    three = next(o for o in fused_markers if o.marker_id == 3)
    assert three.marker_heading_deg is not None and abs(three.marker_heading_deg - 30.0) < 3.0


# --- properties over random scenes ---------------------------------------------------------------

spots = st.lists(
    st.tuples(st.floats(-2.5, 2.5), st.floats(3.0, 9.0), st.floats(0.1, 0.6), st.sampled_from(["", "person"])),
    min_size=0,
    max_size=8,
)
shifts = st.tuples(st.floats(-2.0, 2.0), st.floats(-2.0, 2.0))


@settings(max_examples=60, deadline=None)
@given(scene=spots, seen_by=st.lists(st.sampled_from(["south", "north", "both"]), min_size=8, max_size=8), shift=shifts)
def test_every_detection_lands_in_exactly_one_object(
    scene: list[tuple[float, float, float, str]], seen_by: list[str], shift: tuple[float, float]
) -> None:
    """Whatever the scene (objects anywhere, overlapping or not, of two labels): each detection is
    in exactly one object, no object holds two of one camera's, labels never mix, ids are 1..N."""
    per_camera: dict[str, list[Detection]] = {"south": [], "north": []}
    for (x, y, side, label), who in zip(scene, seen_by, strict=False):
        for cam in ("south", "north") if who == "both" else (who,):
            per_camera[cam].append(seen(cam, square(x, y, side), shift_px=shift, label=label))
    objects = fuse([report(c, *ds) for c, ds in per_camera.items()], CAMERAS.get)
    assert sum(len(o.camera_ids) for o in objects) == sum(len(ds) for ds in per_camera.values())
    assert all(len(set(o.camera_ids)) == len(o.camera_ids) for o in objects)
    assert max(len(ds) for ds in per_camera.values()) <= len(objects) <= sum(len(ds) for ds in per_camera.values())
    assert [o.track_id for o in objects] == list(range(1, len(objects) + 1))
    for label in ("", "person"):
        assert sum(1 for o in objects for _ in o.camera_ids if o.label == label) == sum(
            1 for ds in per_camera.values() for d in ds if d.label == label
        )
    for o in objects:
        assert math.isfinite(o.uncertainty_m) and o.uncertainty_m > 0
        assert o.outline.is_valid and not o.outline.is_empty

"""Floor geometry: pinhole homographies, their validation, fields of view, and region validation."""

from __future__ import annotations

import math

import numpy as np
import pytest
from shapely.geometry import Point, Polygon

from drvs.core.errors import InvalidArgument
from drvs.core.geometry import (
    FieldOfView,
    Homography,
    box_region,
    homography_from_pose,
    polygon_coords,
    polygon_region,
)

SIZE = (640, 480)
HFOV = 60.0
#: Focal length in pixels of a 640-pixel-wide image with a 60° horizontal field of view.
F = 320.0 / math.tan(math.radians(30.0))


def reference_camera() -> Homography:
    """3 m up at the origin, looking along +y (yaw 90), 40° below horizontal."""
    return homography_from_pose((0.0, 0.0, 3.0), 90.0, 40.0, HFOV, SIZE)


def floor_y_of_row(v: float, pitch_deg: float, height: float = 3.0) -> float:
    """Floor distance (along the yaw direction) seen by image row v of a camera with zero roll."""
    angle = math.radians(pitch_deg) + math.atan((v - 240.0) / F)
    return height / math.tan(angle)


# --- homography_from_pose -------------------------------------------------------------------------


def test_image_centre_maps_to_optical_axis_floor_point() -> None:
    x, y = reference_camera().apply([[320.0, 240.0]])[0]
    assert abs(x - 0.0) < 1e-9
    assert abs(y - 3.0 / math.tan(math.radians(40.0))) < 1e-9


def test_pixels_map_to_their_pinhole_rays() -> None:
    h = reference_camera()
    # Centre row: the ray is forward + (u - cx)/f * right, and right is +x for yaw 90.
    along_axis = 3.0 / math.sin(math.radians(40.0))
    x, y = h.apply([[600.0, 240.0]])[0]
    assert abs(x - (600.0 - 320.0) / F * along_axis) < 1e-9
    assert abs(y - 3.0 / math.tan(math.radians(40.0))) < 1e-9
    # Centre column: pure pitch.
    for v in (0.0, 100.0, 479.5, 480.0):
        x, y = h.apply([[320.0, v]])[0]
        assert abs(x) < 1e-9
        assert abs(y - floor_y_of_row(v, 40.0)) < 1e-9


def test_yaw_and_position() -> None:
    # Yaw 0 looks along +x; the camera stands at (5, -2).
    h = homography_from_pose((5.0, -2.0, 3.0), 0.0, 40.0, HFOV, SIZE)
    x, y = h.apply([[320.0, 240.0]])[0]
    assert abs(x - (5.0 + 3.0 / math.tan(math.radians(40.0)))) < 1e-9
    assert abs(y - -2.0) < 1e-9
    # Right of the image is the camera's right: -y when looking along +x.
    _, y_right = h.apply([[600.0, 240.0]])[0]
    assert y_right < -2.0


def test_world_point_round_trips_through_the_inverse() -> None:
    h = reference_camera()
    world = np.array([[1.2, 4.7], [-1.5, 2.0], [0.0, 9.5], [1.5, 1.8], [0.0, 3.0 / math.tan(math.radians(40.0))]])
    pixels = h.inverse().apply(world)
    assert np.all((pixels >= 0) & (pixels <= [[640, 480]]))
    # The optical-axis floor point is the image centre.
    assert np.max(np.abs(pixels[-1] - [320.0, 240.0])) < 1e-9
    back = h.apply(pixels)
    assert np.max(np.abs(back - world)) < 1e-9


def test_homography_from_pose_rejects_impossible_cameras() -> None:
    with pytest.raises(InvalidArgument, match=r"position: camera height"):
        homography_from_pose((0.0, 0.0, 0.0), 90.0, 40.0, HFOV, SIZE)
    with pytest.raises(InvalidArgument, match=r"hfov_deg"):
        homography_from_pose((0.0, 0.0, 3.0), 90.0, 40.0, 180.0, SIZE)
    with pytest.raises(InvalidArgument, match=r"hfov_deg"):
        homography_from_pose((0.0, 0.0, 3.0), 90.0, 40.0, 0.0, SIZE)


# --- Homography.from_values -----------------------------------------------------------------------


def test_from_values_accepts_flat_or_3x3_and_normalises_scale() -> None:
    m = [[2.0, 0.0, 4.0], [0.0, -8.0, 1.0], [0.0, 0.5, 2.0]]
    a = Homography.from_values(m)
    b = Homography.from_values([v for row in m for v in row])
    assert np.array_equal(a.matrix, b.matrix)
    assert float(np.max(np.abs(a.matrix))) == 1.0
    assert np.allclose(a.matrix * 8.0, m)
    # Scale does not change the mapping.
    assert np.allclose(a.apply([[3.0, 5.0]]), Homography.from_values(np.asarray(m) * 123.0).apply([[3.0, 5.0]]))
    assert a.to_list() == [float(v) for v in a.matrix.reshape(-1)]


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ([1.0] * 8, r"homography: expected 9 numbers .*got 8"),
        ([1.0] * 10, r"homography: expected 9 numbers .*got 10"),
        (np.eye(4), r"homography: expected 9 numbers .*got 16"),
        ([], r"homography: expected 9 numbers .*got 0"),
        ("abcdefghi", r"homography: expected 9 numbers"),
        ([1, 0, 0, 0, 1, 0, 0, 0, math.nan], r"homography: contains NaN or infinite"),
        ([1, 0, 0, 0, 1, 0, 0, 0, math.inf], r"homography: contains NaN or infinite"),
        ([1, 0, 0, 0, -math.inf, 0, 0, 0, 1], r"homography: contains NaN or infinite"),
        ([0.0] * 9, r"homography: all zeros"),
        # A Python int beyond float64's range (as YAML or JSON can hold) is not a usable number.
        ([10**400, 0, 0, 0, 1, 0, 0, 0, 1], r"homography: "),
        ([[1, 0, 0], [0, 1, 0], [1, 0, 0]], r"homography: singular"),
        ([[1, 2, 3], [4, 5, 6], [7, 8, 9]], r"homography: singular"),
        ([1.0] * 9, r"homography: singular"),
        (np.diag([1.0, 1.0, 1e-16]), r"homography: singular"),
    ],
)
def test_from_values_rejects_bad_matrices(values: object, message: str) -> None:
    with pytest.raises(InvalidArgument, match=message):
        Homography.from_values(values)  # type: ignore[arg-type]


def test_from_values_names_the_field() -> None:
    with pytest.raises(InvalidArgument, match=r"^camera\.homography: all zeros"):
        Homography.from_values([0.0] * 9, "camera.homography")


# --- FieldOfView.compute ---------------------------------------------------------------------------


def test_field_of_view_of_reference_camera() -> None:
    h = reference_camera()
    fov = FieldOfView.compute(h, SIZE)
    floor = fov.floor
    assert floor.is_valid
    assert floor.area > 0
    # Everything in front of the camera (+y), nothing behind it.
    x0, y0, x1, y1 = floor.bounds
    assert y0 > 0
    # Contains the optical-axis floor point.
    assert floor.contains(Point(0.0, 3.0 / math.tan(math.radians(40.0))))
    # The whole image is below the horizon (it is 465 pixels above the top row), so the floor
    # polygon is the image rectangle mapped: its near edge is the image's bottom edge ...
    assert abs(y0 - floor_y_of_row(480.0, 40.0)) < 1e-9
    # ... which is where the bottom-centre pixel looks (within its half pixel).
    near = Point(h.apply([[320.0, 479.5]])[0])
    assert abs(near.y - floor_y_of_row(479.5, 40.0)) < 1e-9
    assert floor.distance(near) < 0.005
    assert floor.exterior.distance(near) < 0.005
    # ... and the far edge is the top row, symmetric about x = 0.
    assert abs(y1 - floor_y_of_row(0.0, 40.0)) < 1e-9
    assert abs(x0 + x1) < 1e-9
    # Not clipped by the default 15 m range: the floor polygon is exactly the mapped image corners.
    corners = h.apply([[0.0, 0.0], [640.0, 0.0], [640.0, 480.0], [0.0, 480.0]])
    assert abs(floor.area - Polygon(corners).area) < 1e-9
    # The image polygon is the whole image.
    assert abs(fov.image.area - 640.0 * 480.0) < 1e-6


def test_max_range_clips_the_field_of_view() -> None:
    h = reference_camera()
    full = FieldOfView.compute(h, SIZE)
    clipped = FieldOfView.compute(h, SIZE, max_range_m=3.0)
    near = Point(h.apply([[320.0, 479.5]])[0])
    assert clipped.floor.area < full.floor.area
    assert full.floor.covers(clipped.floor.buffer(-1e-9))
    for x, y in polygon_coords(clipped.floor):
        assert math.dist((x, y), (near.x, near.y)) <= 3.0 + 1e-9
    # The clip is a disc of that radius: its far point straight ahead is 3 m beyond the near point.
    assert abs(clipped.floor.bounds[3] - (near.y + 3.0)) < 1e-9
    # The image polygon shrinks with it and stays inside the image.
    assert clipped.image.area < full.image.area
    assert Polygon([(0, 0), (640, 0), (640, 480), (0, 480)]).buffer(1e-6).covers(clipped.image)


def test_camera_looking_slightly_up_still_sees_distant_floor() -> None:
    # Pitch -10 with a 60°x47° lens: the bottom row looks 13.4° below the horizon, so this camera
    # does see floor, starting 12.6 m away; it is clipped to 15 m from there.
    h = homography_from_pose((0.0, 0.0, 3.0), 90.0, -10.0, HFOV, SIZE)
    fov = FieldOfView.compute(h, SIZE)
    near = Point(h.apply([[320.0, 479.5]])[0])
    assert abs(near.y - floor_y_of_row(479.5, -10.0)) < 1e-9
    assert abs(fov.floor.bounds[1] - floor_y_of_row(480.0, -10.0)) < 1e-9
    for x, y in polygon_coords(fov.floor):
        assert math.dist((x, y), (near.x, near.y)) <= 15.0 + 1e-9
    # The horizon crosses the image, so only its lower part is floor.
    assert 0 < fov.image.area < 640 * 480
    assert fov.image.bounds[3] == pytest.approx(480.0)


def test_camera_pitched_above_the_horizon_sees_no_floor() -> None:
    # Pitch -30: even the bottom row looks 6.6° above the horizon.
    h = homography_from_pose((0.0, 0.0, 3.0), 90.0, -30.0, HFOV, SIZE)
    with pytest.raises(InvalidArgument, match=r"field_of_view: .*sees no floor"):
        FieldOfView.compute(h, SIZE)


def test_bottom_row_above_horizon_sees_no_floor() -> None:
    # w = 0.01 v - 10 < 0 for every row of a 480-row image: the horizon is at v = 1000, below it.
    h = Homography.from_values([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.01, -10.0]])
    with pytest.raises(InvalidArgument, match=r"field_of_view: .*sees no floor"):
        FieldOfView.compute(h, SIZE)


def test_mirrored_homography_sees_no_floor() -> None:
    # Flipping the image left-right reverses orientation: not a real camera's view of the floor.
    h = reference_camera()
    mirrored = Homography.from_values(h.matrix @ np.array([[-1.0, 0.0, 640.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]))
    with pytest.raises(InvalidArgument, match=r"sees no floor"):
        FieldOfView.compute(mirrored, SIZE)


@pytest.mark.parametrize(
    ("size", "max_range", "message"),
    [
        ((0, 480), 15.0, r"cam\.fov: image size 0x480"),
        ((640, -1), 15.0, r"cam\.fov: image size 640x-1"),
        ((640, 480), 0.0, r"cam\.fov: max_range_m 0"),
        ((640, 480), -5.0, r"cam\.fov: max_range_m -5"),
        ((640, 480), math.nan, r"cam\.fov: max_range_m nan"),
        ((640, 480), math.inf, r"cam\.fov: max_range_m inf"),
    ],
)
def test_field_of_view_rejects_bad_parameters(size: tuple[int, int], max_range: float, message: str) -> None:
    with pytest.raises(InvalidArgument, match=message):
        FieldOfView.compute(reference_camera(), size, max_range, name="cam.fov")


# --- regions ---------------------------------------------------------------------------------------


def test_box_region_is_the_box() -> None:
    r = box_region(-1.0, 2.0, 3.0, 5.0)
    assert r.bounds == (-1.0, 2.0, 3.0, 5.0)
    assert r.area == 12.0


@pytest.mark.parametrize(
    ("args", "message"),
    [
        ((1.0, 0.0, 1.0, 1.0), r"region\.box: x_lower 1 must be less than x_upper 1"),
        ((2.0, 0.0, 1.0, 1.0), r"region\.box: x_lower 2 must be less than x_upper 1"),
        ((0.0, 1.0, 1.0, 1.0), r"region\.box: y_lower 1 must be less than y_upper 1"),
        ((0.0, 3.0, 1.0, -1.0), r"region\.box: y_lower 3 must be less than y_upper -1"),
        ((math.nan, 0.0, 1.0, 1.0), r"region\.box\.x_lower: nan is not finite"),
        ((0.0, math.nan, 1.0, 1.0), r"region\.box\.y_lower: nan is not finite"),
        ((0.0, 0.0, math.inf, 1.0), r"region\.box\.x_upper: inf is not finite"),
        ((0.0, 0.0, 1.0, -math.inf), r"region\.box\.y_upper: -inf is not finite"),
        ((0.0, 0.0, 2e6, 1.0), r"region\.box\.x_upper: 2000000.0 is beyond"),
        ((-1.5e6, 0.0, 1.0, 1.0), r"region\.box\.x_lower: -1500000.0 is beyond"),
        ((0.0, 0.0, 1.0, 1e6 + 1), r"region\.box\.y_upper: .* is beyond"),
        (("a", 0.0, 1.0, 1.0), r"region\.box\.x_lower: 'a' is not a number"),
    ],
)
def test_box_region_rejects(args: tuple[float, float, float, float], message: str) -> None:
    with pytest.raises(InvalidArgument, match=message):
        box_region(*args)


def test_box_region_accepts_the_coordinate_limit() -> None:
    assert box_region(-1e6, -1e6, 1e6, 1e6).area == 4e12


def test_box_region_uses_the_given_name() -> None:
    with pytest.raises(InvalidArgument, match=r"^roi\.box: x_lower"):
        box_region(1.0, 0.0, 0.0, 1.0, name="roi")


def test_polygon_region_accepts_closed_or_open_rings() -> None:
    open_ring = polygon_region([(0.0, 0.0), (2.0, 0.0), (2.0, 1.0), (0.0, 1.0)])
    closed_ring = polygon_region([(0.0, 0.0), (2.0, 0.0), (2.0, 1.0), (0.0, 1.0), (0.0, 0.0)])
    assert open_ring.equals(closed_ring)
    assert open_ring.area == 2.0
    assert polygon_coords(closed_ring) == [(0.0, 0.0), (2.0, 0.0), (2.0, 1.0), (0.0, 1.0)]


@pytest.mark.parametrize(
    ("points", "message"),
    [
        ([(0, 0), (2, 2), (0, 2), (2, 0)], r"region\.polygon: not a simple polygon \(Self-intersection"),
        ([(0, 0), (1, 0)], r"region\.polygon: needs at least 3 distinct points, got 2"),
        ([(0, 0), (1, 0), (0, 0)], r"region\.polygon: needs at least 3 distinct points, got 2"),
        ([], r"region\.polygon: needs at least 3 distinct points, got 0"),
        ([(0, 0), (1, 1), (2, 2)], r"region\.polygon: "),
        ([(0, 0), (1, 1), (2, 2), (3, 3)], r"region\.polygon: "),
        ([(0, 0), (1e-6, 0), (0, 1e-6)], r"region\.polygon: has zero area"),
        ([(0, 0), (1, 0), (math.nan, 1)], r"region\.polygon\.points\[2\]\.x: nan is not finite"),
        ([(0, 0), (1, math.inf), (0, 1)], r"region\.polygon\.points\[1\]\.y: inf is not finite"),
        ([(0, 0), (1, 0), (0, 5e6)], r"region\.polygon\.points\[2\]\.y: 5000000.0 is beyond"),
        ([(0, 0, 0), (1, 0), (0, 1)], r"region\.polygon\.points\[0\]: expected \[x, y\], got 3 values"),
        ([(0, 0), (1,), (0, 1)], r"region\.polygon\.points\[1\]: expected \[x, y\], got 1 values"),
    ],
)
def test_polygon_region_rejects(points: list[tuple[float, ...]], message: str) -> None:
    with pytest.raises(InvalidArgument, match=message):
        polygon_region(points)


def test_cameras_far_from_the_origin_are_valid() -> None:
    # A floor plan whose origin is a kilometre (or a hundred) away is still a floor plan.
    near = FieldOfView.compute(homography_from_pose((0.0, 0.0, 3.0), 90.0, 40.0, 60.0, (640, 480)), (640, 480), 6.0)
    for x in (990.0, 1.0e4, 1.0e5):
        far = FieldOfView.compute(homography_from_pose((x, x, 3.0), 90.0, 40.0, 60.0, (640, 480)), (640, 480), 6.0)
        assert far.floor.area == pytest.approx(near.floor.area, rel=1e-6)
        assert far.floor.bounds[0] == pytest.approx(near.floor.bounds[0] + x, abs=1e-6)


def test_field_of_view_beyond_the_coordinate_limit_is_refused() -> None:
    # Invertible, but it maps the image about 1e13 m away.
    with pytest.raises(InvalidArgument, match=r"field_of_view: the field of view lies beyond"):
        FieldOfView.compute(Homography.from_values(np.diag([1.0, -1.0, 1e-13])), (640, 480), 1e4)

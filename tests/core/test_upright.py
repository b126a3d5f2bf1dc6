"""drvs.core.upright: the camera behind a floor homography, and how tall people standing on it look."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drvs.core.errors import InvalidArgument
from drvs.core.geometry import Homography, homography_from_pose
from drvs.core.upright import UprightGeometry


@pytest.mark.parametrize(
    ("position", "yaw", "pitch", "hfov", "size"),
    [
        ((0.0, 0.0, 5.6), 90.0, 26.0, 60.0, (768, 576)),
        ((3.0, -1.0, 2.5), 17.0, 40.0, 70.0, (640, 480)),
        ((10.0, 10.0, 3.0), 200.0, 60.0, 90.0, (1280, 720)),
        ((-4.0, 7.0, 1.2), 0.0, 5.0, 60.0, (640, 480)),
    ],
)
def test_the_pose_comes_back_out_of_the_homography(
    position: tuple[float, float, float], yaw: float, pitch: float, hfov: float, size: tuple[int, int]
) -> None:
    geometry = UprightGeometry.from_homography(homography_from_pose(position, yaw, pitch, hfov, size), size)
    assert geometry.camera_height_m == pytest.approx(position[2], rel=1e-6)
    assert geometry.focal_px == pytest.approx((size[0] / 2) / math.tan(math.radians(hfov) / 2), rel=1e-6)


def test_a_person_at_the_image_centre_has_the_height_the_pose_says() -> None:
    """A camera 5 m up looking 30 degrees down: the floor point at the image centre is 5/tan(30)
    = 8.66 m away (10 m along the axis); the head of a 1.8 m person there is 1.8 cos(30) = 1.56 m
    above the axis, 10 - 1.8 sin(30) = 9.1 m in front: f * 1.56 / 9.1 pixels above the centre."""
    size = (800, 600)
    geometry = UprightGeometry.from_homography(homography_from_pose((0, 0, 5.0), 90.0, 30.0, 90.0, size), size)
    f = 400.0
    expected = f * 1.8 * math.cos(math.radians(30)) / (10.0 - 1.8 * math.sin(math.radians(30)))
    assert geometry.height_px([[400.0, 300.0]], 1.8)[0] == pytest.approx(expected, rel=1e-6)
    # Nearer the camera (lower in the image) a person looks taller; above the horizon nobody stands.
    near, far, sky = geometry.height_px([[400.0, 550.0], [400.0, 150.0], [400.0, 5.0]], 1.8)
    assert near > expected > far > 0 and np.isnan(sky)


def test_a_homography_without_perspective_has_no_camera_in_it() -> None:
    with pytest.raises(InvalidArgument, match="no perspective"):
        UprightGeometry.from_homography(Homography.from_values([0.01, 0, 0, 0, 0.01, 0, 0, 0, 1]), (640, 480))

"""How tall an upright thing standing on the floor appears in a camera's image, from its floor homography.

A floor homography (image -> floor) of a pinhole camera is, inverted, `K [r1 r2 t]` up to scale:
the camera's intrinsics times the first two columns of its rotation and its translation. With
square pixels and the principal point at the image centre (what `homography_from_pose` and a
plain `drvs-camera calibrate` assume), the one unknown of K, the focal length, follows from r1
and r2 being orthogonal and of equal length (Zhang's calibration from one view of a plane, with
two of its constraints), and with it the whole camera: rotation, position and so the height it
hangs at. A camera whose real principal point is off centre gets an approximate pose, good enough
to pick the scales a detector searches, not a measurement.

`UprightGeometry.from_homography` refuses a homography it cannot read as a camera above the
floor looking at it (one that maps straight down with no perspective, or a degenerate one), with
InvalidArgument saying why: a caller then searches without geometry.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from drvs.core.errors import InvalidArgument
from drvs.core.geometry import Homography

#: Constraints weaker than this (relative) cannot fix the focal length: the camera looks straight
#: down, or the homography is affine.
_MIN_CONSTRAINT = 1e-9


@dataclass(frozen=True)
class UprightGeometry:
    """The pinhole camera behind a floor homography: its 3x4 projection (floor metres with z up ->
    pixels), focal length in pixels and height above the floor in metres."""

    projection: NDArray[np.float64]
    floor: Homography
    focal_px: float
    camera_height_m: float

    @classmethod
    def from_homography(cls, homography: Homography, image_size: tuple[int, int]) -> UprightGeometry:
        width, height = image_size
        shift = np.array([[1.0, 0.0, -width / 2.0], [0.0, 1.0, -height / 2.0], [0.0, 0.0, 1.0]])
        g = shift @ np.linalg.inv(homography.matrix)  # floor -> image, principal point at the origin
        # With w = 1/f^2: orthogonality (a0 w + b0 = 0) and equal norms (a1 w + b1 = 0) of K^-1 g's
        # first two columns; least squares over both (either alone vanishes for some poses).
        a = np.array([g[0, 0] * g[0, 1] + g[1, 0] * g[1, 1], g[0, 0] ** 2 + g[1, 0] ** 2 - g[0, 1] ** 2 - g[1, 1] ** 2])
        b = -np.array([g[2, 0] * g[2, 1], g[2, 0] ** 2 - g[2, 1] ** 2])
        scale = float(np.abs(g[:2, :2]).max() ** 2)
        if float(a @ a) <= (_MIN_CONSTRAINT * scale) ** 2 or float(np.abs(g[2, :2]).max()) < _MIN_CONSTRAINT:
            raise InvalidArgument(
                "homography: no perspective (a camera looking straight down?): no camera height in it"
            )
        w = float(a @ b) / float(a @ a)
        if not (w > 0 and math.isfinite(w)):
            raise InvalidArgument("homography: not a pinhole camera with square pixels and a centred principal point")
        focal = 1.0 / math.sqrt(w)
        m = np.diag([1.0 / focal, 1.0 / focal, 1.0]) @ g
        lam = 1.0 / float(np.linalg.norm(m[:, 0]))
        r1, r2, t = m[:, 0] * lam, m[:, 1] * lam, m[:, 2] * lam
        # The sign: the floor at the bottom of the image is in front of the camera (positive depth).
        bottom = homography.apply([[width / 2.0, height - 1.0]])[0]
        if r1[2] * bottom[0] + r2[2] * bottom[1] + t[2] < 0:
            r1, r2, t = -r1, -r2, -t
        rotation = np.column_stack([r1, r2, np.cross(r1, r2)])
        centre = -rotation.T @ t
        if not centre[2] > 0:
            # The rotation's third column points up from the floor plane; a camera below it is the mirror image.
            rotation[:, 2] *= -1
            centre = -rotation.T @ t
        if not (centre[2] > 0 and math.isfinite(float(centre[2]))):
            raise InvalidArgument("homography: the camera it implies is not above the floor")
        k = np.array([[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0.0, 0.0, 1.0]])
        projection = k @ np.column_stack([rotation, t])
        return cls(np.asarray(projection, dtype=np.float64), homography, focal, float(centre[2]))

    def head_px(self, feet_px: ArrayLike, height_m: float) -> NDArray[np.float64]:
        """Where the top of something `height_m` tall standing at each pixel of `feet_px` (N x 2) appears
        (N x 2; NaN where it does not: at or beyond the horizon, or behind the camera)."""
        feet = np.asarray(feet_px, dtype=np.float64).reshape(-1, 2)
        floor = self.floor.apply(feet)
        points = np.column_stack([floor, np.full(len(feet), float(height_m)), np.ones(len(feet))])
        image = points @ self.projection.T
        with np.errstate(divide="ignore", invalid="ignore"):
            out = image[:, :2] / image[:, 2:3]
        bad = ~np.all(np.isfinite(floor), axis=1) | ~(image[:, 2] > 0)
        out[bad] = np.nan
        return out

    def height_px(self, feet_px: ArrayLike, height_m: float) -> NDArray[np.float64]:
        """How many pixels tall (feet to top, along the image's rows) something `height_m` tall
        standing at each feet pixel (N x 2) appears; NaN where it cannot stand there."""
        feet = np.asarray(feet_px, dtype=np.float64).reshape(-1, 2)
        return feet[:, 1] - self.head_px(feet, height_m)[:, 1]

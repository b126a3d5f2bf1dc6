"""Fitting a camera's image -> floor homography from point correspondences. Pure logic.

A person picks at least four floor points in a snapshot and measures where they are on the floor
plan; the fit uses RANSAC so one mis-measured point does not spoil it, and reports the error of
every point in metres on the floor.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray

from drvs.core._files import read_yaml
from drvs.core.errors import InvalidArgument
from drvs.core.geometry import FieldOfView, Homography

#: RANSAC threshold: a point farther than this from where the fit puts it is an outlier.
RANSAC_THRESHOLD_M = 0.05
#: Points whose spread is thinner than this fraction of their extent are called collinear.
COLLINEAR_RATIO = 0.01


@dataclass(frozen=True)
class Correspondence:
    image: tuple[float, float]
    world: tuple[float, float]


@dataclass(frozen=True)
class Calibration:
    homography: Homography
    points: tuple[Correspondence, ...]
    errors_m: tuple[float, ...]  # per point: |H(image) - world|
    inliers: tuple[bool, ...]

    @property
    def rms_error_m(self) -> float:
        used = [e for e, ok in zip(self.errors_m, self.inliers, strict=True) if ok]
        return math.sqrt(sum(e * e for e in used) / len(used))

    @property
    def max_error_m(self) -> float:
        return max(e for e, ok in zip(self.errors_m, self.inliers, strict=True) if ok)


def load_points(path: str | Path) -> list[Correspondence]:
    """YAML or JSON: [{image: [u, v], world: [x, y]}, ...]."""
    p = Path(path)
    data = read_yaml(p, "points file")
    if not isinstance(data, list):
        raise InvalidArgument(f"points file {p}: expected a list of {{image: [u, v], world: [x, y]}}")
    points = []
    for i, item in enumerate(data):
        if not isinstance(item, dict) or set(item) != {"image", "world"}:
            raise InvalidArgument(f"points file {p}: [{i}] must have exactly the keys image and world")
        points.append(Correspondence(_pair(item["image"], f"[{i}].image", p), _pair(item["world"], f"[{i}].world", p)))
    return points


def _pair(value: Any, where: str, p: Path) -> tuple[float, float]:
    ok = isinstance(value, list) and len(value) == 2
    ok = ok and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value)
    if not ok:
        raise InvalidArgument(f"points file {p}: {where} must be two finite numbers")
    return float(value[0]), float(value[1])


def _check_spread(pts: NDArray[np.float64], what: str) -> None:
    centred = pts - pts.mean(axis=0)
    singular = np.linalg.svd(centred, compute_uv=False)
    if singular[0] == 0 or singular[1] / singular[0] < COLLINEAR_RATIO:
        raise InvalidArgument(
            f"points: the {what} points are (nearly) on one line; a homography needs points spread over the floor"
        )


def fit_homography(points: list[Correspondence], image_size: tuple[int, int]) -> Calibration:
    """RANSAC fit of the image -> floor homography; refuses degenerate or mirrored layouts."""
    if len(points) < 4:
        raise InvalidArgument(f"points: at least 4 correspondences are needed, got {len(points)}")
    image = np.array([c.image for c in points], dtype=np.float64)
    world = np.array([c.world for c in points], dtype=np.float64)
    width, height = image_size
    outside = [i for i, (u, v) in enumerate(image) if not (0 <= u <= width and 0 <= v <= height)]
    if outside:
        raise InvalidArgument(
            f"points: [{outside[0]}].image {image[outside[0]].tolist()} is outside the {width}x{height} image"
        )
    for what, pts in (("image", image), ("world", world)):
        if len({tuple(p) for p in pts.tolist()}) < len(pts):
            raise InvalidArgument(f"points: two {what} points are the same")
        _check_spread(pts, what)
    matrix, mask = cv2.findHomography(image, world, cv2.RANSAC, RANSAC_THRESHOLD_M)
    if matrix is None or mask is None:
        raise InvalidArgument("points: no homography fits these correspondences (degenerate layout)")
    inliers = mask.ravel().astype(bool)
    if inliers.sum() < 4:
        raise InvalidArgument(f"points: only {int(inliers.sum())} points agree on one homography; at least 4 must")
    homography = Homography.from_values(matrix, "fitted homography")
    # A real camera maps the floor with reversed orientation (see FieldOfView.compute); a fit that
    # does not is the mirror image of the floor: an axis was flipped when the points were measured.
    scale = homography.projective_scale(image[inliers]) * np.linalg.det(homography.matrix)
    if np.any(scale >= 0):
        raise InvalidArgument(
            "points: the layout is mirrored (the world points are a mirror image of the image points); "
            "check the direction of the x or y axis you measured"
        )
    FieldOfView.compute(homography, image_size)  # the fit must give a usable field of view
    errors = np.linalg.norm(homography.apply(image) - world, axis=1)
    return Calibration(
        homography=homography,
        points=tuple(points),
        errors_m=tuple(float(e) for e in errors),
        inliers=tuple(bool(b) for b in inliers),
    )


def save_calibration(path: str | Path, calibration: Calibration, image_size: tuple[int, int]) -> None:
    """The file drvs-camera --homography reads, with the fit's errors for the record."""
    rows = [[float(v) for v in row] for row in calibration.homography.matrix]
    data = {
        "homography": rows,
        "image_size": list(image_size),
        "rms_error_m": round(calibration.rms_error_m, 5),
        "points": [
            {"image": list(c.image), "world": list(c.world), "error_m": round(e, 5), "inlier": ok}
            for c, e, ok in zip(calibration.points, calibration.errors_m, calibration.inliers, strict=True)
        ],
    }
    Path(path).write_text(yaml.safe_dump(data, sort_keys=False))

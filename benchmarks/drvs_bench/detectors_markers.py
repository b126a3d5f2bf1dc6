"""Printed ArUco markers lying on the benchmark's floor: their poses on a grid a camera sees, and
drawn into its frames through its homography (drvs-bench detectors' aruco scene)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np
from numpy.typing import NDArray
from shapely.geometry import Polygon, box

from drvs.core.geometry import FieldOfView, Homography
from drvs.sim.scenario import CameraDef, Scenario


@dataclass(frozen=True)
class MarkerPose:
    """An ArUco marker lying face up on the floor: its centre, side (m) and heading as the aruco
    detector reports it: degrees counter-clockwise from +x to the marker's x axis (its printed top
    edge read left to right)."""

    marker_id: int
    x: float
    y: float
    heading_deg: float
    side_m: float

    def corners(self) -> NDArray[np.float64]:
        """Floor corners of the black square: top-left, top-right, bottom-right, bottom-left."""
        t = math.radians(self.heading_deg)
        right = np.array([math.cos(t), math.sin(t)])
        up = np.array([-math.sin(t), math.cos(t)])  # seen from above, counter-clockwise of the top edge
        c = np.array([self.x, self.y])
        h = self.side_m / 2
        return np.array([c + h * (up - right), c + h * (up + right), c - h * (up - right), c - h * (up + right)])


def draw_markers(
    image: NDArray[np.uint8],
    homography: Homography,
    markers: Sequence[MarkerPose],
    dictionary: str = "DICT_4X4_50",
    rng: np.random.Generator | None = None,
) -> NDArray[np.uint8]:
    """The frame with printed markers (black on white paper, a one-module white margin) warped onto
    the floor through the camera's homography, then sensor noise over the paper."""
    out = image.copy()
    height, width = out.shape[:2]
    to_image = homography.inverse()
    aruco = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    modules = aruco.markerSize + 2
    px = 20 * modules
    paper = np.zeros((height, width), dtype=np.uint8)
    for m in markers:
        marker = cv2.aruco.generateImageMarker(aruco, m.marker_id, px)
        margin = px // modules
        printed = cv2.copyMakeBorder(marker, margin, margin, margin, margin, cv2.BORDER_CONSTANT, value=255)
        # Paper is not 255 and ink is not 0 under office light.
        printed = (30 + printed.astype(np.float32) * (185 / 255)).astype(np.uint8)
        outer = replace(m, side_m=m.side_m * (modules + 2) / modules).corners()
        dst = to_image.apply(outer).astype(np.float32)
        size = printed.shape[0]
        src = np.array([[0, 0], [size, 0], [size, size], [0, size]], dtype=np.float32)
        warp = cv2.getPerspectiveTransform(src, dst)
        layer = cv2.warpPerspective(printed, warp, (width, height), flags=cv2.INTER_AREA)
        mask = cv2.warpPerspective(np.full_like(printed, 255), warp, (width, height), flags=cv2.INTER_NEAREST)
        paper[mask > 0] = 255
        out[mask > 0] = layer[mask > 0][:, None]
    gen = rng if rng is not None else np.random.default_rng(0)
    noise = gen.normal(0.0, 3.0, out.shape).astype(np.float32)
    noisy = np.clip(out.astype(np.float32) + noise, 0, 255).astype(np.uint8)
    out[paper > 0] = noisy[paper > 0]
    return out


def marker_poses(
    camera: CameraDef, scenario: Scenario, side_m: float, spacing_m: float, first_id: int = 0, limit: int = 50
) -> list[MarkerPose]:
    """Markers on a grid over the floor a camera sees (clear of walls, objects and the image edge),
    each at another heading."""
    fov = FieldOfView.compute(camera.homography, camera.resolution, camera.max_range_m)
    to_image = camera.homography.inverse()
    taken = [w.buffer(0.1) for w in scenario.walls] + [o.shape.buffer(0.1) for o in scenario.objects]
    x0, y0, x1, y1 = fov.floor.bounds
    poses: list[MarkerPose] = []
    headings = (0.0, 37.0, 95.0, 160.0, 215.0, 290.0, 330.0, 120.0)
    margin = side_m * 0.8
    image_box = box(8, 8, camera.resolution[0] - 8, camera.resolution[1] - 8)
    for gy in np.arange(y0 + margin, y1, spacing_m):
        for gx in np.arange(x0 + margin, x1, spacing_m):
            pose = MarkerPose(first_id + len(poses), float(gx), float(gy), headings[len(poses) % len(headings)], side_m)
            outline = Polygon(pose.corners()).buffer(side_m / 3)
            if not fov.floor.contains(outline) or any(t.intersects(outline) for t in taken):
                continue
            if not image_box.contains(Polygon(to_image.apply(np.asarray(outline.exterior.coords)))):
                continue
            poses.append(pose)
            if len(poses) >= limit:
                return poses
    return poses

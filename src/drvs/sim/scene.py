"""Render what a camera sees of flat coloured patches on the floor, through its homography.

Homographies map lines to lines, so a floor polygon in front of the camera maps exactly to an
image polygon: the patches are projected vertex by vertex and filled with sub-pixel precision.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray
from shapely.geometry import Point, Polygon

from drvs.core.geometry import FieldOfView, Homography
from drvs.core.homography_file import save_homography
from drvs.core.imaging import fill_polygon


@dataclass(frozen=True)
class FloorPatch:
    """A flat object lying on the floor, painted one colour (BGR)."""

    shape: Polygon
    bgr: tuple[int, int, int]

    @classmethod
    def disc(cls, center: Sequence[float], radius: float, bgr: tuple[int, int, int]) -> FloorPatch:
        return cls(Point(center[0], center[1]).buffer(radius, quad_segs=32), bgr)

    @classmethod
    def rect(cls, x0: float, y0: float, x1: float, y1: float, bgr: tuple[int, int, int]) -> FloorPatch:
        return cls(Polygon([(x0, y0), (x1, y0), (x1, y1), (x0, y1)]), bgr)


def render_view(
    homography: Homography,
    image_size: tuple[int, int],
    patches: Iterable[FloorPatch],
    *,
    floor_bgr: tuple[int, int, int] = (105, 110, 115),
    wall_bgr: tuple[int, int, int] = (190, 185, 180),
    noise_sigma: float = 0.0,
    rng: np.random.Generator | None = None,
) -> NDArray[np.uint8]:
    """A BGR image of the floor and its patches as the camera with this image->floor homography sees it."""
    width, height = image_size
    fov = FieldOfView.compute(homography, image_size, max_range_m=1000.0)
    image = np.empty((height, width, 3), dtype=np.uint8)
    image[:] = wall_bgr
    fill_polygon(image, np.asarray(fov.image.exterior.coords)[:-1], floor_bgr)
    to_image = homography.inverse()
    for patch in patches:
        fill_floor_shape(image, patch.shape, to_image, fov.floor, patch.bgr)
    if noise_sigma > 0:
        gen = rng if rng is not None else np.random.default_rng(0)
        noisy = image.astype(np.float32) + gen.normal(0.0, noise_sigma, image.shape).astype(np.float32)
        image = np.clip(noisy, 0, 255).astype(np.uint8)
    return image


def fill_floor_shape(
    image: NDArray[np.uint8],
    shape: Polygon,
    to_image: Homography,
    visible_floor: Polygon,
    color: int | tuple[int, int, int],
) -> None:
    """Fill the part of a floor shape the camera sees: clipped to its view first, since points
    behind the camera have no image."""
    visible = shape.intersection(visible_floor)
    for piece in getattr(visible, "geoms", [visible]):
        if isinstance(piece, Polygon) and not piece.is_empty:
            fill_polygon(image, to_image.apply(np.asarray(piece.exterior.coords)[:-1]), color)


def write_video(path: str | Path, frames: Iterable[NDArray[np.uint8]], fps: float = 20.0) -> Path:
    """Write frames as an MJPG AVI file that OpenCV's VideoCapture reads back."""
    path = Path(path)
    frames = list(frames)
    height, width = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), fps, (width, height))
    if not writer.isOpened():
        raise OSError(f"cannot write video {path}")
    try:
        for frame in frames:
            writer.write(frame)
    finally:
        writer.release()
    return path


@dataclass(frozen=True)
class RecordedCamera:
    """A camera recorded to disk: a video file and a homography file that drvs-camera reads."""

    camera_id: str
    video: Path
    homography_file: Path
    homography: Homography


def record_camera(
    directory: str | Path,
    camera_id: str,
    homography: Homography,
    image_size: tuple[int, int],
    patches: Sequence[FloorPatch],
    *,
    frames: int = 20,
    fps: float = 20.0,
    noise_sigma: float = 2.0,
    seed: int = 0,
) -> RecordedCamera:
    """Render `frames` noisy views of a static floor and write them with the camera's homography."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    video = write_video(
        directory / f"{camera_id}.avi",
        (render_view(homography, image_size, patches, noise_sigma=noise_sigma, rng=rng) for _ in range(frames)),
        fps,
    )
    hfile = directory / f"{camera_id}.homography.yaml"
    save_homography(hfile, homography)
    return RecordedCamera(camera_id, video, hfile, homography)

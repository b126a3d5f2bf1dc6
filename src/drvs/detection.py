"""Colour-blob detection on real pixels, mapped onto the floor. Pure OpenCV, no gRPC.

The expensive part of a request is per frame, not per request: the colour conversion and each
filter's blobs are computed once per frame (FrameAnalysis) and shared by every request that
looks at that frame; a request only filters the blobs by its region.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import shapely
from numpy.typing import NDArray
from shapely.geometry import Polygon

from drvs.filters import HsvRange
from drvs.geometry import FieldOfView, Homography
from drvs.model import Detection, PixelBox

#: Blobs smaller than this many pixels are noise.
DEFAULT_MIN_AREA_PX = 30.0
#: Outlines are simplified (Douglas-Peucker) to within this many pixels before they are mapped:
#: a contour lists every boundary pixel, and reports would carry ten times the points for
#: no information the image resolution supports.
OUTLINE_TOLERANCE_PX = 1.0


@dataclass(frozen=True)
class Frame:
    """A captured image (BGR) with its capture time (Unix seconds, for reports) and a per-source
    sequence number. `captured_at` is the same instant on the monotonic clock: a frame's age is
    measured on it, so a wall clock that steps (NTP, an operator) never makes a stale frame look
    fresh or a fresh one stale."""

    image: NDArray[np.uint8]
    capture_time: float
    sequence: int
    captured_at: float = field(default_factory=time.monotonic)

    def age_s(self) -> float:
        """Seconds since capture, on the monotonic clock."""
        return time.monotonic() - self.captured_at

    @property
    def size(self) -> tuple[int, int]:
        return int(self.image.shape[1]), int(self.image.shape[0])


@dataclass
class FrameAnalysis:
    """Per-frame caches shared by all requests served from this frame."""

    frame: Frame
    _hsv: NDArray[np.uint8] | None = None
    _blobs: dict[str, tuple[Detection, ...]] = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock)
    #: Filters requests looked up on this frame, and on the frame before it (see drvs.camera.prefetch).
    wanted: set[str] = field(default_factory=set)
    inherited: frozenset[str] = frozenset()

    def cached_blobs(self, filter_def: str) -> tuple[Detection, ...] | None:
        """This filter's blobs if some request already found them (a complete entry or none: the
        entry is stored whole, once), without waiting for a thread that is finding them."""
        return self._blobs.get(filter_def)

    def hsv(self) -> NDArray[np.uint8]:
        if self._hsv is None:
            self._hsv = np.asarray(cv2.cvtColor(self.frame.image, cv2.COLOR_BGR2HSV), dtype=np.uint8)
        return self._hsv


class HsvDetector:
    """Threshold in HSV, clean up, keep connected blobs above a minimum size, map them to the floor."""

    kind = "hsv"

    def __init__(
        self,
        homography: Homography,
        field_of_view: FieldOfView,
        image_size: tuple[int, int],
        *,
        camera_id: str = "",
        min_area_px: float = DEFAULT_MIN_AREA_PX,
        kernel_px: int = 3,
    ) -> None:
        self.homography = homography
        self.field_of_view = field_of_view
        self.image_size = image_size
        self.camera_id = camera_id
        self.min_area_px = min_area_px
        self._kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (kernel_px, kernel_px))
        width, height = image_size
        # Only pixels that map into the field of view may become detections: above the horizon the
        # homography maps to points behind the camera or at infinity.
        self._fov_mask = np.zeros((height, width), dtype=np.uint8)
        ring = np.round(np.asarray(field_of_view.image.exterior.coords)[:-1]).astype(np.int32)
        cv2.fillPoly(self._fov_mask, [ring], 255)

    def detect(self, analysis: FrameAnalysis, filter_def: str, region: Polygon | None = None) -> list[Detection]:
        """Blobs of this filter in the frame whose floor outline meets `region` (all blobs when None)."""
        return self.select(self.blobs(analysis, filter_def), region)

    @staticmethod
    def select(blobs: tuple[Detection, ...], region: Polygon | None) -> list[Detection]:
        """The blobs whose floor outline meets `region` (all of them when None): microseconds."""
        if region is None:
            return list(blobs)
        shapely.prepare(region)
        return [d for d in blobs if region.intersects(d.outline)]

    def blobs(self, analysis: FrameAnalysis, filter_def: str) -> tuple[Detection, ...]:
        with analysis._lock:
            cached = analysis._blobs.get(filter_def)
            if cached is None:
                cached = self._find_blobs(analysis, filter_def)
                analysis._blobs[filter_def] = cached
            return cached

    def _find_blobs(self, analysis: FrameAnalysis, filter_def: str) -> tuple[Detection, ...]:
        frame = analysis.frame
        if frame.size != self.image_size:
            raise ValueError(f"frame size {frame.size} differs from the calibrated size {self.image_size}")
        hsv_range = HsvRange.parse(filter_def)
        raw = cv2.bitwise_and(hsv_range.mask(analysis.hsv()), self._fov_mask)
        mask = cv2.morphologyEx(raw, cv2.MORPH_OPEN, self._kernel)
        mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, self._kernel)
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        found: list[Detection] = []
        for contour in contours:
            area_px = float(cv2.contourArea(contour))
            if area_px < self.min_area_px:
                continue
            detection = self._to_floor(contour, area_px, raw, filter_def, frame.capture_time)
            if detection is not None:
                found.append(detection)
        found.sort(key=lambda d: d.area_px, reverse=True)
        return tuple(found)

    def _to_floor(
        self,
        contour: NDArray[Any],
        area_px: float,
        raw_mask: NDArray[Any],
        filter_def: str,
        capture_time: float,
    ) -> Detection | None:
        x, y, w, h = (int(v) for v in cv2.boundingRect(contour))
        # Score: how much of the blob's outline is really the colour (morphology may have filled holes).
        blob = np.zeros((h, w), dtype=np.uint8)
        cv2.drawContours(blob, [contour - np.array([x, y], dtype=np.int32)], -1, 255, thickness=cv2.FILLED)
        inside = int(np.count_nonzero(blob))
        hits = int(np.count_nonzero(cv2.bitwise_and(blob, raw_mask[y : y + h, x : x + w])))
        score = hits / inside if inside else 0.0

        simplified = cv2.approxPolyDP(contour, OUTLINE_TOLERANCE_PX, True)
        pts = (simplified if len(simplified) >= 3 else contour).reshape(-1, 2).astype(np.float64)
        if len(pts) < 3:
            return None
        floor_pts = self.homography.apply(pts)
        if not np.all(np.isfinite(floor_pts)):
            return None
        outline = Polygon(floor_pts)
        if not outline.is_valid:
            fixed = shapely.make_valid(outline)
            polys = [g for g in getattr(fixed, "geoms", [fixed]) if isinstance(g, Polygon) and not g.is_empty]
            if not polys:
                return None
            outline = max(polys, key=lambda g: g.area)
        if outline.is_empty or outline.area <= 0:
            return None
        contact = self.homography.apply([[x + (w - 1) / 2.0, y + h - 1.0]])[0]
        centroid = outline.centroid
        return Detection(
            outline=outline,
            bounds=tuple(float(v) for v in outline.bounds),  # type: ignore[arg-type]
            centroid_xy=(float(centroid.x), float(centroid.y)),
            ground_contact_xy=(float(contact[0]), float(contact[1])),
            pixel_box=PixelBox(x, y, w, h),
            area_m2=float(outline.area),
            area_px=area_px,
            score=float(score),
            filter_def=filter_def,
            camera_id=self.camera_id,
            capture_time=capture_time,
        )

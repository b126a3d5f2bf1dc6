"""The paper's colour model: blobs of the colour an ``hsv_HloSloVloHhiShiVhi`` filter_def names
(its grammar and `HsvRange` are the core's, drvs.core.object_types)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import cv2

from drvs.core.model import Detection
from drvs.core.object_types import HSV_PREFIX as HSV_PREFIX
from drvs.core.object_types import HsvRange as HsvRange
from drvs.core.object_types import parse_hsv

from .base import CameraView, Detector, FrameAnalysis, ObjectType, register, select


@register
class HsvDetector(Detector):
    """Threshold in HSV, clean up, keep connected blobs above a minimum size, map them to the floor."""

    prefix = "hsv"
    example = "hsv_014110130035225200"

    def __init__(self, view: CameraView, options: Mapping[str, Any] | None = None, *, kernel_px: int = 3) -> None:
        super().__init__(view, options)
        self._kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (kernel_px, kernel_px))

    @property
    def homography(self) -> Any:
        return self.view.homography

    @property
    def image_size(self) -> tuple[int, int]:
        return self.view.image_size

    @property
    def min_area_px(self) -> float:
        return self.view.min_area_px

    @classmethod
    def parse(cls, filter_def: str) -> ObjectType:
        return parse_hsv(filter_def)

    def detect(self, analysis: FrameAnalysis, filter_def: str, region: Any = None) -> list[Detection]:
        """Blobs of this filter in the frame whose floor outline meets `region` (all blobs when None)."""
        return select(self.blobs(analysis, filter_def), region)

    select = staticmethod(select)

    def blobs(self, analysis: FrameAnalysis, filter_def: str) -> tuple[Detection, ...]:
        """This filter's blobs in the frame, found once per frame and filter."""
        object_type = self.parse(filter_def)
        return analysis.found(filter_def, lambda: self.find(analysis, object_type))

    def find(self, analysis: FrameAnalysis, object_type: ObjectType) -> tuple[Detection, ...]:
        frame = analysis.frame
        self.view.check_frame(frame)
        hsv_range: HsvRange = object_type.params
        raw = cv2.bitwise_and(hsv_range.mask(analysis.hsv()), self.view.fov_mask)
        mask = cv2.morphologyEx(raw, cv2.MORPH_OPEN, self._kernel)
        mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, self._kernel)
        return self.view.blobs(raw, mask, object_type, frame.capture_time)

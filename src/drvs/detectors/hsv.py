"""The paper's colour model: ``hsv_HloSloVloHhiShiVhi`` filter_defs and blobs of that colour."""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from drvs.errors import InvalidArgument
from drvs.model import Detection

from .base import CameraView, Detector, FrameAnalysis, ObjectType, register, select

HSV_PREFIX = "hsv_"
_HSV_RE = re.compile(r"hsv_([0-9]{18})")
_LIMITS = {"H": 179, "S": 255, "V": 255}


@dataclass(frozen=True, slots=True)
class HsvRange:
    """An OpenCV HSV threshold box (H 0-179, S and V 0-255). h_lo > h_hi wraps through 0 (red)."""

    h_lo: int
    s_lo: int
    v_lo: int
    h_hi: int
    s_hi: int
    v_hi: int

    @classmethod
    def parse(cls, filter_def: str) -> HsvRange:
        """Parse ``hsv_`` + six zero-padded 3-digit numbers ``HloSloVloHhiShiVhi``."""
        if not isinstance(filter_def, str) or not filter_def.startswith(HSV_PREFIX):
            raise InvalidArgument(f"filter_def: {str(filter_def)[:40]!r} does not start with 'hsv_'")
        m = _HSV_RE.fullmatch(filter_def)
        if m is None:
            raise InvalidArgument(
                f"filter_def: {filter_def[:40]!r} is not 'hsv_' followed by 18 digits "
                "(six zero-padded 3-digit numbers HloSloVloHhiShiVhi)"
            )
        digits = m.group(1)
        values = [int(digits[i : i + 3]) for i in range(0, 18, 3)]
        names = ("H", "S", "V", "H", "S", "V")
        for i, (name, value) in enumerate(zip(names, values, strict=True)):
            bound = "low" if i < 3 else "high"
            if value > _LIMITS[name]:
                raise InvalidArgument(
                    f"filter_def: {name} {bound} = {value} is out of range 0-{_LIMITS[name]} in {filter_def!r}"
                )
        h_lo, s_lo, v_lo, h_hi, s_hi, v_hi = values
        if s_lo > s_hi:
            raise InvalidArgument(f"filter_def: S low {s_lo} > S high {s_hi} in {filter_def!r}")
        if v_lo > v_hi:
            raise InvalidArgument(f"filter_def: V low {v_lo} > V high {v_hi} in {filter_def!r}")
        return cls(h_lo, s_lo, v_lo, h_hi, s_hi, v_hi)

    @property
    def wraps(self) -> bool:
        return self.h_lo > self.h_hi

    def to_filter_def(self) -> str:
        values = (self.h_lo, self.s_lo, self.v_lo, self.h_hi, self.s_hi, self.v_hi)
        return HSV_PREFIX + "".join(f"{v:03d}" for v in values)

    def mask(self, hsv: NDArray[np.uint8]) -> NDArray[np.uint8]:
        """Binary mask (0/255) of the pixels of an HSV image inside this range."""
        if not self.wraps:
            return np.asarray(
                cv2.inRange(hsv, (self.h_lo, self.s_lo, self.v_lo), (self.h_hi, self.s_hi, self.v_hi)), dtype=np.uint8
            )
        upper = cv2.inRange(hsv, (self.h_lo, self.s_lo, self.v_lo), (179, self.s_hi, self.v_hi))
        lower = cv2.inRange(hsv, (0, self.s_lo, self.v_lo), (self.h_hi, self.s_hi, self.v_hi))
        return np.asarray(cv2.bitwise_or(upper, lower), dtype=np.uint8)

    def centre_hsv(self) -> tuple[int, int, int]:
        """An HSV colour in the middle of the range (useful to paint test objects)."""
        if self.wraps:
            span = (179 - self.h_lo + 1) + self.h_hi
            h = (self.h_lo + span // 2) % 180
        else:
            h = (self.h_lo + self.h_hi) // 2
        return h, (self.s_lo + self.s_hi) // 2, (self.v_lo + self.v_hi) // 2

    def centre_bgr(self) -> tuple[int, int, int]:
        hsv = np.array([[self.centre_hsv()]], dtype=np.uint8)
        b, g, r = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)[0, 0]
        return int(b), int(g), int(r)


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
        return ObjectType(filter_def, "hsv", "hsv", filter_def, HsvRange.parse(filter_def))

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

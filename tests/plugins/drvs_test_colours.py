"""A detector plug-in from outside the drvs package, as a third party would ship one: one module,
named under the "drvs.detectors" entry-point group by its package's metadata (the tests write a
.dist-info for it). It finds yellowish and greenish pixels in BGR, not HSV, so its detections come
from its own code on real pixels, mapped to the floor by the common code."""

from __future__ import annotations

from typing import Any, ClassVar

import cv2

from drvs.core.errors import InvalidArgument
from drvs.core.model import Detection
from drvs.detectors import Detector, FrameAnalysis, ObjectType, register


class _BgrBlobs(Detector):
    #: (low, high) BGR bounds.
    bounds: ClassVar[tuple[tuple[int, int, int], tuple[int, int, int]]]

    @classmethod
    def parse(cls, filter_def: str) -> ObjectType:
        head, _, size = filter_def.partition("_")
        if head != cls.prefix or not size.isdigit():
            raise InvalidArgument(f"filter_def: {filter_def!r} is not '{cls.prefix}_' and a minimum area in pixels")
        return ObjectType(filter_def, cls.prefix, cls.prefix, filter_def, int(size))

    def find(self, analysis: FrameAnalysis, object_type: ObjectType) -> tuple[Detection, ...]:
        low, high = self.bounds
        mask = cv2.bitwise_and(cv2.inRange(analysis.frame.image, low, high), self.view.fov_mask)
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        found = []
        for contour in contours:
            if cv2.contourArea(contour) < max(object_type.params, 1):
                continue
            d = self.view.detection(
                self.view.simplified(contour), object_type, analysis.frame.capture_time, score=1.0, label=self.prefix
            )
            if d is not None:
                found.append(d)
        return tuple(found)


@register
class Yellowish(_BgrBlobs):
    prefix = "yellowish"
    example = "yellowish_30"
    bounds = ((0, 120, 120), (110, 255, 255))


@register
class Greenish(_BgrBlobs):
    prefix = "greenish"
    example = "greenish_30"
    bounds = ((0, 100, 0), (110, 255, 90))


@register
class SlowYellowish(Yellowish):
    """`yellowish` behind a deliberately expensive, real image operation (a wide blur, repeated), so
    one search of a frame takes a few hundred milliseconds, as a people detector or a model does."""

    prefix = "slowyellowish"
    example = "slowyellowish_30"
    heavy = True

    def find(self, analysis: FrameAnalysis, object_type: ObjectType) -> tuple[Detection, ...]:
        blurred: Any = analysis.frame.image
        for _ in range(25):
            blurred = cv2.GaussianBlur(blurred, (41, 41), 0)
        assert blurred.shape == analysis.frame.image.shape
        return super().find(analysis, object_type)

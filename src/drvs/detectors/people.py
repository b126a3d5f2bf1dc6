"""People (``people``): OpenCV's HOG + linear SVM pedestrian detector, with the feet on the floor.

OpenCV's default people detector (Dalal and Triggs' HOG descriptor with the SVM trained on
upright pedestrians; `cv2.HOGDescriptor_getDefaultPeopleDetector`) ships inside OpenCV itself
(the contrib build in OpenCV 5): nothing is downloaded, and it runs on any CPU. It looks for
upright people in a 64 x 128 pixel window slid over an image pyramid, so it finds people whose
detection box is at least `min_height_px` tall (128 by default: the window at the frame's own
resolution; a smaller value upsamples the frame, a larger one downsamples it, and the cost goes
with the square of the factor).

Measured on real footage (OpenCV's vtest.avi, hand-marked feet in tests/data/vtest_feet.json):
it misses people much smaller than `min_height_px`, people partly hidden (behind another person,
a post, a sign) and people standing close side by side; a person who fills the frame's height gets
feet placed too high. See docs/object-types.md for the figures.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import cv2
import numpy as np
from shapely.geometry import Point

from drvs.core.errors import InvalidArgument
from drvs.core.model import Detection, PixelBox
from drvs.core.object_types import PEOPLE, parse_people

from .base import CameraView, Detector, FrameAnalysis, ObjectType, register

#: HOG's detection window height: with min_height_px at this, frames are searched as they are.
HOG_WINDOW_PX = 128
DEFAULT_MIN_HEIGHT_PX = HOG_WINDOW_PX
MIN_HEIGHT_RANGE_PX = (32.0, 1024.0)
#: Where the feet are in a HOG box, as a fraction of its height from the top: the box has margin
#: below the feet. Measured: the median of (hand-marked feet row - box top) / box height over the
#: 51 detections matched to hand-marked people in tests/data/vtest_feet.json is 0.82 (10th-90th
#: percentile 0.80-0.855). Horizontally the feet are at the box's centre (median 0.49 of its width).
#: A person too tall for their ideal box to fit in the frame is found in a smaller box with less
#: margin (basketball1.png: feet at 0.99 of the box), so their feet come out too high.
FEET_FRACTION = 0.82
#: The person occupies about the middle half of a HOG box's width (the window is 64 px wide for a
#: person about 32 px across the shoulders): the footprint's diameter is that half width.
BODY_WIDTH_FRACTION = 0.5
#: detectMultiScale settings, tuned on vtest.avi at min_height_px 85 (before MIN_MARGIN): a finer
#: pyramid (1.05) found no more people and seven times the false ones for 1.4 times the time; a
#: coarser one (1.2) missed 4 more; a 16 px stride missed half.
WIN_STRIDE = (8, 8)
PADDING = (8, 8)
PYRAMID_SCALE = 1.1
#: Boxes overlapping a stronger one by more than this (intersection over union) are the same person.
NMS_IOU = 0.3
#: Detections with a smaller SVM margin are dropped (after suppression). On vtest.avi 7 of the 9
#: false detections at margin > 0 had a margin below 0.7, and 1 of the 49 true ones.
MIN_MARGIN = 0.7


@register
class PeopleDetector(Detector):
    """Upright people, each with its feet (the ground-contact point) on the floor.

    Each detection: label "person"; `pixel_box` the HOG box (clipped to the image); the
    ground-contact point the feet, at the box's horizontal centre and FEET_FRACTION of its height
    (the box's bottom edge is below the feet); the score the SVM's margin w (how far the window is
    on the person side of the decision boundary; detections need w >= MIN_MARGIN) squashed into
    [0, 1) as w / (1 + w): 0 on the boundary, 0.41 at the threshold, 0.5 at margin 1, 0.75 at 3
    (the median true detection on vtest.avi), towards 1 for clear people.

    The outline is the person's footprint on the floor, not the image box mapped: everything above
    the feet is in the air, and mapping it through the floor homography would smear the person
    metres away from where they stand. The footprint is an octagon centred on the feet whose
    diameter is the floor distance spanned, at the feet's row, by the middle half of the box's
    width (the body's width, BODY_WIDTH_FRACTION): about 0.5-0.7 m for an adult, shoulders plus a
    stride. That is what a path planner must keep out of (inflated by its own robot's radius);
    a region query selects people by it, and `centroid` is the feet.

    Only people whose feet are in the camera's field of view are reported.

    Options (per camera, `detector_options={"people": {...}}`): `min_height_px`, the smallest
    detection box height to find, in the camera's pixels (default 128, HOG's window: no resampling).
    """

    prefix = PEOPLE
    example = PEOPLE
    heavy = True

    def __init__(self, view: CameraView, options: Mapping[str, Any] | None = None) -> None:
        super().__init__(view, options)
        self.refuse_unknown_options("min_height_px")
        raw = self.options.get("min_height_px", DEFAULT_MIN_HEIGHT_PX)
        lo, hi = MIN_HEIGHT_RANGE_PX
        if isinstance(raw, bool) or not isinstance(raw, int | float) or not (lo <= float(raw) <= hi):
            raise InvalidArgument(f"people.min_height_px: {raw!r} must be a number of pixels in [{lo:g}, {hi:g}]")
        self.min_height_px = float(raw)
        #: Resampling factor applied to frames before the search (1: none).
        self.resize = HOG_WINDOW_PX / self.min_height_px
        self._hog = cv2.HOGDescriptor()
        self._hog.setSVMDetector(np.asarray(cv2.HOGDescriptor.getDefaultPeopleDetector(), dtype=np.float32))

    @classmethod
    def parse(cls, filter_def: str) -> ObjectType:
        return parse_people(filter_def)

    def search(self, gray: np.ndarray[Any, Any]) -> list[tuple[float, float, float, float, float]]:
        """The HOG search on a grey frame: (x, y, w, h, margin) of each person in the frame's
        pixels, strongest first, after non-maximum suppression. Grey, not colour: HOG on colour
        takes each pixel's strongest channel gradient; on vtest.avi grey did as well (49 of 57 people
        found, 9 false, before the margin threshold; colour 47 and 10), one channel is less to
        resample, and the grey frame is computed once and shared with other detectors."""
        f = self.resize
        work = gray
        if abs(f - 1.0) > 1e-6:
            interpolation = cv2.INTER_LINEAR if f > 1 else cv2.INTER_AREA
            work = cv2.resize(gray, None, fx=f, fy=f, interpolation=interpolation)
        rects, weights = self._hog.detectMultiScale(
            work, hitThreshold=0.0, winStride=WIN_STRIDE, padding=PADDING, scale=PYRAMID_SCALE
        )
        if len(rects) == 0:
            return []
        margins = [float(w) for w in np.ravel(weights)]
        keep = cv2.dnn.NMSBoxes([[int(v) for v in r] for r in rects], margins, 0.0, NMS_IOU)
        out = []
        for i in np.ravel(keep):
            if margins[int(i)] < MIN_MARGIN:
                continue
            x, y, w, h = (float(v) / f for v in rects[int(i)])
            out.append((x, y, w, h, margins[int(i)]))
        out.sort(key=lambda b: -b[4])
        return out

    def find(self, analysis: FrameAnalysis, object_type: ObjectType) -> tuple[Detection, ...]:
        frame = analysis.frame
        self.view.check_frame(frame)
        found = []
        for x, y, w, h, margin in self.search(analysis.gray()):
            detection = self._person(x, y, w, h, margin, object_type, frame.capture_time)
            if detection is not None:
                found.append(detection)
        return tuple(found)

    def _person(
        self, x: float, y: float, w: float, h: float, margin: float, object_type: ObjectType, capture_time: float
    ) -> Detection | None:
        feet_px = (x + w / 2.0, y + FEET_FRACTION * h)
        if not self.view.in_view(*feet_px):
            return None
        half_body = BODY_WIDTH_FRACTION * w / 2.0
        ends = self.view.homography.apply([[feet_px[0] - half_body, feet_px[1]], [feet_px[0] + half_body, feet_px[1]]])
        feet = self.view.to_floor(feet_px)
        if not (np.all(np.isfinite(ends)) and all(math.isfinite(v) for v in feet)):
            return None
        radius = float(np.linalg.norm(ends[1] - ends[0])) / 2.0
        if radius <= 0:
            return None
        outline = Point(feet).buffer(radius, quad_segs=2)
        width, height = self.view.image_size
        x0, y0 = max(0, math.floor(x)), max(0, math.floor(y))
        x1, y1 = min(width, math.ceil(x + w)), min(height, math.ceil(y + h))
        return Detection(
            outline=outline,
            bounds=(
                float(outline.bounds[0]),
                float(outline.bounds[1]),
                float(outline.bounds[2]),
                float(outline.bounds[3]),
            ),
            centroid_xy=feet,
            ground_contact_xy=feet,
            pixel_box=PixelBox(x0, y0, max(1, x1 - x0), max(1, y1 - y0)),
            area_m2=float(outline.area),
            area_px=float(w * h),
            score=max(0.0, margin) / (1.0 + max(0.0, margin)),
            filter_def=object_type.filter_def,
            camera_id=self.view.camera_id,
            capture_time=capture_time,
            label="person",
        )

"""People (``people``): OpenCV's HOG + linear SVM pedestrian detector, searched where the floor's
geometry says a person can stand, with the feet on the floor.

OpenCV's default people detector (Dalal and Triggs' HOG descriptor with the SVM trained on
upright pedestrians; `cv2.HOGDescriptor_getDefaultPeopleDetector`) ships inside OpenCV itself
(the contrib build in OpenCV 5): nothing is downloaded, and it runs on any CPU. It looks for
upright people in a 64 x 128 pixel window (a person about 96 px tall in it).

How it searches (see `plan_passes`): the camera's floor homography is also a camera pose
(`drvs.core.upright`: its height above the floor, its tilt, its focal length), so a person
`person_height_m` tall (1.7 m) standing with their feet at image row v appears h(v) pixels tall,
in a HOG box h(v) / PERSON_IN_WINDOW tall. The search runs HOG's window at a short series of
sizes (SEARCH_STEP apart); each size only over the horizontal strip of the frame that holds the
boxes of that size whose feet are on rows where a person is nearer that size than any other
searched, one `HOGDescriptor.detect` per size (side by side on OpenCV's threads, the costliest
first). A size of 80-112 px is searched on the frame's own pixels with HOG's cells shrunk to a
sixteenth of it (NATIVE_CELLS_PX: the same descriptor and SVM, none of the upsampling's cost);
the others on the strip resized so the size fills HOG's 128 px window.
Rows whose person would be a box smaller than MIN_BOX_PX are not searched (HOG does not find
people that small even upsampled; see MIN_BOX_PX). A detection whose box is not within `height_tolerance` of
what its feet's row expects is dropped: a box of the wrong size for where it stands is not a
person standing there. With `min_height_px` set (the camera's --people-min-height), the whole
frame is searched at every scale from that height up (detectMultiScale), without the geometry;
likewise when the homography is not a camera above the floor (logged once).

Measured on real footage (OpenCV's vtest.avi, hand-marked feet in tests/data/vtest_feet.json):
it misses people partly hidden (behind another person, a post, a sign) and people standing close
side by side; a person who fills the frame's height gets feet placed too high. See
docs/object-types.md for the figures.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from shapely.geometry import Point

from drvs.core.errors import InvalidArgument
from drvs.core.model import Detection, PixelBox
from drvs.core.object_types import PEOPLE, parse_people
from drvs.core.upright import UprightGeometry

from .base import CameraView, Detector, FrameAnalysis, ObjectType, register

log = logging.getLogger(__name__)

#: HOG's detection window height: with min_height_px at this, frames are searched as they are.
HOG_WINDOW_PX = 128
#: HOG's cell (8 x 8 px), and the window's height in cells: the default people detector's window is
#: 8 x 16 cells, its blocks 2 x 2 cells moved a cell at a time.
HOG_CELL_PX = 8
WINDOW_CELLS = HOG_WINDOW_PX // HOG_CELL_PX
#: Cell sizes searched on the frame's own pixels. A box 16 c px tall is HOG's window with c px
#: cells: the same descriptor (the same 105 blocks of 2 x 2 cells, each 9 orientation bins, L2-Hys
#: normalised, so the same SVM applies) as an 8 px cell window on the frame resized by 8 / c,
#: without resampling the frame, so the pass costs the frame's pixels, not (8 / c)^2 as many. A
#: size within half a pixel a cell of one (boxes of 72-119 px) runs so, its strip resized by at most
#: 10 %. The gradient is then taken over pixels 8 / c times larger, relative to a cell, than the
#: detector was trained on: cells of 5-7 px keep that within 1.6; 4 px cells (64 px boxes, twice
#: the trained gradient scale) are upsampled as before (on vtest.avi they found one person fewer
#: and put a far person's feet 0.6 m off, for 0.1 of the old default's time less).
NATIVE_CELLS_PX = (5, 6, 7)
DEFAULT_MIN_HEIGHT_PX = HOG_WINDOW_PX
MIN_HEIGHT_RANGE_PX = (32.0, 1024.0)
#: Where the feet are in a HOG box, as a fraction of its height from the top: the box has margin
#: below the feet. Measured: the median of (hand-marked feet row - box top) / box height over the
#: 51 detections matched to hand-marked people in tests/data/vtest_feet.json is 0.82 (10th-90th
#: percentile 0.80-0.855). Horizontally the feet are at the box's centre (median 0.49 of its width).
#: A person too tall for their ideal box to fit in the frame is found in a smaller box with less
#: margin (basketball1.png: feet at 0.99 of the box), so their feet come out too high.
FEET_FRACTION = 0.82
#: The person's height in a HOG box (Dalal and Triggs: about 96 px of the 128 px window). On
#: vtest.avi, with the pose fitted to it, the true detections' boxes are 0.83-1.21 times
#: (1.7 m / this) of what their feet's row expects.
PERSON_IN_WINDOW = 0.75
#: The person's height the search expects, metres, and how far a box may be from what it expects
#: (a fraction: boxes from expected / (1 + t) to expected * (1 + t) are people).
DEFAULT_PERSON_HEIGHT_M = 1.7
PERSON_HEIGHT_RANGE_M = (0.5, 2.5)
DEFAULT_HEIGHT_TOLERANCE = 0.3
HEIGHT_TOLERANCE_RANGE = (0.05, 1.0)
#: The window sizes searched: a geometric series from MIN_BOX_PX, of ratio SEARCH_STEP under HOG's
#: 128 px (the passes that cost the most per frame pixel) and FINE_STEP from there (cheap,
#: downsampled); each size is searched on the rows whose expected box is nearer to it than to the
#: sizes beside it (between the geometric means of neighbours, widened by SEARCH_SPREAD; 1:
#: neighbouring sizes' rows just meet), so every row gets the size nearest its own, within half a
#: step (the step from under 128 px to over it included). Chosen on vtest.avi's 57 marked people: finer
#: steps below 128 px (1.15-1.2) found up to 3 more for 15-50 % more time, coarser ones (1.3-1.4)
#: lost 2-4; the man filling basketball1.png's height is found only with the finer step above
#: 128 px (his box is 0.93 of what his row expects, between two 1.25 sizes).
SEARCH_STEP = 1.25
FINE_STEP = 1.12
SEARCH_SPREAD = 1.0
#: Rows where the expected box is smaller than this are not searched: upsampling them more than
#: HOG_WINDOW_PX / MIN_BOX_PX costs more than the few people found there.
MIN_BOX_PX = 64.0
#: The person occupies about the middle half of a HOG box's width (the window is 64 px wide for a
#: person about 32 px across the shoulders): the footprint's diameter is that half width.
BODY_WIDTH_FRACTION = 0.5
#: detectMultiScale settings, tuned on vtest.avi at min_height_px 85 (before MIN_MARGIN): a finer
#: pyramid (1.05) found no more people and seven times the false ones for 1.4 times the time; a
#: coarser one (1.2) missed 4 more; a 16 px stride missed half.
WIN_STRIDE = (8, 8)
PADDING = (8, 8)
PYRAMID_SCALE = 1.1
#: The search by geometry: raw window hits a person needs (detectMultiScale's grouping needs more
#: than 2 alike over its finer pyramid; one pass per size has fewer), and the margin it needs (the
#: size check drops what a lower margin lets in: on vtest.avi no false detection at 0.4).
GROUP_MIN_HITS = 1
GEOMETRY_MIN_MARGIN = 0.4
#: Each pass's crop reaches this many of HOG's pixels (at the pass's scale) beyond the boxes whose
#: feet are on its rows, above and below (two of its 8 px strides: with one, 2 of the 57 people on
#: vtest.avi are lost at 768x576).
PASS_MARGIN = 16.0
#: HOG pads each crop (replicating its edge) for windows partly out of the frame at its sides.
PASS_PADDING = (8, 0)
#: Boxes overlapping a stronger one by more than this (intersection over union) are the same person.
NMS_IOU = 0.3
#: Detections with a smaller SVM margin are dropped (after suppression). On vtest.avi 7 of the 9
#: false detections at margin > 0 had a margin below 0.7, and 1 of the 49 true ones.
MIN_MARGIN = 0.7

Box = tuple[float, float, float, float, float]


def _hog(cell_px: int = HOG_CELL_PX) -> cv2.HOGDescriptor:
    """OpenCV's default people detector with `cell_px` pixel cells (HOG_CELL_PX: its own window)."""
    if cell_px == HOG_CELL_PX:
        hog = cv2.HOGDescriptor()
    else:
        c = cell_px
        # Gamma correction and the blocks' Gaussian weight (its sigma a quarter of the block) as the default's.
        hog = cv2.HOGDescriptor((WINDOW_CELLS // 2 * c, WINDOW_CELLS * c), (2 * c, 2 * c), (c, c), (c, c), 9)
    hog.setSVMDetector(np.asarray(cv2.HOGDescriptor.getDefaultPeopleDetector(), dtype=np.float32))
    return hog


@dataclass(frozen=True)
class Pass:
    """One pass of the search: HOG's window at one size, `box_px` tall in the frame's pixels, over
    the crop (x0, y0, x1, y1) of the frame that holds every box of that size whose feet are on a row
    where a person is about that tall (`feet_rows`, first and last); the crop is resized by
    HOG_WINDOW_PX / box_px."""

    box_px: float
    feet_rows: tuple[int, int]
    crop: tuple[int, int, int, int]

    @property
    def cell_px(self) -> int:
        """HOG's cell size for this pass: one of NATIVE_CELLS_PX when the size is nearest a window
        of that many pixels a cell (the crop then resized by at most a few per cent), else
        HOG_CELL_PX (the crop resized to HOG's own window)."""
        cell = round(self.box_px / WINDOW_CELLS)
        return cell if cell in NATIVE_CELLS_PX else HOG_CELL_PX

    @property
    def factor(self) -> float:
        """How much the crop is resized by: the box to the window's height at the pass's cell size."""
        return WINDOW_CELLS * self.cell_px / self.box_px

    @property
    def cells(self) -> float:
        """How many HOG cells the resized crop holds: what the pass costs (the windows it scores and
        the blocks it bins are both so many, at a stride of one cell)."""
        x0, y0, x1, y1 = self.crop
        return (x1 - x0) * (y1 - y0) * (self.factor / self.cell_px) ** 2


def expected_box_px(
    geometry: UprightGeometry, view: CameraView, person_height_m: float
) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
    """For every image row, the HOG box height a standing person with feet on that row gets (the
    smallest and largest over the view's columns at that row; NaN where no one can stand)."""
    width, height = view.image_size
    x0, _, x1, _ = view.field_of_view.image.bounds
    cols = np.clip(np.array([x0, (x0 + x1) / 2.0, x1]), 0.0, width - 1.0)
    feet = np.array([[u, v] for v in range(height) for u in cols], dtype=np.float64)
    boxes = (geometry.height_px(feet, person_height_m) / PERSON_IN_WINDOW).reshape(height, len(cols))
    usable = np.all(boxes > 0, axis=1)  # NaN compares False
    lo = np.where(usable, np.min(boxes, axis=1, initial=np.inf, where=usable[:, None]), np.nan)
    hi = np.where(usable, np.max(boxes, axis=1, initial=-np.inf, where=usable[:, None]), np.nan)
    return lo, hi


def search_sizes(smallest: float, biggest: float) -> list[float]:
    """The window sizes searched: from `smallest`, SEARCH_STEP apart under HOG_WINDOW_PX and
    FINE_STEP apart from there, up to the first at or beyond `biggest`."""
    sizes = [smallest]
    while sizes[-1] < biggest:
        sizes.append(sizes[-1] * (SEARCH_STEP if sizes[-1] < HOG_WINDOW_PX else FINE_STEP))
    return sizes


def plan_passes(view: CameraView, lo: np.ndarray[Any, Any], hi: np.ndarray[Any, Any]) -> list[Pass]:
    """The window sizes to search (`search_sizes` from MIN_BOX_PX), each over the rows where feet can
    be (in the field of view) and a person's expected box is nearer to it than to the sizes beside
    it (the geometric means between neighbours, times SEARCH_SPREAD; the smallest and the biggest
    reach half their step outwards): every row of the floor is searched at the size nearest its own."""
    width, height = view.image_size
    fx0, fy0, fx1, fy1 = view.field_of_view.image.bounds
    rows = np.arange(height)
    in_view = (rows >= math.ceil(fy0)) & (rows <= math.floor(fy1)) & np.isfinite(lo)
    if not in_view.any():
        return []
    left, right = max(0, math.floor(fx0) - PADDING[0]), min(width, math.ceil(fx1) + PADDING[0])
    sizes = search_sizes(MIN_BOX_PX, float(np.max(hi[in_view])))
    if len(sizes) == 1:  # one size: it covers half a step either side
        sizes.append(sizes[0] * SEARCH_STEP)
    bounds = [sizes[0] ** 1.5 / sizes[1] ** 0.5]
    bounds += [math.sqrt(a * b) for a, b in itertools.pairwise(sizes)]
    bounds += [sizes[-1] ** 1.5 / sizes[-2] ** 0.5]
    passes: list[Pass] = []
    for box, below, above in zip(sizes, bounds, bounds[1:], strict=False):
        near = rows[in_view & (lo <= above * SEARCH_SPREAD) & (hi >= below / SEARCH_SPREAD)]
        if len(near):
            first, last = int(near.min()), int(near.max())
            margin = PASS_MARGIN * box / HOG_WINDOW_PX  # a window's stride or two, in the frame's pixels
            top = max(0, math.floor(first - FEET_FRACTION * box - margin))
            bottom = min(height, math.ceil(last + (1.0 - FEET_FRACTION) * box + margin))
            passes.append(Pass(box, (first, last), (left, top, right, bottom)))
    return passes


def group(boxes: list[Box], min_hits: int, eps: float = 0.2) -> list[Box]:
    """OpenCV's grouping of raw window hits (cv::groupRectangles, as detectMultiScale runs it): hits
    alike within `eps` of their size are one cluster; a cluster of at least `min_hits` becomes its
    average box with its strongest hit's margin; a cluster inside a much stronger one is dropped."""
    n = len(boxes)
    parent = list(range(n))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i in range(n):
        xi, yi, wi, hi_, _ = boxes[i]
        for j in range(i):
            xj, yj, wj, hj, _ = boxes[j]
            delta = eps * (min(wi, wj) + min(hi_, hj)) * 0.5
            if (abs(xi - xj) <= delta and abs(yi - yj) <= delta and abs(xi + wi - xj - wj) <= delta
                    and abs(yi + hi_ - yj - hj) <= delta):  # fmt: skip
                parent[root(i)] = root(j)
    clusters: dict[int, list[Box]] = {}
    for i in range(n):
        clusters.setdefault(root(i), []).append(boxes[i])
    merged = []
    for members in clusters.values():
        if len(members) < min_hits:
            continue
        mean = np.mean(np.array([m[:4] for m in members]), axis=0)
        merged.append((*(float(v) for v in mean), max(m[4] for m in members), len(members)))
    out: list[Box] = []
    for x, y, w, h, margin, count in merged:
        inside = False
        for x2, y2, w2, h2, _, count2 in merged:
            dx, dy = w2 * 0.2, h2 * 0.2
            if (count2 > max(3, count) and x >= x2 - dx and y >= y2 - dy and x + w <= x2 + w2 + dx
                    and y + h <= y2 + h2 + dy):  # fmt: skip
                inside = True
                break
        if not inside:
            out.append((x, y, w, h, margin))
    return out


def suppress(boxes: list[Box], min_margin: float) -> list[Box]:
    """Non-maximum suppression (NMS_IOU) and the margin threshold, strongest first."""
    if not boxes:
        return []
    margins = [b[4] for b in boxes]
    keep = cv2.dnn.NMSBoxes([[round(v) for v in b[:4]] for b in boxes], margins, 0.0, NMS_IOU)
    out = [boxes[int(i)] for i in np.ravel(keep) if margins[int(i)] >= min_margin]
    out.sort(key=lambda b: -b[4])
    return out


def _resized(image: np.ndarray[Any, Any], factor: float) -> np.ndarray[Any, Any]:
    if abs(factor - 1.0) <= 1e-6:
        return image
    interpolation = cv2.INTER_LINEAR if factor > 1 else cv2.INTER_AREA
    return cv2.resize(image, None, fx=factor, fy=factor, interpolation=interpolation)


def _hits(hogs: Mapping[int, cv2.HOGDescriptor], gray: np.ndarray[Any, Any], p: Pass) -> list[Box]:
    """Every window of one pass where the SVM says person (margin > 0), in the frame's pixels."""
    x0, y0, x1, y1 = p.crop
    cell = p.cell_px
    work = _resized(gray[y0:y1, x0:x1], p.factor)
    if work.shape[0] < WINDOW_CELLS * cell or work.shape[1] < WINDOW_CELLS // 2 * cell:
        return []
    stride = (WIN_STRIDE[0] * cell // HOG_CELL_PX, WIN_STRIDE[1] * cell // HOG_CELL_PX)
    if cell == HOG_CELL_PX:
        pad = 0
        points, weights = hogs[cell].detect(work, hitThreshold=0.0, winStride=stride, padding=PASS_PADDING)
    else:
        # HOG aligns its padding to a power of two, which a 5-7 px stride is not: the crop is padded
        # here instead, by PASS_PADDING in cells, reflecting its edge as HOG does.
        pad = PASS_PADDING[0] * cell // HOG_CELL_PX
        work = cv2.copyMakeBorder(work, 0, 0, pad, pad, cv2.BORDER_REFLECT_101)
        points, weights = hogs[cell].detect(work, hitThreshold=0.0, winStride=stride, padding=(0, 0))
    w = p.box_px / 2.0
    return [(x0 + float(u - pad) / p.factor, y0 + float(v) / p.factor, w, p.box_px, float(m))
            for (u, v), m in zip(np.reshape(points, (-1, 2)), np.ravel(weights), strict=True)]  # fmt: skip


def _number(options: Mapping[str, Any], key: str, default: float, limits: tuple[float, float], unit: str) -> float:
    raw = options.get(key, default)
    lo, hi = limits
    if isinstance(raw, bool) or not isinstance(raw, int | float) or not (lo <= float(raw) <= hi):
        raise InvalidArgument(f"people.{key}: {raw!r} must be a number of {unit} in [{lo:g}, {hi:g}]")
    return float(raw)


@register
class PeopleDetector(Detector):
    """Upright people, each with its feet (the ground-contact point) on the floor.

    Each detection: label "person"; `pixel_box` the HOG box (clipped to the image); the
    ground-contact point the feet, at the box's horizontal centre and FEET_FRACTION of its height
    (the box's bottom edge is below the feet); the score the SVM's margin w (how far the window is
    on the person side of the decision boundary; detections need w >= GEOMETRY_MIN_MARGIN when
    searched by geometry, MIN_MARGIN over the whole frame) squashed into [0, 1) as w / (1 + w): 0 on
    the boundary, 0.29 and 0.41 at the thresholds, 0.5 at margin 1, 0.75 at 3 (the median true
    detection on vtest.avi), towards 1 for clear people.

    The outline is the person's footprint on the floor, not the image box mapped: everything above
    the feet is in the air, and mapping it through the floor homography would smear the person
    metres away from where they stand. The footprint is an octagon centred on the feet whose
    diameter is the floor distance spanned, at the feet's row, by the middle half of the box's
    width (the body's width, BODY_WIDTH_FRACTION): about 0.5-0.7 m for an adult, shoulders plus a
    stride. That is what a path planner must keep out of (inflated by its own robot's radius);
    a region query selects people by it, and `centroid` is the feet.

    Only people whose feet are in the camera's field of view are reported.

    Options (per camera, `detector_options={"people": {...}}`): `person_height_m` (default 1.7) and
    `height_tolerance` (default 0.3) for the search by geometry; `min_height_px`, the smallest
    detection box height to find in the camera's pixels, searches the whole frame instead (128 is
    HOG's window: no resampling).
    """

    prefix = PEOPLE
    example = PEOPLE
    heavy = True

    def __init__(self, view: CameraView, options: Mapping[str, Any] | None = None) -> None:
        super().__init__(view, options)
        self.refuse_unknown_options("min_height_px", "person_height_m", "height_tolerance")
        self.min_height_px = _number(
            self.options, "min_height_px", DEFAULT_MIN_HEIGHT_PX, MIN_HEIGHT_RANGE_PX, "pixels"
        )
        self.person_height_m = _number(self.options, "person_height_m", DEFAULT_PERSON_HEIGHT_M,
                                       PERSON_HEIGHT_RANGE_M, "metres")  # fmt: skip
        self.height_tolerance = _number(self.options, "height_tolerance", DEFAULT_HEIGHT_TOLERANCE,
                                        HEIGHT_TOLERANCE_RANGE, "the expected height")  # fmt: skip
        #: Resampling factor applied to frames before a whole-frame search (1: none).
        self.resize = HOG_WINDOW_PX / self.min_height_px
        #: The search by geometry: its passes and, per feet row, the expected box (None: whole frame).
        self.passes: list[Pass] | None = None
        self._expected: np.ndarray[Any, Any] | None = None
        #: The camera's height above the floor its homography implies (None: no geometry).
        self.camera_height_m: float | None = None
        if "min_height_px" not in self.options:
            try:
                geometry = UprightGeometry.from_homography(view.homography, view.image_size)
            except InvalidArgument as exc:
                log.warning("people on camera %r: searching the whole frame, not by geometry: %s",
                            view.camera_id, exc)  # fmt: skip
            else:
                lo, hi = expected_box_px(geometry, view, self.person_height_m)
                self._expected = np.sqrt(lo * hi)
                self.passes = plan_passes(view, lo, hi)
                self.camera_height_m = geometry.camera_height_m
        self._hog = _hog()
        #: The descriptor per cell size the passes use (HOG_CELL_PX: the one above).
        self._hogs = {HOG_CELL_PX: self._hog} | {p.cell_px: _hog(p.cell_px) for p in self.passes or ()}
        #: The passes run side by side on OpenCV's threads (cv2.setNumThreads), as detectMultiScale
        #: runs its pyramid's levels: one HOGDescriptor serves concurrent detect calls.
        threads = min(cv2.getNumThreads(), len(self.passes or ()))
        self._pool = ThreadPoolExecutor(threads, thread_name_prefix="people") if threads > 1 else None
        #: The order the pool takes the passes in: the costliest first, so the threads end together.
        self._by_cost = sorted(self.passes or (), key=lambda p: -p.cells)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    @classmethod
    def parse(cls, filter_def: str) -> ObjectType:
        return parse_people(filter_def)

    def search(self, gray: np.ndarray[Any, Any]) -> list[Box]:
        """The HOG search on a grey frame: (x, y, w, h, margin) of each person in the frame's
        pixels, strongest first, after non-maximum suppression. Grey, not colour: HOG on colour
        takes each pixel's strongest channel gradient; on vtest.avi grey did as well (49 of 57 people
        found, 9 false, before the margin threshold; colour 47 and 10), one channel is less to
        resample, and the grey frame is computed once and shared with other detectors."""
        if self.passes is None:
            work = _resized(gray, self.resize)
            rects, weights = self._hog.detectMultiScale(work, hitThreshold=0.0, winStride=WIN_STRIDE,
                                                        padding=PADDING, scale=PYRAMID_SCALE)  # fmt: skip
            f = self.resize
            boxes = [
                (r[0] / f, r[1] / f, r[2] / f, r[3] / f, float(w))
                for r, w in zip(rects, np.ravel(weights), strict=True)
            ]
            return suppress(boxes, MIN_MARGIN)
        if self._pool is None:
            hits = [h for p in self.passes for h in _hits(self._hogs, gray, p)]
        else:
            parts = self._pool.map(lambda p: _hits(self._hogs, gray, p), self._by_cost)
            hits = [h for part in parts for h in part]
        return suppress([b for b in group(hits, GROUP_MIN_HITS) if self.plausible(b)], GEOMETRY_MIN_MARGIN)

    def plausible(self, box: Box) -> bool:
        """Is the box the size a person standing at its feet's row has (within the tolerance)?"""
        if self._expected is None:
            return True
        _, y, _, h, _ = box
        row = round(y + FEET_FRACTION * h)
        if not 0 <= row < len(self._expected) or not math.isfinite(self._expected[row]):
            return False
        ratio = h / float(self._expected[row])
        return 1.0 / (1.0 + self.height_tolerance) <= ratio <= 1.0 + self.height_tolerance

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

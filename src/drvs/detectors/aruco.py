"""Fiducial markers lying on the floor: ``aruco_<dictionary>`` and ``aruco_<dictionary>_<id>``
(the grammar and the dictionary table are the core's, drvs.core.object_types).

Dictionaries are OpenCV's predefined ones (the ``cv2.aruco.DICT_*`` constants), named in lower
case without ``DICT_``: ``4x4_50``, ``6x6_1000``, ``apriltag_36h11``; the two whose OpenCV names
repeat the word (``DICT_ARUCO_ORIGINAL``, ``DICT_ARUCO_MIP_36H12``) drop it: ``aruco_original``,
``aruco_mip_36h12_3``. One search per frame and dictionary finds every marker of it; a one-id
type keeps its marker (`narrow`).

A detection is the marker's floor outline (its four corners mapped through the homography), its
centre (where the image diagonals cross, mapped: the centre of a square seen in perspective is
not the centroid of its image), and its heading: degrees counter-clockwise from the world x axis
to the marker's x axis (corner 0 to corner 1 in OpenCV's order, the printed marker's top edge
read left to right), measured between the mapped corners and so free of the perspective.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import threading
from collections.abc import Mapping
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from drvs.core.model import Detection
from drvs.core.object_types import ARUCO_PREFIX as ARUCO_PREFIX
from drvs.core.object_types import DICTIONARIES as DICTIONARIES
from drvs.core.object_types import DICTIONARY_SIZES as DICTIONARY_SIZES
from drvs.core.object_types import MarkerType as MarkerType
from drvs.core.object_types import parse_aruco
from drvs.core.object_types import parse_marker_type as parse_marker_type

from .base import CameraView, Detector, FrameAnalysis, ObjectType, register


@functools.cache
def _check_dictionaries() -> None:
    """(Once, when the first detector is built: an OpenCV without cv2.aruco must still import this
    module, so that a camera can say the detector is unavailable and serve the others.)

    The grammar's dictionary table (drvs.core.object_types, which imports no OpenCV) is this cv2's:
    each name (OpenCV's DICT_ constant's, lower case, "aruco_" dropped) is that constant, of that size.
    A dictionary a later OpenCV adds is not offered until the table names it."""
    for attr in dir(cv2.aruco):
        value = getattr(cv2.aruco, attr)
        name = attr[len("DICT_") :].lower().removeprefix("aruco_")
        if attr.startswith("DICT_") and name in DICTIONARIES and DICTIONARIES[name] != value:
            raise RuntimeError(
                f"cv2.aruco.{attr} is {value}; drvs.core.object_types has {name}: {DICTIONARIES.get(name)}"
            )
    for name, value in DICTIONARIES.items():
        size = int(cv2.aruco.getPredefinedDictionary(value).bytesList.shape[0])
        if size != DICTIONARY_SIZES[name]:
            raise RuntimeError(
                f"ArUco {name}: OpenCV has {size} markers, drvs.core.object_types {DICTIONARY_SIZES[name]}"
            )


def heading_deg(corners_floor: NDArray[np.float64]) -> float:
    """Degrees counter-clockwise from the world x axis to the marker's x axis (corner 0 -> corner 1),
    in (-180, 180]: the mean direction of its two sides along x (0 -> 1 and 3 -> 2), which halves
    the error one side's corners carry."""
    dx, dy = (corners_floor[1] - corners_floor[0]) + (corners_floor[2] - corners_floor[3])
    heading = math.degrees(math.atan2(float(dy), float(dx)))
    return 180.0 if heading <= -180.0 else heading


def diagonal_crossing(corners: NDArray[np.float64]) -> tuple[float, float] | None:
    """Where the diagonals corner 0-2 and corner 1-3 cross (the square's true centre in the image)."""
    p0, p1, p2, p3 = (np.asarray(c, dtype=np.float64) for c in corners)
    d1, d2 = p2 - p0, p3 - p1
    denom = d1[0] * d2[1] - d1[1] * d2[0]
    if abs(denom) < 1e-12:
        return None
    diff = p1 - p0
    t = (diff[0] * d2[1] - diff[1] * d2[0]) / denom
    x, y = p0 + t * d1
    return float(x), float(y)


@register
class ArucoDetector(Detector):
    """OpenCV's ArUco detector (sub-pixel corners), one search per frame and dictionary."""

    prefix = "aruco"
    example = "aruco_4x4_50_7"

    def __init__(self, view: CameraView, options: Mapping[str, Any] | None = None) -> None:
        super().__init__(view, options)
        _check_dictionaries()
        # cv2.aruco.ArucoDetector objects are built once per thread and dictionary: find() for
        # different keys (and for one key on two frames) may run at once on different threads,
        # and OpenCV does not promise that one detector object may be used concurrently.
        self._local = threading.local()

    @classmethod
    def parse(cls, filter_def: str) -> ObjectType:
        return parse_aruco(filter_def)

    def _detector(self, dictionary: str) -> cv2.aruco.ArucoDetector:
        cache: dict[str, cv2.aruco.ArucoDetector] | None = getattr(self._local, "detectors", None)
        if cache is None:
            cache = self._local.detectors = {}
        detector = cache.get(dictionary)
        if detector is None:
            params = cv2.aruco.DetectorParameters()
            # Sub-pixel corners (cornerSubPix): positions, outlines and headings come from them.
            # The window's half-size is 0.8 of a module (a marker cell), so that it stays within
            # the marker's black border and the white around it, whatever the marker's size in
            # the image. On 50 markers 17-50 px wide, rendered as tests/detectors/test_aruco_detector.py
            # renders them, then blurred, noisy and JPEG compressed, OpenCV's default of 0.3 left
            # corners up to 2.3 px off (3.7 degrees of heading); 0.8 kept them within 0.6 px
            # (0.9 degrees). CORNER_REFINE_CONTOUR placed corners 0.5-0.7 px inside the marker.
            params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
            params.relativeCornerRefinmentWinSize = 0.8
            detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(DICTIONARIES[dictionary]), params)
            cache[dictionary] = detector
        return detector

    def find(self, analysis: FrameAnalysis, object_type: ObjectType) -> tuple[Detection, ...]:
        frame = analysis.frame
        self.view.check_frame(frame)
        marker: MarkerType = object_type.params
        corners, ids, _rejected = self._detector(marker.dictionary).detectMarkers(analysis.gray())
        if ids is None:
            return ()
        found: list[Detection] = []
        for marker_corners, marker_id in zip(corners, np.asarray(ids).ravel(), strict=True):
            detection = self._to_floor(
                np.asarray(marker_corners, dtype=np.float64).reshape(4, 2),
                int(marker_id),
                object_type.key,
                frame.capture_time,
            )
            if detection is not None:
                found.append(detection)
        found.sort(key=lambda d: d.marker_id or 0)
        return tuple(found)

    def _to_floor(
        self, corners: NDArray[np.float64], marker_id: int, key: str, capture_time: float
    ) -> Detection | None:
        centre = diagonal_crossing(corners)
        if centre is None or not self.view.in_view(*centre):
            return None  # outside the field of view the homography means nothing
        corners_floor = self.view.homography.apply(corners)
        if not np.all(np.isfinite(corners_floor)):
            return None
        return self.view.detection(
            corners,
            key,
            capture_time,
            score=1.0,
            contact_px=centre,
            centre_px=centre,
            marker_id=marker_id,
            heading_deg=heading_deg(np.asarray(corners_floor, dtype=np.float64)),
        )

    def narrow(self, found: tuple[Detection, ...], object_type: ObjectType) -> tuple[Detection, ...]:
        marker: MarkerType = object_type.params
        if object_type.filter_def == object_type.key:
            return found
        return tuple(
            dataclasses.replace(d, filter_def=object_type.filter_def)
            for d in found
            if marker.marker_id is None or d.marker_id == marker.marker_id
        )

"""Detection on real pixels, mapped onto the floor: frames, per-frame analyses and the detectors.

The detectors themselves are plug-ins in `drvs.detectors`; this module keeps the names robot
and camera code have always imported from here.
"""

from __future__ import annotations

from drvs.detectors import (
    DEFAULT_MIN_AREA_PX,
    OUTLINE_TOLERANCE_PX,
    CameraView,
    Detector,
    Frame,
    FrameAnalysis,
    HsvDetector,
    ObjectType,
    select,
)

__all__ = [
    "DEFAULT_MIN_AREA_PX",
    "OUTLINE_TOLERANCE_PX",
    "CameraView",
    "Detector",
    "Frame",
    "FrameAnalysis",
    "HsvDetector",
    "ObjectType",
    "select",
]

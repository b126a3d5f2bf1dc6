"""Detector plug-ins, keyed by the prefix of the filter_def strings they serve.

A new detector is one module here: a `Detector` subclass decorated with `@register`, imported
below. See `drvs.detectors.base` for what a detector implements and what stays common.
"""

from __future__ import annotations

from .aruco import ArucoDetector as ArucoDetector
from .base import (
    DEFAULT_MIN_AREA_PX,
    OUTLINE_TOLERANCE_PX,
    REGISTRY,
    CameraView,
    Detector,
    Frame,
    FrameAnalysis,
    ObjectType,
    parse_object_type,
    prefixes,
    register,
    select,
)

# Built-in detectors register themselves on import.
from .hsv import HsvDetector, HsvRange
from .people import PeopleDetector  # noqa: F401

# isort: split
from .foreground import ForegroundDetector  # noqa: F401  (registers "foreground")
from .model import ModelDetector  # noqa: F401

__all__ = [
    "DEFAULT_MIN_AREA_PX",
    "OUTLINE_TOLERANCE_PX",
    "REGISTRY",
    "CameraView",
    "Detector",
    "Frame",
    "FrameAnalysis",
    "HsvDetector",
    "HsvRange",
    "ObjectType",
    "parse_object_type",
    "prefixes",
    "register",
    "select",
]

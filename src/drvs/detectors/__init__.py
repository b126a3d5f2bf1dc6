"""Detector plug-ins, keyed by the prefix of the filter_def strings they serve.

A new detector is one module: a `Detector` subclass decorated with `@register`, either here
(imported below) or in any installed package that names the module under the "drvs.detectors"
entry-point group. Cameras load them all; `@register` adds a plug-in's filter_def grammar to the
core's (`drvs.core.object_types`), which servers and robots parse with without importing this package.
See `drvs.detectors.base` for what a detector implements and what stays common.
"""

from __future__ import annotations

import importlib.metadata
import logging

from drvs.core.object_types import PLUGIN_GROUP

from .aruco import ArucoDetector as ArucoDetector
from .base import (
    DEFAULT_MIN_AREA_PX,
    OPENCV_CONTRIB_FIX,
    OUTLINE_TOLERANCE_PX,
    REGISTRY,
    Backend,
    CameraView,
    Detector,
    DetectorUnavailable,
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
from .model import ModelDetector  # noqa: F401
from .people import PeopleDetector  # noqa: F401

# isort: split
from .foreground import ForegroundDetector  # noqa: F401  (registers "foreground")

__all__ = [
    "DEFAULT_MIN_AREA_PX",
    "DETECTOR_KINDS",
    "OPENCV_CONTRIB_FIX",
    "OUTLINE_TOLERANCE_PX",
    "REGISTRY",
    "Backend",
    "CameraView",
    "Detector",
    "DetectorUnavailable",
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


#: The entry-point group a package names its detector modules in, e.g. in its pyproject.toml:
#: [project.entry-points."drvs.detectors"] stripes = "my_package.stripes"
ENTRY_POINT_GROUP = PLUGIN_GROUP
log = logging.getLogger(__name__)


def _load_plugins() -> None:
    """Import the detector modules installed packages name; each registers itself. A broken
    plug-in is logged and skipped: it must not take down the cameras and servers that never use it."""
    for entry in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
        try:
            entry.load()
        except Exception as exc:  # a third party's import error, whatever it is
            log.error(
                "detector plug-in %s (%s) failed to load: %s: %s", entry.name, entry.value, type(exc).__name__, exc
            )


_load_plugins()

#: The prefixes of the detectors this process can run (built-ins, then plug-ins), in registration order.
DETECTOR_KINDS = prefixes()

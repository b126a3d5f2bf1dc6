"""filter_def strings: which object type a robot asks for (``hsv_014110130035225200``,
``aruco_4x4_50_7``, ``people``, ``foreground``, ``model_yolo_person``).

Parsing belongs to each detector plug-in (`drvs.detectors`); this module is the entry point the
request model, the server and the client use.
"""

from __future__ import annotations

import functools

from drvs.detectors import REGISTRY, HsvRange, ObjectType, parse_object_type, prefixes
from drvs.detectors.hsv import HSV_PREFIX

__all__ = [
    "DETECTOR_KINDS",
    "HSV_PREFIX",
    "HsvRange",
    "detector_kind",
    "is_known_type",
    "object_type",
    "validate_filter_def",
]

#: The filter_def prefixes this package can parse, in registration order.
DETECTOR_KINDS = prefixes()


def validate_filter_def(filter_def: str) -> str:
    """The routing kind of a well-formed filter_def; InvalidArgument says what is wrong."""
    return object_type(filter_def).kind


def object_type(filter_def: str) -> ObjectType:
    """The parsed filter_def; InvalidArgument naming the part that is wrong."""
    if isinstance(filter_def, str) and len(filter_def) <= 64:
        return _parsed(filter_def)  # robots ask for the same few objects again and again
    return parse_object_type(filter_def)


@functools.lru_cache(maxsize=1024)
def _parsed(filter_def: str) -> ObjectType:
    return parse_object_type(filter_def)  # lru_cache keeps answers only: a bad filter_def raises every time


def detector_kind(filter_def: str) -> str:
    """The routing kind a filter_def asks for (what cameras register), or InvalidArgument."""
    return object_type(filter_def).kind


def is_known_type(filter_def: str) -> bool:
    """Does this process have a detector plug-in for the filter_def's prefix?"""
    return isinstance(filter_def, str) and filter_def.split("_", 1)[0] in REGISTRY

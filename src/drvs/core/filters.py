"""filter_def strings: which object type a robot asks for (``hsv_014110130035225200``,
``aruco_4x4_50_7``, ``people``, ``foreground``, ``model_yolo_person``).

The grammar is `drvs.core.object_types` (pure: no OpenCV, no detector); this module keeps the names
the request model, the server, cameras and tools have imported from here.
"""

from __future__ import annotations

from drvs.core.object_types import HSV_PREFIX, HsvRange, ObjectType, detector_kind, is_known_type, object_type

__all__ = [
    "HSV_PREFIX",
    "HsvRange",
    "ObjectType",
    "detector_kind",
    "is_known_type",
    "object_type",
    "validate_filter_def",
]

#: The old name of `detector_kind` (both validated a filter_def and returned its routing kind).
validate_filter_def = detector_kind

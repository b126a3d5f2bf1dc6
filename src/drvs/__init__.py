"""DRVS: a Distributed Robotic Vision Service.

Robots ask for *what* (a filter_def) and *where* (a floor region); the server forwards the request to
the camera nodes that see that region; the cameras stream object locations back to the robot.

The robot programmer's API is re-exported here (from drvs.robot and drvs.errors):

    from drvs import DrvsClient

    async with DrvsClient.connect("drvs.example:50051", robot_id="turtle-1") as drvs:
        result = await drvs.detect("hsv_014110130035225200", (0, 0, 5, 5))

Those names are imported when first used, so `import drvs` (as a camera node or the server does
for its own modules) stays light.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

if TYPE_CHECKING:
    from drvs.errors import (
        DeadlineExceeded,
        DrvsError,
        FailedPrecondition,
        InvalidArgument,
        NotFound,
        PermissionDenied,
        ResourceExhausted,
        Unauthenticated,
        Unavailable,
    )
    from drvs.model import CameraError, Detection, DetectionReport
    from drvs.robot.client import CameraInfo, DetectionResult, DrvsClient, RetryPolicy, Subscription

_EXPORTS = {
    "DrvsClient": "drvs.robot.client",
    "RetryPolicy": "drvs.robot.client",
    "DetectionResult": "drvs.robot.client",
    "Subscription": "drvs.robot.client",
    "CameraInfo": "drvs.robot.client",
    "Detection": "drvs.model",
    "DetectionReport": "drvs.model",
    "CameraError": "drvs.model",
    "DrvsError": "drvs.errors",
    "InvalidArgument": "drvs.errors",
    "NotFound": "drvs.errors",
    "Unavailable": "drvs.errors",
    "DeadlineExceeded": "drvs.errors",
    "FailedPrecondition": "drvs.errors",
    "ResourceExhausted": "drvs.errors",
    "PermissionDenied": "drvs.errors",
    "Unauthenticated": "drvs.errors",
}

__all__ = [
    "CameraError",
    "CameraInfo",
    "DeadlineExceeded",
    "Detection",
    "DetectionReport",
    "DetectionResult",
    "DrvsClient",
    "DrvsError",
    "FailedPrecondition",
    "InvalidArgument",
    "NotFound",
    "PermissionDenied",
    "ResourceExhausted",
    "RetryPolicy",
    "Subscription",
    "Unauthenticated",
    "Unavailable",
    "__version__",
]


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'drvs' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_EXPORTS])

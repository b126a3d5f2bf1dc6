"""DRVS: a Distributed Robotic Vision Service.

Robots ask for *what* (a filter_def) and *where* (a floor region); the server forwards the request to
the camera nodes that see that region; the cameras stream object locations back to the robot.

The robot programmer's API is re-exported here (from drvs.robot, drvs.core.model, drvs.core.errors and
drvs.wire.security):

    from drvs import DrvsClient

    async with DrvsClient.connect("drvs.example:50051", robot_id="turtle-1") as drvs:
        result = await drvs.detect("hsv_014110130035225200", (0, 0, 5, 5))

filter_defs can be built from typed arguments, checked by the grammar (drvs.core.object_types):
`drvs.hsv((14, 110, 130), (35, 225, 200))`, `drvs.aruco("4x4_50", 7)`, `drvs.people()`,
`drvs.foreground()`, `drvs.model_type("yolo", "person")` (model_type: `model` names a module).

Those names are imported when first used, so `import drvs` (as a camera node or the server does
for its own modules) stays light.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

if TYPE_CHECKING:
    from drvs.core.errors import DeadlineExceeded as DeadlineExceeded
    from drvs.core.errors import DrvsError as DrvsError
    from drvs.core.errors import FailedPrecondition as FailedPrecondition
    from drvs.core.errors import InvalidArgument as InvalidArgument
    from drvs.core.errors import NotFound as NotFound
    from drvs.core.errors import PermissionDenied as PermissionDenied
    from drvs.core.errors import ResourceExhausted as ResourceExhausted
    from drvs.core.errors import Unauthenticated as Unauthenticated
    from drvs.core.errors import Unavailable as Unavailable
    from drvs.core.model import CameraError as CameraError
    from drvs.core.model import Detection as Detection
    from drvs.core.model import DetectionReport as DetectionReport
    from drvs.core.model import FusionOptions as FusionOptions
    from drvs.core.model import Pose2 as Pose2
    from drvs.core.model import Snapshot as Snapshot
    from drvs.core.model import WorldObject as WorldObject
    from drvs.core.object_types import aruco as aruco
    from drvs.core.object_types import foreground as foreground
    from drvs.core.object_types import hsv as hsv
    from drvs.core.object_types import model_type as model_type
    from drvs.core.object_types import people as people
    from drvs.robot.client import CameraInfo as CameraInfo
    from drvs.robot.client import DetectionResult as DetectionResult
    from drvs.robot.client import DrvsClient as DrvsClient
    from drvs.robot.client import RetryPolicy as RetryPolicy
    from drvs.robot.client import Subscription as Subscription
    from drvs.robot.client import Track as Track
    from drvs.robot.client import Tracking as Tracking
    from drvs.robot.snapshots import snapshot_json as snapshot_json
    from drvs.wire.security import Security as Security

_EXPORTS = {
    "DrvsClient": "drvs.robot.client",
    "RetryPolicy": "drvs.robot.client",
    "DetectionResult": "drvs.robot.client",
    "Subscription": "drvs.robot.client",
    "CameraInfo": "drvs.robot.client",
    "Track": "drvs.robot.client",
    "Tracking": "drvs.robot.client",
    "snapshot_json": "drvs.robot.snapshots",
    "Security": "drvs.wire.security",
    "Snapshot": "drvs.core.model",
    "WorldObject": "drvs.core.model",
    "FusionOptions": "drvs.core.model",
    "Pose2": "drvs.core.model",
    "Detection": "drvs.core.model",
    "DetectionReport": "drvs.core.model",
    "CameraError": "drvs.core.model",
    "DrvsError": "drvs.core.errors",
    "InvalidArgument": "drvs.core.errors",
    "NotFound": "drvs.core.errors",
    "Unavailable": "drvs.core.errors",
    "DeadlineExceeded": "drvs.core.errors",
    "FailedPrecondition": "drvs.core.errors",
    "ResourceExhausted": "drvs.core.errors",
    "PermissionDenied": "drvs.core.errors",
    "Unauthenticated": "drvs.core.errors",
    "hsv": "drvs.core.object_types",
    "aruco": "drvs.core.object_types",
    "people": "drvs.core.object_types",
    "foreground": "drvs.core.object_types",
    "model_type": "drvs.core.object_types",
}

__all__ = ["__version__", *_EXPORTS]


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'drvs' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_EXPORTS])

"""The robot's side of DRVS: a client that asks the server and a listener that receives reports.

    from drvs import DrvsClient

    async with DrvsClient.connect("drvs.example:50051", robot_id="turtle-1") as drvs:
        result = await drvs.detect("hsv_014110130035225200", (0, 0, 5, 5))  # a box, metres
        for d in result.detections:
            print(d.camera_id, d.centroid.x, d.centroid.y)

See DrvsClient (connect, subscribe, detect, cameras), RetryPolicy, and drvs.errors.
"""

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
from drvs.robot.client import (
    CameraInfo,
    Connecting,
    DetectionResult,
    DrvsClient,
    RegionLike,
    RetryPolicy,
    Subscribing,
    Subscription,
)

__all__ = [
    "CameraError",
    "CameraInfo",
    "Connecting",
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
    "RegionLike",
    "ResourceExhausted",
    "RetryPolicy",
    "Subscribing",
    "Subscription",
    "Unauthenticated",
    "Unavailable",
]

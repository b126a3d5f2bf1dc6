"""The robot's side of DRVS: a client that asks the server and a listener that receives reports.

    from drvs import DrvsClient

    async with DrvsClient.connect("drvs.example:50051", robot_id="turtle-1") as drvs:
        result = await drvs.detect("hsv_014110130035225200", (0, 0, 5, 5))  # a box, metres
        for d in result.detections:
            print(d.camera_id, d.centroid.x, d.centroid.y)

Fused delivery: the server merges what the cameras see into world objects and answers on the
robot's own connection (no listener, so it works behind NAT):

        snapshot = await drvs.snapshot("hsv_014110130035225200", (0, 0, 5, 5))
        async for time, objects, missing in drvs.track("hsv_014110130035225200", (0, 0, 5, 5), duration_s=5):
            ...

See DrvsClient (connect, subscribe, detect, snapshot, track, cameras), Snapshot, WorldObject, RetryPolicy,
Security (TLS files and the robot's token),
snapshot_json, and drvs.core.errors.
"""

from drvs.core.errors import (
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
from drvs.core.model import CameraError, Detection, DetectionReport, FusionOptions, Pose2, Snapshot, WorldObject
from drvs.robot.client import (
    CameraInfo,
    Connecting,
    DetectionResult,
    DrvsClient,
    RegionLike,
    RetryPolicy,
    Subscribing,
    Subscription,
    Track,
    Tracking,
)
from drvs.robot.snapshots import snapshot_json, world_object_json
from drvs.wire.security import Security

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
    "FusionOptions",
    "InvalidArgument",
    "NotFound",
    "PermissionDenied",
    "Pose2",
    "RegionLike",
    "ResourceExhausted",
    "RetryPolicy",
    "Security",
    "Snapshot",
    "Subscribing",
    "Subscription",
    "Track",
    "Tracking",
    "Unauthenticated",
    "Unavailable",
    "WorldObject",
    "snapshot_json",
    "world_object_json",
]

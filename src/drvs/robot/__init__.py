"""The robot's side of DRVS: a client that asks the server and a listener that receives reports.

async with DrvsClient("server:50051", robot_id="turtle") as drvs:
    result = await drvs.detect("hsv_014110130035225200", (0, 0, 5, 5))
    for d in result.detections:
        print(d.camera_id, d.centroid.x, d.centroid.y)
"""

from drvs.model import Detection, DetectionReport
from drvs.robot.client import CameraError, CameraInfo, DetectionResult, DrvsClient, Subscription

__all__ = ["CameraError", "CameraInfo", "Detection", "DetectionReport", "DetectionResult", "DrvsClient", "Subscription"]

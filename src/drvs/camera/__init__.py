"""A DRVS camera node: grabs frames, detects objects on request, reports them to robots."""

from drvs.camera.node import CameraNode
from drvs.camera.source import FrameSource, VideoSource

__all__ = ["CameraNode", "FrameSource", "VideoSource"]

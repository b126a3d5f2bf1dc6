"""A DRVS camera node: grabs frames, detects objects on request, reports them to robots."""

from drvs.camera.node import CameraNode
from drvs.camera.source import FrameSource, PushSource, VideoSource

__all__ = ["CameraNode", "FrameSource", "PushSource", "VideoSource"]

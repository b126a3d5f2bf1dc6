"""Drawing on images with sub-pixel precision, and encoding them. Pure logic, shared by the camera's
calibration board view (drvs.camera.aruco), its frame streams and live view (drvs.camera.node,
drvs.camera.liveview) and the simulator's renderers (drvs.sim.scene, drvs.sim.render)."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

_SHIFT = 4  # fillPoly fractional bits: 1/16 pixel


def fill_polygon(image: NDArray[np.uint8], points: NDArray[np.float64], color: int | tuple[int, int, int]) -> None:
    """Fill a polygon given in (fractional) pixels, to 1/16 pixel."""
    pts = np.round(points * (1 << _SHIFT)).astype(np.int32)
    cv2.fillPoly(image, [pts], color, lineType=cv2.LINE_8, shift=_SHIFT)


def encode_jpeg(image: NDArray[np.uint8], quality: int) -> bytes:
    """`image` (BGR) as JPEG at `quality` (0-100)."""
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return bytes(buf)

"""Drawing on images with sub-pixel precision. Pure logic, shared by the camera's calibration board
view (drvs.camera.aruco) and the simulator's renderers (drvs.sim.scene, drvs.sim.render)."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

_SHIFT = 4  # fillPoly fractional bits: 1/16 pixel


def fill_polygon(image: NDArray[np.uint8], points: NDArray[np.float64], color: int | tuple[int, int, int]) -> None:
    """Fill a polygon given in (fractional) pixels, to 1/16 pixel."""
    pts = np.round(points * (1 << _SHIFT)).astype(np.int32)
    cv2.fillPoly(image, [pts], color, lineType=cv2.LINE_8, shift=_SHIFT)

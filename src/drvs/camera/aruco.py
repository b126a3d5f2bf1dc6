"""Automatic calibration from an ArUco grid board lying face up on the floor at a known place.

The board is described as COLSxROWS:MARKER_M:GAP_M (e.g. 4x3:0.15:0.05) in an OpenCV
dictionary; --board-origin is the top-left corner of the printed board as you read it, and
--board-yaw the direction its top edge runs (left to right), counter-clockwise from +x. Every
detected marker gives four floor points; the homography is fitted to them as by hand.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from drvs.camera.calibration import Correspondence
from drvs.core.errors import InvalidArgument
from drvs.core.geometry import Homography
from drvs.core.imaging import fill_polygon

DEFAULT_DICTIONARY = "DICT_4X4_50"


@dataclass(frozen=True)
class BoardSpec:
    cols: int
    rows: int
    marker_m: float
    gap_m: float
    origin: tuple[float, float] = (0.0, 0.0)
    yaw_deg: float = 0.0
    dictionary: str = DEFAULT_DICTIONARY

    @classmethod
    def parse(cls, text: str, origin: tuple[float, float], yaw_deg: float, dictionary: str) -> BoardSpec:
        try:
            grid, marker, gap = text.split(":")
            cols, rows = (int(v) for v in grid.lower().split("x"))
            spec = cls(cols, rows, float(marker), float(gap), origin, float(yaw_deg), dictionary)
        except ValueError:
            raise InvalidArgument(f"--board: {text!r} is not COLSxROWS:MARKER_M:GAP_M, e.g. 4x3:0.15:0.05") from None
        if not (1 <= cols <= 50 and 1 <= rows <= 50 and cols * rows >= 2):
            raise InvalidArgument(f"--board: {cols}x{rows} markers is not a board (2 to 2500 markers)")
        if not (0.01 <= spec.marker_m <= 5 and 0 <= spec.gap_m <= 5):
            raise InvalidArgument("--board: marker size must be 0.01-5 m and the gap 0-5 m")
        if not all(math.isfinite(v) for v in (*origin, yaw_deg)):
            raise InvalidArgument("--board-origin/--board-yaw: must be finite numbers")
        if not hasattr(cv2.aruco, dictionary) or not dictionary.startswith("DICT_"):
            raise InvalidArgument(f"--dictionary: {dictionary!r} is not an OpenCV ArUco dictionary (e.g. DICT_4X4_50)")
        if cols * rows > cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)).bytesList.shape[0]:
            raise InvalidArgument(f"--board: {dictionary} has fewer markers than {cols}x{rows}")
        return spec

    def board(self) -> cv2.aruco.GridBoard:
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.GridBoard((self.cols, self.rows), self.marker_m, self.gap_m, d)

    def to_world(self, board_xy: NDArray[np.float64]) -> NDArray[np.float64]:
        """Board coordinates (x along the top edge, y down the page) to the floor frame."""
        yaw = math.radians(self.yaw_deg)
        along = np.array([math.cos(yaw), math.sin(yaw)])
        down = np.array([math.sin(yaw), -math.cos(yaw)])  # face up: down the page is to the right of the top edge
        return np.asarray(np.asarray(self.origin) + board_xy[:, :1] * along + board_xy[:, 1:2] * down, dtype=np.float64)

    def marker_corners_world(self) -> dict[int, NDArray[np.float64]]:
        board = self.board()
        return {
            int(marker_id): self.to_world(np.asarray(points, dtype=np.float64)[:, :2])
            for marker_id, points in zip(np.asarray(board.getIds()).ravel(), board.getObjPoints(), strict=True)
        }


def find_correspondences(image: NDArray[np.uint8], spec: BoardSpec) -> list[Correspondence]:
    """Every corner of every board marker found in the image, with where it lies on the floor."""
    board = spec.board()
    params = cv2.aruco.DetectorParameters()
    # Sub-pixel corners: the board is small next to the field of view, so corner errors are
    # magnified when the fit is extrapolated across the floor.
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.ArucoDetector(board.getDictionary(), params)
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    corners, ids, _ = detector.detectMarkers(gray)
    world = spec.marker_corners_world()
    found: list[Correspondence] = []
    for marker_corners, marker_id in zip(corners, [] if ids is None else np.asarray(ids).ravel(), strict=True):
        if int(marker_id) not in world:
            continue  # a marker of the dictionary that is not on this board
        for (u, v), (x, y) in zip(np.asarray(marker_corners).reshape(4, 2), world[int(marker_id)], strict=True):
            found.append(Correspondence((float(u), float(v)), (float(x), float(y))))
    if len(found) < 8:
        raise InvalidArgument(
            f"board: found {len(found) // 4} marker(s) of the board in the image; need at least 2 "
            "(is the board in view, lit, and the --dictionary right?)"
        )
    return found


def board_image(spec: BoardSpec, px_per_m: float = 2000.0, margin_m: float = 0.02) -> NDArray[np.uint8]:
    """The board to print, at px_per_m (print it so that markers measure marker_m)."""
    width_m = spec.cols * spec.marker_m + (spec.cols - 1) * spec.gap_m + 2 * margin_m
    height_m = spec.rows * spec.marker_m + (spec.rows - 1) * spec.gap_m + 2 * margin_m
    size = (round(width_m * px_per_m), round(height_m * px_per_m))
    return np.asarray(spec.board().generateImage(size, marginSize=round(margin_m * px_per_m)), dtype=np.uint8)


def render_board_view(
    homography: Homography, image_size: tuple[int, int], spec: BoardSpec, floor_gray: int = 128, marker_px: int = 200
) -> NDArray[np.uint8]:
    """What a camera with this image->floor homography sees of the board on a plain floor (for tests)."""
    width, height = image_size
    to_image = homography.inverse()
    image = np.full((height, width), floor_gray, dtype=np.uint8)
    board = spec.board()
    # White paper under the markers, then each marker warped from its own image.
    pts = np.vstack([np.asarray(p, dtype=np.float64)[:, :2] for p in board.getObjPoints()])
    pad = spec.gap_m + spec.marker_m * 0.25
    x0, y0 = pts.min(axis=0) - pad
    x1, y1 = pts.max(axis=0) + pad
    paper = to_image.apply(spec.to_world(np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])))
    fill_polygon(image, paper, 255)
    src = np.array([[0, 0], [marker_px, 0], [marker_px, marker_px], [0, marker_px]], dtype=np.float32)
    for marker_id, points in zip(np.asarray(board.getIds()).ravel(), board.getObjPoints(), strict=True):
        marker = cv2.aruco.generateImageMarker(board.getDictionary(), int(marker_id), marker_px)
        dst = to_image.apply(spec.to_world(np.asarray(points, dtype=np.float64)[:, :2])).astype(np.float32)
        warp = cv2.getPerspectiveTransform(src, dst)
        cv2.warpPerspective(marker, warp, (width, height), image, borderMode=cv2.BORDER_TRANSPARENT)
    return image

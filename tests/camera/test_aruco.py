"""Calibration from an ArUco board lying on the floor: rendered through a known homography, found, fitted."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from shapely import contains_xy

from drvs.camera.aruco import BoardSpec, find_correspondences, render_board_view
from drvs.camera.calibration import fit_homography
from drvs.core.errors import InvalidArgument
from drvs.core.geometry import FieldOfView, Homography, homography_from_pose
from drvs.core.homography_file import load_homography
from drvs.tools.launch import ManagedProcess

SIZE = (640, 480)
TRUE = homography_from_pose((0.0, 0.0, 2.5), 90.0, 45.0, 60.0, SIZE)


def error_near_board_m(fitted: Homography, spec: BoardSpec, radius_m: float = 2.0) -> float:
    """Largest floor error of the fit, over the field of view within radius_m of the board's centre."""
    fov = FieldOfView.compute(TRUE, SIZE, 8.0)
    corners = np.vstack(list(spec.marker_corners_world().values()))
    centre = corners.mean(axis=0)
    xs, ys = np.meshgrid(np.linspace(-4, 4, 41), np.linspace(0, 10, 51))
    grid = np.column_stack([xs.ravel(), ys.ravel()])
    grid = grid[contains_xy(fov.floor, grid[:, 0], grid[:, 1]) & (np.linalg.norm(grid - centre, axis=1) < radius_m)]
    return float(np.max(np.linalg.norm(fitted.apply(TRUE.inverse().apply(grid)) - grid, axis=1)))


@pytest.mark.parametrize(("origin", "yaw"), [((-0.7, 3.9), 0.0), ((0.6, 3.3), 90.0)])
def test_board_on_the_floor_calibrates_the_camera(origin: tuple[float, float], yaw: float) -> None:
    spec = BoardSpec.parse("6x4:0.2:0.05", origin, yaw, "DICT_4X4_50")
    view = np.asarray(cv2.cvtColor(render_board_view(TRUE, SIZE, spec), cv2.COLOR_GRAY2BGR), dtype=np.uint8)
    points = find_correspondences(view, spec)
    assert len(points) >= 4 * 20  # (nearly) every marker of the board found; far ones may be too foreshortened
    calibration = fit_homography(points, SIZE)
    assert calibration.rms_error_m < 0.015
    assert error_near_board_m(calibration.homography, spec) < 0.03


def test_wrong_dictionary_finds_no_board() -> None:
    spec = BoardSpec.parse("6x4:0.2:0.05", (-0.7, 3.9), 0.0, "DICT_4X4_50")
    view = render_board_view(TRUE, SIZE, spec)
    other = BoardSpec.parse("6x4:0.2:0.05", (-0.7, 3.9), 0.0, "DICT_6X6_250")
    with pytest.raises(InvalidArgument, match=r"found 0 marker\(s\) of the board"):
        find_correspondences(view, other)


@pytest.mark.parametrize(
    ("text", "dictionary", "message"),
    [
        ("6x4", "DICT_4X4_50", "not COLSxROWS"),
        ("6x4:0.2:0.05", "DICT_NOPE", "--dictionary"),
        ("9x9:0.2:0.05", "DICT_4X4_50", "fewer markers"),
    ],
)
def test_bad_board_descriptions(text: str, dictionary: str, message: str) -> None:
    with pytest.raises(InvalidArgument, match=message):
        BoardSpec.parse(text, (0.0, 0.0), 0.0, dictionary)


async def test_calibrate_aruco_and_board_commands(tmp_path: Path) -> None:
    spec = BoardSpec.parse("6x4:0.2:0.05", (-0.7, 3.9), 0.0, "DICT_4X4_50")
    view = tmp_path / "view.png"
    cv2.imwrite(str(view), render_board_view(TRUE, SIZE, spec))
    out = tmp_path / "cam.yaml"
    proc = ManagedProcess.entry_point(
        "cal", "drvs-camera", "calibrate-aruco", "--source", str(view), "--board", "6x4:0.2:0.05",
        "--board-origin", "-0.7,3.9", "--out", str(out),
    )  # fmt: skip
    await proc.start()
    assert await proc.wait(timeout=60) == 0, proc.output()
    assert "24 markers, 96 corners" in proc.output()
    assert error_near_board_m(load_homography(out), spec) < 0.03

    board_png = tmp_path / "board.png"
    proc = ManagedProcess.entry_point(
        "board", "drvs-camera", "aruco-board", "--board", "6x4:0.2:0.05", "--out", str(board_png)
    )
    await proc.start()
    assert await proc.wait(timeout=60) == 0, proc.output()
    printed = cv2.imread(str(board_png), cv2.IMREAD_GRAYSCALE)
    assert printed is not None
    ids = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)).detectMarkers(printed)[1]
    assert ids is not None and sorted(np.asarray(ids).ravel().tolist()) == list(range(24))

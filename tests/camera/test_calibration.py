"""Calibration: a homography fitted from measured points, and the snapshot / calibrate / fov commands."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from drvs.camera.calibration import Correspondence, fit_homography, load_points
from drvs.core.errors import InvalidArgument
from drvs.core.geometry import FieldOfView, homography_from_pose
from drvs.core.homography_file import load_homography
from drvs.sim.scene import RecordedCamera
from drvs.tools.launch import ManagedProcess

SIZE = (640, 480)
TRUE = homography_from_pose((2.0, -1.0, 3.0), 80.0, 40.0, 60.0, SIZE)
PIXELS = np.array(
    [[80, 420], [560, 430], [320, 300], [120, 250], [520, 240], [300, 180], [200, 350], [450, 360]], float
)


def correspondences(pixels: np.ndarray = PIXELS) -> list[Correspondence]:
    return [
        Correspondence((float(u), float(v)), (float(x), float(y)))
        for (u, v), (x, y) in zip(pixels, TRUE.apply(pixels), strict=True)
    ]


def floor_grid_error_m(fitted: np.ndarray) -> float:
    """Largest distance, over a grid of floor points the camera sees, between the fit and the truth."""
    fov = FieldOfView.compute(TRUE, SIZE, 8.0)
    x0, y0, x1, y1 = fov.floor.bounds
    xs, ys = np.meshgrid(np.linspace(x0, x1, 25), np.linspace(y0, y1, 25))
    floor = np.column_stack([xs.ravel(), ys.ravel()])
    from shapely import contains_xy

    floor = floor[contains_xy(fov.floor, floor[:, 0], floor[:, 1])]
    pixels = TRUE.inverse().apply(floor)
    from drvs.core.geometry import Homography

    return float(np.max(np.linalg.norm(Homography.from_values(fitted).apply(pixels) - floor, axis=1)))


def test_synthetic_correspondences_recover_the_homography_within_a_millimetre() -> None:
    calibration = fit_homography(correspondences(), SIZE)
    assert floor_grid_error_m(calibration.homography.matrix) < 0.001
    assert calibration.rms_error_m < 0.001 and all(calibration.inliers)


def test_ransac_drops_a_mismeasured_point() -> None:
    points = correspondences()
    bad = points[3]
    points[3] = Correspondence(bad.image, (bad.world[0] + 0.8, bad.world[1] - 0.5))  # measured 94 cm off
    calibration = fit_homography(points, SIZE)
    assert calibration.inliers[3] is False and sum(calibration.inliers) == 7
    assert calibration.errors_m[3] > 0.5
    assert floor_grid_error_m(calibration.homography.matrix) < 0.001


@pytest.mark.parametrize(
    ("points", "message"),
    [
        (correspondences()[:3], r"at least 4 correspondences are needed, got 3"),
        (
            correspondences(np.array([[100, 400], [200, 350], [300, 300], [400, 250], [500, 200]], float)),
            r"image points are \(nearly\) on one line",
        ),
        ([*correspondences()[:4], correspondences()[0]], r"two image points are the same"),
        ([Correspondence(c.image, (c.world[0], -c.world[1])) for c in correspondences()], r"the layout is mirrored"),
        (
            [*correspondences()[:4], Correspondence((700.0, 10.0), (1.0, 1.0))],
            r"\[4\]\.image .* is outside the 640x480 image",
        ),
    ],
)
def test_degenerate_calibrations_are_refused(points: list[Correspondence], message: str) -> None:
    with pytest.raises(InvalidArgument, match=message):
        fit_homography(points, SIZE)


def test_points_file_errors_name_the_entry(tmp_path: Path) -> None:
    f = tmp_path / "p.yaml"
    f.write_text(yaml.safe_dump([{"image": [1, 2], "world": [1, "x"]}]))
    with pytest.raises(InvalidArgument, match=r"\[0\]\.world must be two finite numbers"):
        load_points(f)
    f.write_text(yaml.safe_dump([{"image": [1, 2]}]))
    with pytest.raises(InvalidArgument, match=r"\[0\] must have exactly the keys image and world"):
        load_points(f)


async def run(*args: str) -> tuple[int, str]:
    proc = await ManagedProcess.entry_point("camera", "drvs-camera", *args).start()
    code = await proc.wait(timeout=60)
    return code, proc.output()


async def test_calibrate_command_writes_a_file_the_camera_reads(tmp_path: Path) -> None:
    points = tmp_path / "points.json"
    points.write_text(json.dumps([{"image": list(c.image), "world": list(c.world)} for c in correspondences()]))
    out = tmp_path / "cam.yaml"
    code, log = await run("calibrate", "--points", str(points), "--image-size", "640,480", "--out", str(out))
    assert code == 0, log
    assert "rms error 0.0 mm" in log and "over 8 of 8 points" in log
    assert floor_grid_error_m(load_homography(out).matrix) < 0.001


async def test_calibrate_command_refuses_too_few_points(tmp_path: Path) -> None:
    points = tmp_path / "points.yaml"
    points.write_text(yaml.safe_dump([{"image": list(c.image), "world": list(c.world)} for c in correspondences()[:3]]))
    code, log = await run("calibrate", "--points", str(points), "--image-size", "640,480", "--out", str(tmp_path / "x"))
    assert code == 2 and "Traceback" not in log and not (tmp_path / "x").exists(), log
    lines = log.splitlines()
    assert any(line.startswith("drvs-camera calibrate: ") and "at least 4 correspondences" in line for line in lines)


@pytest.mark.slow
async def test_snapshot_and_fov_commands(tmp_path: Path, recorded: dict[str, RecordedCamera]) -> None:
    rec = recorded["cam1"]
    png = tmp_path / "snap.png"
    code, log = await run("snapshot", "--source", str(rec.video), "--out", str(png))
    assert code == 0, log
    frame = cv2.imread(str(png))
    assert frame is not None and frame.shape == (480, 640, 3)

    drawn = tmp_path / "fov.png"
    code, log = await run(
        "fov",
        "--homography",
        str(rec.homography_file),
        "--source",
        str(rec.video),
        "--max-range",
        "6",
        "--out",
        str(drawn),
    )
    assert code == 0, log
    expected = FieldOfView.compute(rec.homography, (640, 480), 6.0).floor.area
    assert f"field of view: {expected:.2f} m²" in log
    picture = cv2.imread(str(drawn))
    assert picture is not None and picture.shape == (480, 640, 3)
    assert not np.array_equal(picture, frame)  # the field of view is drawn on it

    code, log = await run(
        "fov", "--homography", str(rec.homography_file), "--image-size", "640,480", "--max-range", "6"
    )
    assert code == 0 and f"{expected:.2f} m²" in log

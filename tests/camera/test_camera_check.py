"""`drvs-camera check`, run as an installer runs it: a real process on a real video file (and a real
OpenCV, also one without contrib: tests/data/cv2_without), printing ok or FAIL per step and exiting
0 only when everything works."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from drvs.detectors import OPENCV_CONTRIB_FIX
from drvs.sim.scene import RecordedCamera
from drvs.tools.launch import ManagedProcess
from tests.helpers import MAX_RANGE, without


async def check(*args: str, env: dict[str, str] | None = None) -> tuple[int, dict[str, str], str]:
    """(exit code, {what: its line} for the step lines, the whole output)."""
    proc = await ManagedProcess.entry_point("check", "drvs-camera", "check", *args, env=env).start()
    try:
        code = await proc.wait(timeout=60)
    finally:
        await proc.stop()
    steps = {}
    for line in proc.lines:
        status, _, rest = line.strip().partition(" ")
        if status in ("ok", "FAIL", "--"):
            steps[rest.strip().split(":", 1)[0]] = line.strip()
    return code, steps, proc.output()


def camera_flags(rec: RecordedCamera, *more: str) -> list[str]:
    return [
        "--id",
        "hall-1",
        "--source",
        str(rec.video),
        "--homography",
        str(rec.homography_file),
        "--max-range",
        MAX_RANGE,
        *more,
    ]


async def test_a_working_camera_checks_ok(recorded: dict[str, RecordedCamera]) -> None:
    rec = recorded["cam1"]
    code, steps, output = await check(*camera_flags(rec))
    assert code == 0, output
    assert steps[f"source {rec.video}"].endswith("read a 640x480 frame"), output
    assert steps[f"homography {rec.homography_file}"].startswith("ok"), output
    assert steps["field of view"].startswith("ok") and "m² of floor within 6 m" in steps["field of view"], output
    for prefix in ("hsv", "aruco", "people", "foreground"):
        assert steps[f"detector {prefix}"] == f"ok    detector {prefix}: ready, serves {prefix}", output
    assert output.rstrip().endswith("everything works"), output
    # --check is the same command.
    proc = await ManagedProcess.entry_point(
        "check", "drvs-camera", "--check", *camera_flags(rec, "--detectors", "hsv")
    ).start()
    assert await proc.wait(timeout=60) == 0 and "ok    detector hsv: ready, serves hsv" in proc.output(), proc.output()


async def test_an_opencv_without_contrib_fails_the_check_naming_the_detectors_and_the_fix(
    recorded: dict[str, RecordedCamera],
) -> None:
    code, steps, output = await check(*camera_flags(recorded["cam1"]), env=without("HOGDescriptor", "aruco"))
    assert code == 1, output
    assert steps["detector hsv"].startswith("ok") and steps["detector foreground"].startswith("ok"), output
    for prefix, attribute in (("people", "HOGDescriptor"), ("aruco", "aruco")):
        line = steps[f"detector {prefix}"]
        assert line.startswith(f"FAIL  detector {prefix}: unavailable (the camera would serve without it): "), line
        assert f"has no {attribute}" in line and line.endswith(f"Fix: {OPENCV_CONTRIB_FIX}"), line
    assert "2 problem(s)" in output, output


async def test_a_source_without_frames_and_a_broken_homography_fail_the_check(
    recorded: dict[str, RecordedCamera], tmp_path: Path
) -> None:
    rec = recorded["cam1"]
    gone = tmp_path / "gone.avi"
    code, steps, output = await check("--id", "c", "--source", str(gone), "--homography", str(rec.homography_file))
    assert code == 1, output
    assert steps[f"source {gone}"].startswith(f"FAIL  source {gone}: no frame: source: '{gone}' is neither"), output
    assert steps["detector hsv"].startswith("--    detector hsv: its backend is here; not built"), output
    assert "1 problem(s)" in output, output

    code, steps, output = await check("--id", "c", "--source", str(rec.video), "--homography", str(rec.video))
    assert code == 1 and steps[f"homography {rec.video}"].startswith("FAIL"), output
    assert "not a text file (expected JSON or YAML)" in steps[f"homography {rec.video}"], output


async def test_an_absent_model_and_a_wrong_background_fail_the_check(
    recorded: dict[str, RecordedCamera], tmp_path: Path
) -> None:
    rec = recorded["cam1"]
    cv2.imwrite(str(tmp_path / "small.png"), np.zeros((240, 320, 3), np.uint8))
    config = {
        "id": "hall-1",
        "source": str(rec.video),
        "homography": str(rec.homography_file),
        "detectors": ["hsv", "foreground", "model"],
        "background": "small.png",
        "models": {"boxes": {"path": "boxes.onnx", "classes": ["box"]}},
    }
    (tmp_path / "cam.yaml").write_text(yaml.safe_dump(config))
    code, steps, output = await check("--config", str(tmp_path / "cam.yaml"))
    assert code == 1, output
    assert steps["detector hsv"].startswith("ok"), output
    assert steps["detector model"] == (
        f"FAIL  detector model: unavailable (the camera would serve without it): models: boxes: "
        f"{tmp_path / 'boxes.onnx'}: no such file"
    ), output
    assert steps["detector foreground"].startswith(
        "FAIL  detector foreground: refused (the camera would not start): "
    ), output
    assert "small.png: 320x240, but the camera's frames are 640x480" in steps["detector foreground"], output


@pytest.mark.parametrize(
    "args", [("--source", "x.avi"), ("--id", "c", "--source", "x.avi", "--homography", "h", "--max-range", "-1")]
)
async def test_settings_the_camera_would_refuse_exit_2(args: tuple[str, ...]) -> None:
    code, steps, output = await check(*args)
    assert code == 2 and not steps and output.startswith("drvs-camera check: "), output

"""A camera whose Python lacks a detector's backend serves the rest: real processes, real OpenCV.

The OpenCV without contrib is the real cv2 with the attributes a plain opencv-python-headless build
lacks deleted at interpreter start (tests/data/cv2_without/sitecustomize.py, first on the camera
process's PYTHONPATH): `cv2.HOGDescriptor` (the people detector) and `cv2.aruco`. The absent model
is a `models:` entry whose file is not there. In each case the camera starts, registers and serves
its other types (hsv finds the floor's yellow discs), says once why the detector is unavailable and
what fixes it, and a robot that asks for the missing type hears FAILED_PRECONDITION naming it."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pytest
import yaml
from drvs_bench.onnx_models import COLOUR_CLASSES, colour_box_model

from drvs.core.errors import FailedPrecondition
from drvs.detectors import OPENCV_CONTRIB_FIX, Backend
from drvs.robot import DrvsClient
from drvs.sim.scene import RecordedCamera
from drvs.tools.launch import ManagedProcess, camera_ready, start_server
from tests.fakes import start_recorded_camera
from tests.helpers import CAM1_REGION, MAX_RANGE, OBJECTS, YELLOW, metrics_port, scrape, without


def test_a_backend_says_what_is_missing_and_what_fixes_it() -> None:
    assert Backend("cv2", "aruco", "ArUco", OPENCV_CONTRIB_FIX).missing() is None
    missing = Backend("cv2", "NoSuchDetector", "a detector", "pip install it").missing()
    assert (
        missing is not None and missing.startswith("a detector is missing: cv2 ") and "has no NoSuchDetector" in missing
    )
    absent = Backend("drvs_no_such_module", "", "a runtime", "pip install it").missing()
    assert absent is not None and "needs the Python module drvs_no_such_module, which does not import" in absent


def assert_found_yellow(detections: Sequence[Any]) -> None:
    yellow = [o for o in OBJECTS if o.filter_def == YELLOW and o.center[0] < 5]
    assert len(detections) == len(yellow), detections
    for d in detections:
        assert min(math.dist(d.centroid_xy, o.center) for o in yellow) < 0.15


async def test_a_camera_without_contrib_opencv_serves_hsv_and_refuses_people_and_aruco_by_name(
    recorded: dict[str, RecordedCamera],
) -> None:
    env = without("HOGDescriptor", "aruco")
    server, address = await start_server()
    camera = None
    try:
        camera = await start_recorded_camera("plain", recorded["cam1"], address, "--metrics-port", "0", env=env)
        await camera.wait_for_line(r"metrics on http://")
        output = camera.output()
        for prefix, attribute in (("people", "HOGDescriptor"), ("aruco", "aruco")):
            lines = [line for line in camera.lines if f"detector {prefix} unavailable" in line]
            assert len(lines) == 1, output  # said once, at start
            assert f"has no {attribute}" in lines[0] and f"Fix: {OPENCV_CONTRIB_FIX}" in lines[0], lines[0]
        assert "Traceback" not in output, output
        gauge = await scrape(metrics_port(camera))
        assert gauge['drvs_detector_available{detector="people"}'] == 0.0
        assert gauge['drvs_detector_available{detector="aruco"}'] == 0.0
        assert gauge['drvs_detector_available{detector="hsv"}'] == 1.0
        async with DrvsClient(address, robot_id="r1") as robot:
            (listed,) = await robot.cameras()
            assert listed.camera_id == "plain" and set(listed.detector_kinds) == {"hsv", "foreground"}
            colour = await robot.detect(YELLOW, CAM1_REGION, timeout_s=20)
            assert colour.camera_ids == ("plain",) and colour.complete
            assert_found_yellow(colour.detections)
            with pytest.raises(
                FailedPrecondition, match=r"filter_def: no camera serves 'people' .*serve foreground, hsv"
            ):
                await robot.detect("people", CAM1_REGION, timeout_s=20)
            with pytest.raises(FailedPrecondition, match=r"filter_def: no camera serves 'aruco'"):
                await robot.detect("aruco_4x4_50", CAM1_REGION, timeout_s=20)
    finally:
        if camera is not None:
            assert await camera.stop() == 0, camera.output()[-3000:]
        await server.stop()


async def test_a_camera_whose_model_file_is_absent_serves_its_other_types_and_models(
    recorded: dict[str, RecordedCamera], tmp_path: Path
) -> None:
    rec = recorded["cam1"]
    server, address = await start_server()
    camera = None
    try:
        config = {
            "id": "nomodel",
            "source": str(rec.video),
            "homography": str(rec.homography_file),
            "server": address,
            "listen": "127.0.0.1:0",
            "max_range_m": float(MAX_RANGE),
            "detectors": ["hsv", "model"],
            "models": {  # paths relative to the config file
                "boxes": {"path": "boxes.onnx", "classes": ["box"]},
                "colours": {"path": str(colour_box_model(tmp_path / "colours.onnx")), "classes": list(COLOUR_CLASSES)},
            },
        }
        (tmp_path / "cam.yaml").write_text(yaml.safe_dump(config))
        camera = await ManagedProcess.entry_point(
            "nomodel", "drvs-camera", "--config", str(tmp_path / "cam.yaml")
        ).start()
        await camera_ready(camera, "nomodel")
        (line,) = [line for line in camera.lines if "unavailable" in line]
        assert f"detector model_boxes unavailable: models: boxes: {tmp_path / 'boxes.onnx'}: no such file" in line
        async with DrvsClient(address, robot_id="r1") as robot:
            (listed,) = await robot.cameras()
            assert set(listed.detector_kinds) == {"hsv", "model_colours"}
            colour = await robot.detect(YELLOW, CAM1_REGION, timeout_s=20)
            assert_found_yellow(colour.detections)
            with pytest.raises(FailedPrecondition, match=r"filter_def: no camera serves 'model_boxes'"):
                await robot.detect("model_boxes_box", CAM1_REGION, timeout_s=20)
    finally:
        if camera is not None:
            assert await camera.stop() == 0, camera.output()[-3000:]
        await server.stop()


async def test_a_camera_that_could_serve_nothing_stops_at_start_saying_why(
    recorded: dict[str, RecordedCamera],
) -> None:
    rec = recorded["cam1"]
    args = ["--id", "nothing", "--source", str(rec.video), "--homography", str(rec.homography_file)]
    camera = ManagedProcess.entry_point(
        "nothing",
        "drvs-camera",
        *args,
        "--server",
        "127.0.0.1:1",
        "--detectors",
        "people",
        env=without("HOGDescriptor"),
    )
    await camera.start()
    try:
        code = await camera.wait(timeout=60)
    finally:
        await camera.stop()
    assert code == 1 and "Traceback" not in camera.output(), camera.output()
    assert (
        "camera nothing cannot start: detectors: camera nothing would serve no object type (people: " in camera.output()
    )

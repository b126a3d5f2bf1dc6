"""The console scripts as a person runs them."""

from __future__ import annotations

import json

import pytest

from drvs.launch import ManagedProcess

from .helpers import CAM1_REGION, OBJECTS, YELLOW, Office, nearest, roi, run_robot


@pytest.mark.office_cameras("cam1")
async def test_robot_detect_json_prints_one_object_per_report(office: Office) -> None:
    code, lines = await run_robot(
        "detect", "--server", office.address, "--filter", YELLOW, "--roi", roi(CAM1_REGION), "--json"
    )
    assert code == 0, lines
    reports = [json.loads(line) for line in lines]
    assert len(reports) == 1
    report = reports[0]
    assert report["camera_id"] == "cam1" and report["final"] is True and report["request_id"]
    assert len(report["detections"]) == len([o for o in OBJECTS if o.filter_def == YELLOW and o.center[0] < 6])
    for d in report["detections"]:
        assert d["filter_def"] == YELLOW and len(d["bounds"]) == 4
        assert nearest(YELLOW, *d["centroid"])[1] < 0.03


@pytest.mark.office_cameras("cam1")
async def test_robot_detect_continuous_json(office: Office) -> None:
    code, lines = await run_robot(
        "detect", "--server", office.address, "--filter", YELLOW, "--roi", roi(CAM1_REGION),
        "--rate", "10", "--duration", "0.5", "--json",
    )  # fmt: skip
    assert code == 0, lines
    reports = [json.loads(line) for line in lines]
    assert [r["sequence"] for r in reports] == list(range(6))
    assert [r["final"] for r in reports] == [False] * 5 + [True]


@pytest.mark.slow
@pytest.mark.timeout(180)  # its own waits (starts, runs, requests) add up to 150 s
async def test_robot_detect_human_output_and_cameras(office: Office) -> None:
    code, lines = await run_robot("detect", "--server", office.address, "--filter", YELLOW, "--roi", roi(CAM1_REGION))
    assert code == 0, lines
    assert "dispatched to cam1" in lines[0]
    assert any("centroid" in line for line in lines)
    code, lines = await run_robot("cameras", "--server", office.address, "--json")
    assert code == 0
    assert sorted(json.loads(line)["camera_id"] for line in lines) == ["cam1", "cam2"]


@pytest.mark.office_cameras()
async def test_robot_bad_filter_is_an_error_naming_the_field(office: Office) -> None:
    code, lines = await run_robot("detect", "--server", office.address, "--filter", "hsv_12", "--roi", "0,0,1,1")
    assert code != 0
    assert any("filter_def" in line for line in lines), lines


@pytest.mark.office_cameras()
async def test_robot_bad_roi_is_an_error(office: Office) -> None:
    code, lines = await run_robot("detect", "--server", office.address, "--filter", YELLOW, "--roi", "1,1,0,0")
    assert code != 0 and any("x_lower" in line for line in lines), lines


async def test_robot_unreachable_server_is_an_error() -> None:
    code, lines = await run_robot("detect", "--server", "127.0.0.1:1", "--filter", YELLOW, "--roi", "0,0,1,1")
    assert code != 0 and any("127.0.0.1:1" in line for line in lines), lines


@pytest.mark.office_cameras()
async def test_camera_with_missing_source_exits_with_an_error(tmp_path: object, office: Office) -> None:
    rec = office.recorded["cam1"]
    proc = ManagedProcess.entry_point(
        "bad-cam", "drvs-camera", "--id", "bad", "--source", "/nonexistent.avi",
        "--homography", str(rec.homography_file), "--server", office.address,
    )  # fmt: skip
    await proc.start()
    assert await proc.wait(timeout=30) != 0
    assert "nonexistent.avi" in proc.output()


@pytest.mark.office_cameras()
async def test_camera_with_bad_homography_file_exits_with_an_error(tmp_path: object, office: Office) -> None:
    from pathlib import Path

    bad = Path(str(tmp_path)) / "h.json"
    bad.write_text('{"homography": [[1, 0, 0], [0, 1, 0]]}')
    proc = ManagedProcess.entry_point(
        "bad-cam", "drvs-camera", "--id", "bad", "--source", str(office.recorded["cam1"].video),
        "--homography", str(bad), "--server", office.address,
    )  # fmt: skip
    await proc.start()
    assert await proc.wait(timeout=30) != 0
    assert "homography" in proc.output()

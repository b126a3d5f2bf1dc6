"""The console scripts as a person runs them."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import pytest

from drvs.tools.launch import ManagedProcess
from tests.helpers import CAM1_SEEN, OBJECTS, YELLOW, Office, nearest, roi, run_robot


def assert_refused(code: int, output: str, message: str, status: int = 2) -> None:
    """Bad input: exactly the documented exit code (2 unless said), no traceback, and the message
    itself as a line of its own (`drvs-robot: filter_def: ...`), not a substring a traceback has too."""
    assert code == status, (code, output)
    assert "Traceback" not in output, output
    assert any(line.strip().startswith(message) for line in output.splitlines()), (message, output)


@pytest.mark.office_cameras("cam1")
async def test_robot_detect_json_prints_one_object_per_report(office: Office) -> None:
    code, lines = await run_robot(
        "detect", "--server", office.address, "--filter", YELLOW, "--roi", roi(CAM1_SEEN), "--json"
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
        "detect", "--server", office.address, "--filter", YELLOW, "--roi", roi(CAM1_SEEN),
        "--rate", "10", "--duration", "0.5", "--json",
    )  # fmt: skip
    assert code == 0, lines
    reports = [json.loads(line) for line in lines]
    assert [r["sequence"] for r in reports] == list(range(6))
    assert [r["final"] for r in reports] == [False] * 5 + [True]


@pytest.mark.slow
@pytest.mark.timeout(180)  # its own waits (starts, runs, requests) add up to 150 s
async def test_robot_detect_human_output_and_cameras(office: Office) -> None:
    code, lines = await run_robot("detect", "--server", office.address, "--filter", YELLOW, "--roi", roi(CAM1_SEEN))
    assert code == 0, lines
    assert "dispatched to cam1" in lines[0]
    assert any("centroid" in line for line in lines)
    code, lines = await run_robot("cameras", "--server", office.address, "--json")
    assert code == 0
    assert sorted(json.loads(line)["camera_id"] for line in lines) == ["cam1", "cam2"]


@pytest.mark.office_cameras()
async def test_robot_bad_filter_is_an_error_naming_the_field(office: Office) -> None:
    code, lines = await run_robot("detect", "--server", office.address, "--filter", "hsv_12", "--roi", "0,0,1,1")
    assert_refused(code, "\n".join(lines), "drvs-robot: filter_def: 'hsv_12' is not 'hsv_' followed by 18 digits")


@pytest.mark.office_cameras()
async def test_robot_bad_roi_is_an_error(office: Office) -> None:
    code, lines = await run_robot("detect", "--server", office.address, "--filter", YELLOW, "--roi", "1,1,0,0")
    assert_refused(code, "\n".join(lines), "drvs-robot: region.box: x_lower 1 must be less than x_upper 0")


async def test_robot_unreachable_server_is_an_error() -> None:
    code, lines = await run_robot("detect", "--server", "127.0.0.1:1", "--filter", YELLOW, "--roi", "0,0,1,1")
    assert_refused(code, "\n".join(lines), "drvs-robot: server 127.0.0.1:1: ")


@pytest.mark.office_cameras()
async def test_camera_with_missing_source_exits_with_an_error(tmp_path: object, office: Office) -> None:
    rec = office.recorded["cam1"]
    proc = ManagedProcess.entry_point(
        "bad-cam", "drvs-camera", "--id", "bad", "--source", "/nonexistent.avi",
        "--homography", str(rec.homography_file), "--server", office.address,
    )  # fmt: skip
    await proc.start()
    # Found only at start, so exit 1 and a log line (docs/validation.md), still no traceback.
    message = "camera bad cannot start: source: '/nonexistent.avi' is neither a device index"
    code = await proc.wait(timeout=30)
    assert code == 1 and "Traceback" not in proc.output(), proc.output()
    assert any(message in line for line in proc.lines), proc.output()


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
    code = await proc.wait(timeout=30)
    assert_refused(code, proc.output(), f"drvs-camera: error: homography file {bad}: 'homography' must be a 3x3")


@pytest.mark.parametrize(
    ("command", "args", "message"),
    [
        ("drvs-server", ["--allow-callback", "bogus"], "drvs-server: error: --allow-callback: 'bogus' is not"),
        ("drvs-server", ["--metrics-port", "abc"], "drvs-server: error: --metrics-port: 'abc' is not host:port"),
        ("drvs-server", ["--no-such-flag"], "drvs-server: error: unrecognized arguments: --no-such-flag"),
        ("drvs-server", ["--foxglove", "here"], "drvs-server: error: --foxglove: 'here' is not host:port"),
        ("drvs-server", ["--foxglove", "0", "--floor-plan", "/nonexistent.yaml"],
         "drvs-server: error: --floor-plan /nonexistent.yaml: No such file or directory"),
        ("drvs-server", ["--floor-plan", "/nonexistent.yaml"],
         "drvs-server: error: --floor-plan: only drawn in a live view or a recording (--foxglove, --record)"),
        ("drvs-server", ["--foxglove", "0", "--foxglove-token", "short"],
         "drvs-server: error: --foxglove-token: at least 16 printable characters"),
        ("drvs-server", ["--record", "x.mcap", "--foxglove-token", "0123456789abcdef"],
         "drvs-server: error: --foxglove-token: only with a live view (--foxglove)"),
        ("drvs-server", ["--record", "x.mcap", "--record-max-rate", "0"],
         "drvs-server: error: --record-max-rate: 0 is not a rate above 0 (MiB a second)"),
        ("drvs-office", ["--foxglove", "70000"], "drvs-office: --foxglove: port 70000 is out of range"),
        ("drvs-camera", ["--id", "c", "--source", "0", "--homography", "/nonexistent.json", "--server", "127.0.0.1:1"],
         "drvs-camera: error: homography file /nonexistent.json: No such file or directory"),
        ("drvs-camera", ["calibrate", "--points", "p.json", "--image-size", "abc", "--out", "h.json"],
         "drvs-camera calibrate: --image-size: expected W,H in pixels"),
        ("drvs-robot", ["detect", "--server", "nonsense", "--filter", YELLOW, "--roi", "0,0,1,1"],
         "drvs-robot: server: 'nonsense' is not host:port"),
        ("drvs-office", ["--kill-camera", "nonsense"], "drvs-office: --kill-camera: 'nonsense' is not ID@SECONDS"),
        ("drvs-office", ["--scenario", "/nonexistent.yaml"], "drvs-office: scenario /nonexistent.yaml: No such file"),
        ("drvs-sim", ["world", "--no-such-flag"], "drvs-sim: error: unrecognized arguments: --no-such-flag"),
        ("drvs-bench", ["paper", "--requests", "-5"], "drvs-bench paper: --requests, --rounds, --people-requests"),
        ("drvs-bench", ["load", "--robots", "-1"], "drvs-bench load: --robots, --workers, --repeat"),
        ("drvs-certs", ["--days", "0"], "drvs-certs: days: 0 must be from 1 to 3650"),
        ("drvs-certs", ["--role", "boss"], "drvs-certs: role: 'boss' must be server, camera, robot"),
    ],
)  # fmt: skip
async def test_every_cli_refuses_bad_input_with_exit_2_and_no_traceback(
    tmp_path: Path, command: str, args: list[str], message: str
) -> None:
    """Bad flags are refused before anything starts: exit code 2 (argparse's), the message naming
    the flag on a line of its own, and never a traceback. Nothing is written to --out."""
    out = tmp_path / "out"
    if command in ("drvs-office", "drvs-bench", "drvs-certs"):
        args = [*args, "--out", str(out)]
    if command == "drvs-certs":
        proc = ManagedProcess(
            "certs", [sys.executable, "-c", "from drvs.tools.certs import main; raise SystemExit(main())", *args]
        )
    else:
        proc = ManagedProcess.entry_point("bad", command, *args)
    await proc.start()
    assert_refused(await proc.wait(timeout=60), proc.output(), message)
    assert not out.exists() or not any(out.iterdir())


@pytest.mark.parametrize("command", [["drvs-office"], ["drvs-certs"], ["drvs-bench", "ros2"]])
async def test_an_out_folder_under_a_file_is_refused_before_anything_runs(tmp_path: Path, command: list[str]) -> None:
    """The tools that write a folder (drvs-office ended in a NotADirectoryError traceback): --out
    under a file is refused at once, exit 2, saying which path is not a folder; the file stays."""
    afile = tmp_path / "afile"
    afile.write_text("kept")
    proc = ManagedProcess.entry_point("out", command[0], *command[1:], "--out", str(afile / "out"))
    await proc.start()
    label = " ".join(command)
    assert_refused(
        await proc.wait(timeout=60), proc.output(), f"{label}: --out {afile / 'out'}: {afile} is not a folder"
    )
    assert afile.read_text() == "kept" and os.listdir(tmp_path) == ["afile"]

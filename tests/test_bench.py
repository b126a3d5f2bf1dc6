"""A smoke run of the benchmarks: they run end to end and write what they promise (no timing asserted)."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import cv2
import pytest
from drvs_bench.common import record_scene
from drvs_bench.paper import check_drvs, check_stream, run_mode
from drvs_bench.stats import QUICK_ROUNDS, WorkMismatch

from drvs.launch import ManagedProcess, start_camera, start_server


@pytest.mark.timeout(480)  # 24 runs, each a process of its own: a minute alone, more on a loaded machine
async def test_paper_benchmark_smoke(tmp_path: Path) -> None:
    """--quick's three interleaved rounds (of 15 requests here), every mode and floor, checked work."""
    proc = ManagedProcess.entry_point(
        "bench", "drvs-bench", "paper", "--quick", "--requests", "15", "--out", str(tmp_path)
    )
    await proc.start()
    assert await proc.wait(timeout=420) == 0, proc.output()
    result = json.loads((tmp_path / "paper.json").read_text())
    assert result["rounds"] == QUICK_ROUNDS == 3
    assert set(result["modes"]) == {"drvs", "drvs_boxes", "drvs_boxes_moving", "raw", "jpeg"}
    for mode in result["modes"].values():
        assert mode["bytes"] > 0 and mode["cpu_s"] > 0 and mode["bytes_timeline"]
        # Wire bytes are the payload plus 66 B of headers a segment, in every run.
        runs = zip(mode["bytes_runs"], mode["payload_bytes_runs"], mode["segments_runs"], strict=True)
        assert all(wire == payload + 66 * segments for wire, payload, segments in runs)
        assert len(mode["bytes_runs"]) == 3 and mode["bytes_spread"][0] <= mode["bytes"] <= mode["bytes_spread"][1]
        cores = os.cpu_count() or 1
        assert 0 < mode["robot_cpu_cores"] < cores and 0 < mode["machine_cpu_cores"] <= cores + 0.1  # 10 ms ticks
    for name in ("drvs_boxes", "drvs_boxes_moving"):
        boxes = result["modes"][name]
        assert boxes["requests"] == boxes["requests_delivered"] == 15 and boxes["reports"] == 30, name
        assert boxes["missing_finals"] == boxes["error_reports"] == boxes["busy_reports"] == 0, name
        assert boxes["reports_per_request"] == {"2": 15}, name
    # Three yellow objects seen by two cameras in every request, and in every frame of the streams.
    assert result["modes"]["drvs_boxes"]["detections_per_request"] == {"3": 15}
    for name in ("raw", "jpeg"):
        stream = result["modes"][name]
        assert stream["frames"] == stream["frames_analysed"] > 0
        assert [set(c["detections_per_frame"]) for c in stream["per_camera"]] == [{"2"}, {"1"}]
    # The moving variant's region and filter change: the detections found vary from request to request.
    assert len(result["modes"]["drvs_boxes_moving"]["detections_per_request"]) > 1
    for key in ("bandwidth_ratio_raw", "bandwidth_ratio_jpeg", "robot_cpu_ratio", "bandwidth_ratio_raw_moving"):
        assert result[key] > 1, key  # streaming video always costs the robot more than DRVS
        assert result[f"{key}_median"] == result[key] and len(result[f"{key}_runs"]) == 3, key
        lo, hi = result[f"{key}_spread"]
        assert lo <= result[key] <= hi, key
    # Headers weigh far more on DRVS's small messages than on a stream's full segments.
    assert result["bandwidth_ratio_raw_payload"] > result["bandwidth_ratio_raw"]
    assert set(result["targets"]) == {"bandwidth_ratio_raw", "bandwidth_ratio_jpeg", "robot_cpu_ratio"}
    for target in result["targets"].values():
        assert target["verdict"] in ("met", "missed", "spread crosses target")
    # The floors ran: DRVS's message flow in bare grpc.aio, and an idle loop at the same rate.
    for key in ("robot_cpu_ratio_at_bare_path", "robot_cpu_over_bare_path", "robot_cpu_ratio_at_idle"):
        assert result[key] > 0, key
    assert result["robot_cpu_bare_path"]["last_report_ms_p50"] > 0
    assert {"cpu_s", "machine_cpu_cores", "cameras_cpu_s / server_cpu_s"} <= set(result["cpu"])
    for png in ("bandwidth.png", "cpu.png"):
        image = cv2.imread(str(tmp_path / png))
        assert image is not None and image.shape[0] > 200


def _drvs_run(requests: int, **changes: Any) -> dict[str, Any]:
    """A DRVS mode's outcome as the robot process reports it, with every request delivered."""
    run: dict[str, Any] = {
        "requests": requests,
        "requests_delivered": requests,
        "reports": 2 * requests,
        "error_reports": 0,
        "busy_reports": 0,
        "refused_requests": 0,
        "missing_finals": 0,
        "detections": 3 * requests,
    }
    run.update(changes)
    return run


@pytest.mark.parametrize(
    ("changes", "named"),
    [
        ({"requests_delivered": 9, "reports": 19, "missing_finals": 1}, "reports: expected 20, got 19"),
        ({"requests_delivered": 9, "error_reports": 1, "busy_reports": 1}, "busy_reports: expected 0, got 1"),
        ({"requests_delivered": 9, "refused_requests": 1, "reports": 18}, "refused_requests: expected 0, got 1"),
        ({"detections": 29}, "detections: expected 30, got 29"),
    ],
)
def test_paper_work_check_fires_when_drvs_work_is_missing(changes: dict[str, Any], named: str) -> None:
    check_drvs("drvs_boxes", _drvs_run(10), 10, 2, 3)  # the work as it should be: passes
    with pytest.raises(WorkMismatch, match=named):
        check_drvs("drvs_boxes", _drvs_run(10, **changes), 10, 2, 3)


def test_paper_work_check_fires_when_stream_work_is_missing() -> None:
    def camera(received: int, analysed: int, detections: int) -> dict[str, Any]:
        return {"frames_received": received, "frames_analysed": analysed, "detections": detections}

    check_stream("raw", {"per_camera": [camera(20, 20, 40), camera(20, 20, 20)]}, [2, 1])
    with pytest.raises(WorkMismatch, match=r"camera 0.*frames_analysed: expected 20, got 19"):
        check_stream("raw", {"per_camera": [camera(20, 19, 38), camera(20, 20, 20)]}, [2, 1])
    # A detection count that lost an update (two cameras adding at once) is caught.
    with pytest.raises(WorkMismatch, match=r"camera 1.*detections: expected 20, got 19"):
        check_stream("raw", {"per_camera": [camera(20, 20, 40), camera(20, 20, 19)]}, [2, 1])
    with pytest.raises(WorkMismatch, match="camera 1: no frame received"):
        check_stream("jpeg", {"per_camera": [camera(20, 20, 40), camera(0, 0, 0)]}, [2, 1])


@pytest.mark.timeout(240)
async def test_paper_work_check_fires_on_a_real_run_with_a_camera_missing(tmp_path: Path) -> None:
    """Two cameras expected, one running: every request gets one report, and the check refuses the run."""
    scene = record_scene(tmp_path, frames=10)
    procs: list[ManagedProcess] = []
    try:
        server, address = await start_server()
        procs.append(server)
        rec = scene["cam1"]
        procs.append(await start_camera("cam1", rec.video, rec.homography_file, address, "--max-range", "6"))
        cameras = {cid: ("127.0.0.1:1", r.homography_file) for cid, r in scene.items()}  # cam2 never started
        run = await run_mode("drvs_boxes", address, cameras, 10, 30.0)
    finally:
        for proc in reversed(procs):
            await proc.stop()
    assert run["reports_per_request"] == {"1": 10} and run["requests_delivered"] == 0
    assert run["bytes"] > run["payload_bytes"] > 0
    with pytest.raises(WorkMismatch, match="requests_delivered: expected 10, got 0"):
        check_drvs("drvs_boxes", run, 10, 2, None)


async def test_service_benchmark_smoke(tmp_path: Path) -> None:
    proc = ManagedProcess.entry_point("bench", "drvs-bench", "service", "--quick", "--out", str(tmp_path))
    await proc.start()
    assert await proc.wait(timeout=400) == 0, proc.output()
    result = json.loads((tmp_path / "service.json").read_text())
    for key in (
        "latency_p50_over_floor",
        "routing_over_echo",
        "bare_proxy_over_echo",
        "routing_over_bare_proxy",
        "lookup_10k_over_100",
        "camera_cpu_200_over_20",
        "server_peak_rss_bytes_2000_cameras",
        "camera_peak_rss_bytes",
        "robot_client_peak_rss_bytes",
    ):
        assert result[key] > 0, key
    assert result["latency"]["30"]["missing"] == 0 and result["routing"]["errors"] == 0
    assert cv2.imread(str(tmp_path / "latency.png")) is not None


async def test_load_benchmark_smoke(tmp_path: Path) -> None:
    proc = ManagedProcess.entry_point("bench", "drvs-bench", "load", "--quick", "--out", str(tmp_path))
    await proc.start()
    assert await proc.wait(timeout=240) == 0, proc.output()
    result = json.loads((tmp_path / "load.json").read_text())
    assert (result["robots"], result["workers"], result["cameras"], result["rate_hz"]) == (10, 2, 3, 30)
    # Ten robots at 30 Hz for a 2 s warm-up and 10 s, every request over all three cameras.
    assert result["requests"] == 3600 and result["reports_expected"] == 10800
    assert 0 < result["reports_received"] <= result["reports_expected"]
    assert result["reports_lost"] == result["reports_expected"] - result["reports_received"]
    assert 0 < result["latency_p50_ms"] <= result["latency_p99_ms"] <= 1000 * result["report_timeout_s"]
    for key in ("server_rss_growth", "camera_rss_growth"):
        assert -0.5 < result[key] < 0.5, key  # a ratio, not bytes
    assert result["server_rss_start_bytes"] > 10 * 2**20 and len(result["camera_rss_start_bytes"]) == 3
    assert len(result["timeline"]) == 12 and set(result["targets"]) == {"no_report_lost", "rss_growth_under_10_percent"}
    assert cv2.imread(str(tmp_path / "load.png")) is not None

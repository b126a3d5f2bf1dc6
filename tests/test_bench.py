"""A smoke run of the benchmarks: they run end to end and write what they promise (no timing asserted)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2

from drvs.launch import ManagedProcess


async def test_paper_benchmark_smoke(tmp_path: Path) -> None:
    proc = ManagedProcess.entry_point("bench", "drvs-bench", "paper", "--requests", "15", "--out", str(tmp_path))
    await proc.start()
    assert await proc.wait(timeout=240) == 0, proc.output()
    result = json.loads((tmp_path / "paper.json").read_text())
    assert set(result["modes"]) == {"drvs", "drvs_boxes", "raw", "jpeg"}
    for mode in result["modes"].values():
        assert mode["bytes"] > 0 and mode["cpu_s"] > 0 and mode["bytes_timeline"]
    boxes = result["modes"]["drvs_boxes"]
    assert boxes["requests"] == 15 and boxes["missing_finals"] == 0 and boxes["reports"] == 30
    assert boxes["detections"] == 45  # three objects seen by two cameras, every request
    assert result["modes"]["raw"]["frames"] > 0 and result["modes"]["raw"]["detections"] > 0
    for key in ("bandwidth_ratio_raw", "bandwidth_ratio_jpeg", "robot_cpu_ratio"):
        assert result[key] > 1, key  # streaming video always costs the robot more than DRVS
    # The floors ran: DRVS's message flow in bare grpc.aio, and an idle loop at the same rate.
    for key in ("robot_cpu_ratio_at_bare_path", "robot_cpu_over_bare_path", "robot_cpu_ratio_at_idle"):
        assert result[key] > 0, key
    assert result["robot_cpu_bare_path"]["last_report_ms_p50"] > 0
    for png in ("bandwidth.png", "cpu.png"):
        image = cv2.imread(str(tmp_path / png))
        assert image is not None and image.shape[0] > 200


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

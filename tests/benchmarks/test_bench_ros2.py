"""drvs-bench ros2 --quick end to end: the bridge's publishing half and a subscriber process on
loopback Cyclone; every snapshot reaches the subscriber, the figures and verdicts are written, and
the DDS floor (the same snapshots' bytes written with no bridge code) is measured in the round.
No timing is asserted: the targets are the benchmark's verdicts, not tests; on a DDS domain of its own,
it runs beside other tests (not marked `bench`)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from drvs_bench.cli import main


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_ros2_bench_quick_writes_its_figures_and_verdicts(tmp_path: Path) -> None:
    assert main(["ros2", "--quick", "--rounds", "1", "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "ros2.json").read_text())
    assert (tmp_path / "ros2.png").is_file() and result["rounds"] == 1 and result["objects"] == 20
    (run,) = result["runs"]
    assert run["snapshots"] == 150 and 0 <= run["lost"] <= 1  # at most 1 % lost (else WorkMismatch, exit 1)
    others = run["other_topics_taken"]  # the subscriber reads every topic, so every one is made
    assert set(others) == {"/drvs/obstacles", "/drvs/tracks", "/drvs/markers", "/diagnostics"}
    assert min(others.values()) > 0 and run["publish_thread_cpu_ms_p50"] <= run["publish_thread_cpu_ms_p99"]
    assert 0 < run["latency_p50_ms"] <= run["latency_p99_ms"] <= run["latency_max_ms"]
    # The bridge's share (call start to Cyclone's write of /drvs/objects) is a part of the latency.
    assert 0 < run["objects_written_ms_p50"] <= run["objects_written_ms_p99"] <= run["latency_max_ms"]
    assert run["cpu_ms_per_snapshot"] > 0 and run["publish_thread_cpu_ms_p50"] > 0
    # The DDS floor (the same snapshots' bytes written with no bridge code) ran in the same round.
    assert run["dds_floor_lost"] <= 1 and run["first"] == "bridge"
    assert run["dds_floor_cpu_ms_per_snapshot"] > 0 and run["dds_floor_latency_p99_ms"] > 0
    assert run["cpu_over_dds_floor"] == pytest.approx(run["cpu_ms_per_snapshot"] / run["dds_floor_cpu_ms_per_snapshot"])
    assert run["cpu_ms_beyond_dds_floor"] == pytest.approx(
        run["cpu_ms_per_snapshot"] - run["dds_floor_cpu_ms_per_snapshot"]
    )
    # The encoding alone: back to back before the clock, and paced (the publish call's thread CPU less
    # the floor's, the same writes with nothing to encode), and the one over the other.
    assert run["encode_back_to_back_ms_p50"] > 0
    assert run["encode_paced_ms_p50"] == pytest.approx(
        run["publish_thread_cpu_ms_p50"] - run["dds_floor_thread_cpu_ms_p50"]
    )
    assert run["encode_paced_over_back_to_back"] == pytest.approx(
        run["encode_paced_ms_p50"] / run["encode_back_to_back_ms_p50"]
    )
    for key in ("latency_p99_ms", "cpu_ms_per_snapshot", "dds_floor_cpu_ms_per_snapshot", "cpu_over_dds_floor",
                "encode_paced_over_back_to_back"):  # fmt: skip
        assert result[f"{key}_spread"] == [run[key], run[key]]
    for key in ("latency_p99_ms", "cpu_ms_per_snapshot"):
        assert result["targets"][key]["verdict"] in ("met", "missed", "spread crosses target")


def test_ros2_bench_refuses_zero_rounds(tmp_path: Path) -> None:
    assert main(["ros2", "--rounds", "-1", "--out", str(tmp_path)]) == 2
    assert not (tmp_path / "ros2.json").exists()

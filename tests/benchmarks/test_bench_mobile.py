"""drvs-bench mobile: a smoke run checks its keys, its verdict and that pose updates never rebuilt
the static index; bad flags are refused with exit 2. Marked `bench` (run alone, after the rest of the
suite): the runs whose checks read timing (lookups at 2 kHz against pose updates, staleness under
the pose lease, snapshots in a fail-over's window, servers at saturation); the others run beside
other tests."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest
from drvs_bench.cli import main

#: Debian's etcd-server, which `./run test` installs as root (as CI runs it).
NEEDS_ETCD = pytest.mark.skipif(
    shutil.which("etcd") is None, reason="etcd is not installed (./run test installs it as root)"
)

#: Interleaved rounds in the cluster throughput smoke run (--rounds): two instead of --quick's three.
CLUSTER_SMOKE_ROUNDS = 2


@pytest.mark.bench
@pytest.mark.slow
def test_mobile_routing_smoke(tmp_path: Path) -> None:
    assert (
        main(["mobile", "--quick", "--parts", "routing", "--rounds", "2", "--lookups", "500", "--out", str(tmp_path)])
        == 0
    )
    result = json.loads((tmp_path / "mobile.json").read_text())
    assert result["static_index_rebuilt_by_pose_updates"] is False
    assert len(result["runs"]) == 2 and (tmp_path / "mobile.png").is_file()
    for run in result["runs"]:
        # 100 cameras at 5 Hz for 500 lookups at 2 kHz (0.25 s): every camera updated at least once.
        assert run["mobile"]["pose_updates"] >= 100 and run["fixed"]["pose_updates"] == 0
        assert run["mobile"]["lookups"] == run["fixed"]["lookups"] == 500
    assert result["lookup_p99_mobile_over_fixed_spread"][0] > 0
    assert result["targets"]["lookup_p99_mobile_over_fixed"]["verdict"] in ("met", "missed", "spread crosses target")


def test_mobile_accuracy_by_pose_error(tmp_path: Path) -> None:
    """The accuracy part on real rendered frames: with the true pose the still disc lands within
    3 cm; a pose 100 ms late puts it about speed x 100 ms off (5 cm at 0.5 m/s, 10 cm at 1 m/s),
    and heading noise of 2° costs more than 1°."""
    assert main(["mobile", "--quick", "--parts", "accuracy", "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "mobile.json").read_text())
    assert result["targets"]["accuracy_true_pose_error_cm_p95"]["verdict"] == "met"
    for speed, data in result["accuracy"]["speeds"].items():
        settings = data["settings"]
        assert data["frames_with_the_disc"] >= 20 and settings["true pose"]["error_cm_p95"] < 3.0
        late = settings["late 100 ms"]["error_cm_median"]
        assert late == pytest.approx(float(speed) * 10, abs=1.5), (speed, late)
        assert settings["heading noise 2°"]["error_cm_median"] > settings["heading noise 1°"]["error_cm_median"]
    assert (tmp_path / "mobile_accuracy.png").is_file() and not (tmp_path / "mobile.png").exists()


@pytest.mark.bench
@pytest.mark.slow
def test_mobile_staleness_smoke(tmp_path: Path) -> None:
    """The staleness part with a real server process: the server holds poses the robot pushed, and
    the one it routes by is younger than the pose lease (1 s), past which it would not route at all.
    (How young is the benchmark's figure, not this test's.)"""
    assert main(["mobile", "--quick", "--parts", "staleness", "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "mobile.json").read_text())
    for data in result["staleness"]["speeds"].values():
        assert min(data["samples"]) >= 20
        assert 0 < data["staleness_ms_p50"] <= data["staleness_ms_p95"] < 1000


@pytest.mark.parametrize(
    "args", [["--parts", "accuracy,nonsense"], ["--parts", ""], ["--rounds", "-1"], ["--lookups", "-5"]]
)
def test_mobile_benchmark_refuses_bad_flags(args: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["mobile", *args]) == 2
    assert "drvs-bench mobile: " in capsys.readouterr().err


@NEEDS_ETCD
def test_cluster_propagation_smoke(tmp_path: Path) -> None:
    """drvs-bench cluster: a real etcd and two servers; every registration through A reached B's
    routing index, and the published figures are what the delays say."""
    assert main(["cluster", "--parts", "propagation", "--registrations", "10", "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "cluster.json").read_text())["propagation"]
    assert result["registrations"] == len(result["delays_ms"]) == 10
    assert 0 < result["propagation_ms_p50"] <= result["propagation_ms_p99"] == max(result["delays_ms"])
    assert result["etcd_cpu_s"] >= 0 and (tmp_path / "cluster.png").is_file()
    assert main(["cluster", "--parts", "nonsense"]) == 2 and main(["cluster", "--rounds", "-1"]) == 2
    for bad in ("0", "1,x", "2,2", ""):
        assert main(["cluster", "--parts", "throughput", "--workers-list", bad]) == 2


@NEEDS_ETCD
def test_cluster_writes_smoke(tmp_path: Path) -> None:
    """drvs-bench cluster --parts writes: what a fleet writes to etcd, per operation and per camera
    and second, in its JSON; heartbeats write no history, registrations and poses do."""
    assert main(["cluster", "--quick", "--parts", "writes", "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "cluster.json").read_text())["writes"]
    ops = result["per_operation"]
    assert ops["registration"]["history_bytes"] > 300 and ops["pose_update"]["history_bytes"] > 50
    assert ops["heartbeat"]["history_bytes"] == 0 < ops["heartbeat"]["bytes_sent_to_etcd"]
    per_s = result["per_camera_per_s"]
    assert 0 < per_s["static"]["bytes_sent_to_etcd"] < per_s["mobile"]["bytes_sent_to_etcd"]


@pytest.mark.bench
@pytest.mark.slow
@NEEDS_ETCD
def test_cluster_failover_smoke(tmp_path: Path) -> None:
    """drvs-bench cluster --parts failover: a round kills the robot's server mid-track; the track
    resumed once through the other, with snapshots before and after, and the gap is published."""
    assert main(["cluster", "--parts", "failover", "--rounds", "1", "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "cluster.json").read_text())["failover"]
    assert result["rounds"] == 1 and len(result["gaps_ms"]) == 1 and result["gaps_ms"][0] > 0
    assert result["snapshots_before_kill"][0] >= 20 and result["snapshots_after_kill"][0] > 0


@pytest.mark.bench
@pytest.mark.slow
@pytest.mark.timeout(300)  # 11 load windows and two etcds: over a minute alone, more when loaded
@NEEDS_ETCD
def test_cluster_throughput_smoke(tmp_path: Path) -> None:
    """drvs-bench cluster --parts throughput: 1000 cameras registered through A are routed by both
    servers; every run completes without an error, and the ratio is the rounds' own. drvs-server
    --workers 1 and 2 (--quick's list): every worker served, the scaling ratio is each round's own,
    and the cores, the harness's size and the plot are there. Two interleaved rounds (--rounds),
    not --quick's three: two are enough to check that each ratio is its round's own."""
    rounds = ["--rounds", str(CLUSTER_SMOKE_ROUNDS)]
    assert main(["cluster", "--quick", "--parts", "throughput", *rounds, "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "cluster.json").read_text())["throughput"]
    assert result["cameras"] == 1000 and len(result["two_over_one_runs"]) == result["rounds"] == CLUSTER_SMOKE_ROUNDS
    assert all(r > 0 for r in result["rps_one_server_runs"] + result["rps_two_servers_runs"])
    ratios = [t / o for t, o in zip(result["rps_two_servers_runs"], result["rps_one_server_runs"], strict=True)]
    assert result["two_over_one_runs"] == pytest.approx(ratios)
    workers = json.loads((tmp_path / "cluster.json").read_text())["workers"]
    assert workers["cores"] == os.cpu_count() and workers["workers_list"] == [1, 2]
    assert workers["baseline_workers"] == 1 and workers["cameras"] == 1000
    assert workers["fake_camera_processes"] >= 2 and workers["load_processes"] >= 2
    assert workers["channels_per_load"] > 1 and (tmp_path / "cluster_workers.png").is_file()
    one, two = workers["by_workers"]["1"], workers["by_workers"]["2"]
    for n, data in ((1, one), (2, two)):
        assert len(data["rps_runs"]) == workers["rounds"] == CLUSTER_SMOKE_ROUNDS and min(data["rps_runs"]) > 0
        assert data["rps"] == data["rps_median"] and data["rps_spread"] == [
            min(data["rps_runs"]),
            max(data["rps_runs"]),
        ]
        assert data["processes"] == n + workers["fake_camera_processes"] + workers["load_processes"]
        # Every worker took connections and spent CPU on them; the harness's CPU is recorded.
        assert all(len(cpu) == n and min(cpu) > 0 for cpu in data["worker_cpu_s_runs"])
        assert data["server_cores"] > 0 and data["load_cores"] > 0 and data["fake_cameras_cores"] > 0
    assert one["over_baseline_runs"] == [1.0] * CLUSTER_SMOKE_ROUNDS
    scaling = [t / o for t, o in zip(two["rps_runs"], one["rps_runs"], strict=True)]
    assert two["over_baseline_runs"] == pytest.approx(scaling)

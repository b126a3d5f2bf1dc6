"""drvs-bench mobile: a smoke run checks its keys, its verdict and that pose updates never rebuilt
the static index; bad flags are refused with exit 2."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from drvs_bench.cli import main

pytestmark = pytest.mark.bench


@pytest.mark.slow
def test_mobile_routing_smoke(tmp_path: Path) -> None:
    assert main(["mobile", "--quick", "--rounds", "2", "--lookups", "500", "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "mobile.json").read_text())
    assert result["static_index_rebuilt_by_pose_updates"] is False
    assert len(result["runs"]) == 2 and (tmp_path / "mobile.png").is_file()
    for run in result["runs"]:
        # 100 cameras at 5 Hz for 500 lookups at 2 kHz (0.25 s): every camera updated at least once.
        assert run["mobile"]["pose_updates"] >= 100 and run["fixed"]["pose_updates"] == 0
        assert run["mobile"]["lookups"] == run["fixed"]["lookups"] == 500
    assert result["lookup_p99_mobile_over_fixed_spread"][0] > 0
    assert result["targets"]["lookup_p99_mobile_over_fixed"]["verdict"] in ("met", "missed", "spread crosses target")


@pytest.mark.parametrize("args", [["--parts", "accuracy"], ["--rounds", "-1"], ["--lookups", "-5"]])
def test_mobile_benchmark_refuses_bad_flags(args: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["mobile", *args]) == 2
    assert "drvs-bench mobile: " in capsys.readouterr().err

"""scripts/device-capacity.sh, the capacity runs prepared for a lent many-core machine: its steps stay
inside the job's deadline (a step that would outrun it is left out and says so), and a wrong verb
is refused. Its runs themselves are the benchmarks' own (their smoke tests beside this one)."""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "scripts" / "device-capacity.sh"


def run_script(*args: str, **env: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        ["bash", str(SCRIPT), *args], capture_output=True, text=True, timeout=60, env={**os.environ, **env}
    )


@pytest.mark.parametrize(
    ("job", "steps"),
    [
        ("run", ["sweep-per-camera", "sweep-fused", "overload-per-camera", "load-100", "cluster-workers",
                 "overload-fused-unary", "service"]),
        ("ros2", ["ros2-quick", "ros2"]),
    ],
)  # fmt: skip
def test_with_no_time_left_every_step_is_left_out_and_logged(job: str, steps: list[str], tmp_path: Path) -> None:
    done = run_script(job, str(tmp_path), DRVS_DEVICE_LOCAL="1", DRVS_DEVICE_DEADLINE_S="0")
    assert done.returncode == 0, done.stderr
    log = (tmp_path / "capacity.log").read_text()
    for step in steps:
        assert re.search(rf"^## {step}: left out, (0|-\d+) s left$", log, re.M), log
    assert "drvs-bench" not in log.split("cores,", 1)[1]  # no run started
    assert "# done after" in log and not (tmp_path / "capacity.tgz").exists()


def test_a_wrong_verb_is_refused_with_the_usage(tmp_path: Path) -> None:
    done = run_script("sweep")
    assert done.returncode == 2 and "usage: scripts/device-capacity.sh prepare | run [DIR] | ros2 [DIR]" in done.stderr

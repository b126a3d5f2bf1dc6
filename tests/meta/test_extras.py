"""Packaging: the roles run on the base package alone; the optional parts (extras sim, bench, certs)
say which extra to install when it is missing.

"Not installed" is made without a second virtualenv: each command runs in a fresh interpreter whose
first import finder refuses the named modules exactly as Python does for a missing one
(ModuleNotFoundError naming the module), then calls the installed console script's entry point.
"""

from __future__ import annotations

import importlib.metadata
import subprocess
import sys
from pathlib import Path

import pytest
from packaging.requirements import Requirement

from drvs.tools._entry import EXTRAS

ROOT = Path(__file__).resolve().parents[2]
ROLE_SCRIPTS = {
    "drvs-server": "drvs.server.cli:main",
    "drvs-camera": "drvs.camera.cli:main",
    "drvs-robot": "drvs.robot.cli:main",
}

RUN_WITHOUT = """
import importlib.abc, importlib.metadata, sys

BLOCKED, COMMAND, ARGS = sys.argv[1].split(","), sys.argv[2], sys.argv[3:]

class NotInstalled(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if any(name == b or name.startswith(b + ".") for b in BLOCKED):
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None

sys.meta_path.insert(0, NotInstalled())
(script,) = importlib.metadata.entry_points(group="console_scripts", name=COMMAND)
sys.argv = [COMMAND, *ARGS]
sys.exit(script.load()())
"""


def run_without(blocked: list[str], command: str, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", RUN_WITHOUT, ",".join(blocked), command, *args],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=ROOT,
    )


def requirements() -> list[Requirement]:
    """The installed package's requirements (pyproject.toml's, as ./run setup installed them)."""
    return [Requirement(r) for r in importlib.metadata.requires("drvs") or []]


def pyproject_extras() -> dict[str, list[Requirement]]:
    extras: dict[str, list[Requirement]] = {}
    for name in importlib.metadata.metadata("drvs").get_all("Provides-Extra") or []:
        if name != "dev":
            extras[name] = [r for r in requirements() if r.marker is not None and r.marker.evaluate({"extra": name})]
    return extras


def test_the_launcher_knows_every_extra_and_the_modules_it_installs() -> None:
    extras = pyproject_extras()
    assert set(extras) == set(EXTRAS) == {"sim", "bench", "certs", "etcd", "live", "ros2"}
    modules_of: dict[str, set[str]] = {}
    for module, owners in importlib.metadata.packages_distributions().items():
        for dist in owners:
            modules_of.setdefault(dist.lower(), set()).add(module)

    def installs(extra: str) -> list[set[str]]:
        """Per distribution of the extra (through the extras it includes), the modules it installs."""
        found: list[set[str]] = []
        for req in extras[extra]:
            if req.name == "drvs":
                found += [m for inner in sorted(req.extras) for m in installs(inner)]
            else:
                assert req.name.lower() in modules_of, f"{req.name} (extra {extra}) is not installed: ./run setup"
                found.append(modules_of[req.name.lower()])
        return found

    for extra, spec in EXTRAS.items():
        dists = installs(extra)
        # Every module the launcher watches belongs to the extra, and every distribution is watched.
        assert set(spec.modules) <= set[str]().union(*dists), extra
        assert all(set(spec.modules) & modules for modules in dists), extra


def test_the_base_package_needs_no_extra() -> None:
    """matplotlib (sim, bench) and onnx (bench) are not base requirements; the roles' are."""
    base = {r.name for r in requirements() if r.marker is None}
    assert "matplotlib" not in base and "onnx" not in base
    assert {"grpcio", "opencv-contrib-python-headless", "shapely", "PyYAML", "onnxruntime"} <= base


def test_every_console_script_is_a_role_or_goes_through_the_launcher() -> None:
    scripts = {
        e.name: e.value for e in importlib.metadata.entry_points(group="console_scripts") if e.name.startswith("drvs-")
    }
    roles = {name: value for name, value in scripts.items() if not value.startswith("drvs.tools._entry:")}
    assert roles == ROLE_SCRIPTS
    assert set(scripts) - set(roles) == {
        "drvs-office", "drvs-sim", "drvs-demo", "drvs-bench", "drvs-certs", "drvs-replay", "drvs-ros2"
    }  # fmt: skip


@pytest.mark.parametrize(
    ("command", "missing", "message"),
    [
        ("drvs-office", "matplotlib", "drvs-office: needs the simulator: pip install 'drvs[sim]'"),
        ("drvs-bench", "matplotlib", "drvs-bench: needs the benchmarks: pip install 'drvs[bench]'"),
        ("drvs-bench", "onnx", "drvs-bench: needs the benchmarks: pip install 'drvs[bench]'"),
        ("drvs-certs", "cryptography", "drvs-certs: needs the certificate tooling: pip install 'drvs[certs]'"),
        ("drvs-replay", "mcap", "drvs-replay: needs the live view and recordings: pip install 'drvs[live]'"),
        (
            "drvs-ros2",
            "cyclonedds",
            "drvs-ros2: needs the ROS 2 bridge (Cyclone DDS, rosbags): pip install 'drvs[ros2]'",
        ),
    ],
)
def test_a_part_whose_extra_is_missing_names_the_extra(command: str, missing: str, message: str) -> None:
    done = run_without([missing], command, "--help")
    assert done.returncode == 1, done.stderr
    assert done.stderr == f"{message} (no module named {missing!r})\n"
    assert done.stdout == ""


def test_with_its_extra_a_part_runs() -> None:
    """The same launcher without the block: the message above is about the block, not the launcher."""
    done = run_without([], "drvs-office", "--help")
    assert done.returncode == 0, done.stderr
    assert "usage: drvs-office" in done.stdout


@pytest.mark.parametrize("command", sorted(ROLE_SCRIPTS))
def test_a_role_runs_without_any_extra_or_the_simulator(command: str) -> None:
    """What a camera host has: the base package. The roles start without matplotlib, onnx, the
    simulator or the benchmarks (cryptography is base: the server reads certificates' roles)."""
    blocked = sorted({m for extra in EXTRAS.values() for m in extra.modules} - {"cryptography"})
    done = run_without([*blocked, "drvs.sim", "drvs_bench"], command, "--help")
    assert done.returncode == 0, done.stderr
    assert f"usage: {command}" in done.stdout
    assert "Traceback" not in done.stderr


def test_a_sim_source_without_the_simulator_names_the_extra(tmp_path: Path) -> None:
    """drvs-camera --source sim://... finds the simulator through an entry point; when it cannot
    load, the camera says so and which extra brings it, and exits 2 as for any bad flag, before it
    grabs a frame."""
    done = run_without(
        ["drvs.sim"], "drvs-camera", "snapshot", "--source", "sim://127.0.0.1:1", "--id", "cam1",
        "--out", str(tmp_path / "frame.png"),
    )  # fmt: skip
    assert done.returncode == 2, done.stderr
    assert done.stderr == (
        "drvs-camera snapshot: source sim://127.0.0.1:1: the sim:// frame source (drvs.sim.source:SimSource) "
        "cannot load: No module named 'drvs.sim' (the simulator: pip install 'drvs[sim]')\n"
    )
    assert not (tmp_path / "frame.png").exists()

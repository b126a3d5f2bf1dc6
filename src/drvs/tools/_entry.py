"""The console scripts of DRVS's optional parts (pyproject.toml's extras: sim, bench, certs, etcd, live, ros2).

Each checks that its extra's libraries are installed, then imports its module and runs its `main`;
when one is missing it says which extra to install (`drvs-office: needs the simulator: pip install
'drvs[sim]'`) and exits 1, instead of an ImportError's traceback at the end of a run. The roles'
scripts (drvs-server, drvs-camera, drvs-robot) need no extra and point at their modules directly.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from collections.abc import Callable
from dataclasses import dataclass
from typing import cast


@dataclass(frozen=True)
class Extra:
    what: str
    #: The top-level modules the extra's distributions install (what an import of them names).
    modules: tuple[str, ...]


#: pyproject.toml's extras but dev (tests/meta/test_extras.py keeps the two in step).
EXTRAS = {
    "sim": Extra("the simulator", ("matplotlib", "foxglove", "mcap", "mcap_protobuf", "websockets")),
    "bench": Extra(
        "the benchmarks", ("matplotlib", "onnx", "motmetrics", "foxglove", "mcap", "mcap_protobuf", "websockets")
    ),
    "certs": Extra("the certificate tooling", ("cryptography",)),
    "etcd": Extra("the etcd client (drvs-server --registry etcd://...)", ("aetcd",)),
    "live": Extra("the live view and recordings", ("foxglove", "mcap", "mcap_protobuf", "websockets")),
    "ros2": Extra("the ROS 2 bridge (Cyclone DDS, rosbags)", ("cyclonedds", "rosbags")),
}


def missing(extra: str) -> str | None:
    """The first module of the extra that cannot be imported, or None when all can."""
    for name in EXTRAS[extra].modules:
        try:
            if importlib.util.find_spec(name) is None:
                return name
        except ImportError:  # a finder that refuses it
            return name
    return None


def run(command: str, extra: str, module: str) -> int:
    """Run the module's main() if its extra is installed; else say which extra to install. Checked
    before anything runs: the simulator and the benchmarks import matplotlib only to draw their
    results, at the end of a run."""
    absent = missing(extra)
    if absent is not None:
        print(
            f"{command}: needs {EXTRAS[extra].what}: pip install 'drvs[{extra}]' (no module named {absent!r})",
            file=sys.stderr,
        )
        return 1
    main = cast(Callable[[], int], importlib.import_module(module).main)
    return main()


def office() -> int:
    return run("drvs-office", "sim", "drvs.sim.office")


def sim() -> int:
    return run("drvs-sim", "sim", "drvs.sim.cli")


def demo() -> int:
    return run("drvs-demo", "sim", "drvs.tools.demo")


def bench() -> int:
    return run("drvs-bench", "bench", "drvs_bench.cli")


def certs() -> int:
    return run("drvs-certs", "certs", "drvs.tools.certs")


def replay() -> int:
    return run("drvs-replay", "live", "drvs.live.replay")


def ros2() -> int:
    return run("drvs-ros2", "ros2", "drvs.ros2.cli")

"""The layers of docs/architecture.md ("Layers"), enforced.

From the bottom up:
  core   every drvs module outside the layers below: pure logic (geometry, filters, model, convert,
         registry, detectors, homography_file, imaging, ...) and the shared plumbing the roles stand on
         (security, metrics, _service, callback, request_stream, ...). Imports no role and no tool.
  roles  drvs.server, drvs.camera, drvs.robot: each stands on the core alone; none imports another
         role, the simulator, the benchmarks or a tool.
  tools  the simulator (drvs.sim), the benchmarks (drvs_bench), drvs.tools.demo, drvs.tools.launch, drvs.tools.certs,
         drvs.tools._entry (the console scripts' launcher), drvs.tools.meter (byte-counting relays around a
         robot's client, for the simulated robot and the benchmarks): may use everything below, but the simulator
         talks to servers and cameras only over the wire (it starts their processes): of the roles
         it imports drvs.robot alone (its robot is a robot program).
The `drvs` package itself (drvs/__init__.py) is the robot programmer's front door: it may re-export
drvs.robot, and nothing else above the core.
Within the core, the detectors (drvs.detectors: OpenCV and every plug-in) are for cameras: the rest
of the core parses filter_defs with the grammar (drvs.core.object_types) and imports no detector, so
neither the server nor a robot loads one (drvs.core.frames, the frame sources' shared part, which cameras
and the simulator alone use, is the one exception: a Frame is the detectors').

Checked twice: statically (every import statement of every module, inside functions too, and
importlib.import_module("...") with a literal name), and by importing every module of each role in
a fresh interpreter and looking at what got loaded (which catches imports through other modules).
"""

from __future__ import annotations

import ast
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SOURCES = {"drvs": ROOT / "src" / "drvs", "drvs_bench": ROOT / "benchmarks" / "drvs_bench"}
ROLES = ("drvs.server", "drvs.camera", "drvs.robot")
SIMULATOR = "drvs.sim"
BENCHMARKS = "drvs_bench"
TOOLS = (
    SIMULATOR,
    BENCHMARKS,
    "drvs.tools.demo",
    "drvs.tools.launch",
    "drvs.tools.certs",
    "drvs.tools._entry",
    "drvs.tools.meter",
)
FACADE = "drvs"
GENERATED = "drvs.v1"
#: Third-party packages that only tools may import: matplotlib draws the office's map and the plots.
TOOL_ONLY_LIBRARIES = ("matplotlib",)
DETECTORS = "drvs.detectors"
#: Core modules outside drvs.detectors that may import it, and why.
DETECTOR_USERS = {"drvs.core.frames": "the frame sources' newest frame is a drvs.detectors Frame"}


def under(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def layer(module: str) -> str:
    if any(under(module, role) for role in ROLES):
        return next(role for role in ROLES if under(module, role))
    if any(under(module, tool) for tool in TOOLS):
        return "tool"
    if module == FACADE:
        return "facade"
    return "core"


@dataclass(frozen=True)
class Import:
    module: str  # the importing module
    target: str  # what it imports, resolved to a module name
    line: int

    def __str__(self) -> str:
        return f"{self.module} (line {self.line}) imports {self.target}"


def module_files() -> dict[str, Path]:
    """Every module of drvs and drvs_bench but the generated protobuf code, by dotted name."""
    found: dict[str, Path] = {}
    for top, directory in SOURCES.items():
        for path in sorted(directory.rglob("*.py")):
            parts = [top, *path.relative_to(directory).with_suffix("").parts]
            if parts[-1] == "__init__":
                parts.pop()
            name = ".".join(parts)
            if not under(name, GENERATED):
                found[name] = path
    return found


def _is_module(name: str) -> bool:
    top, _, rest = name.partition(".")
    if top not in SOURCES:
        return False
    base = SOURCES[top].joinpath(*rest.split(".")) if rest else SOURCES[top]
    return base.with_suffix(".py").is_file() or (base / "__init__.py").is_file()


def imports_of(module: str, path: Path) -> list[Import]:
    """Everything the module imports, wherever the statement is (top level, functions, TYPE_CHECKING)."""
    tree = ast.parse(path.read_text(), str(path))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found: list[Import] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [Import(module, alias.name, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                source = ".".join([*base, node.module] if node.module else base)
            else:
                source = node.module or ""
            for alias in node.names:
                # `from drvs import sim` imports the module drvs.sim; `from drvs.core.geometry import Homography` does not.
                candidate = f"{source}.{alias.name}"
                found.append(Import(module, candidate if _is_module(candidate) else source, node.lineno))
        elif (
            isinstance(node, ast.Call)
            and isinstance(node.func, (ast.Name, ast.Attribute))
            and (node.func.id if isinstance(node.func, ast.Name) else node.func.attr) in ("import_module", "__import__")
            and node.args
            and isinstance(node.args[0], ast.Constant)
            and isinstance(node.args[0].value, str)
        ):
            found.append(Import(module, node.args[0].value, node.lineno))
    return found


def all_imports() -> list[Import]:
    return [imp for name, path in module_files().items() for imp in imports_of(name, path)]


def violations(imports: list[Import]) -> list[str]:
    """Each import that breaks a rule of the layers, saying which rule."""
    bad: list[str] = []
    for imp in imports:
        source, target = layer(imp.module), imp.target
        if source == "tool":
            if under(imp.module, SIMULATOR) and layer(target) in ROLES and layer(target) != "drvs.robot":
                bad.append(f"{imp}: the simulator reaches servers and cameras over the wire only")
            continue
        if any(under(target, lib) for lib in TOOL_ONLY_LIBRARIES):
            bad.append(f"{imp}: only tools (the simulator, the benchmarks) may draw with it")
        elif not target.startswith(("drvs.", "drvs_bench")) or under(target, GENERATED):
            continue
        elif under(target, SIMULATOR) or under(target, BENCHMARKS):
            bad.append(f"{imp}: nothing below the tools may import the simulator or the benchmarks")
        elif layer(target) == "tool":
            bad.append(f"{imp}: {target} is a tool, above every role")
        elif source == "core" and layer(target) in ROLES:
            bad.append(f"{imp}: the core (pure logic and shared plumbing) imports no role")
        elif (
            source == "core"
            and under(target, DETECTORS)
            and not under(imp.module, DETECTORS)
            and imp.module not in DETECTOR_USERS
        ):
            bad.append(
                f"{imp}: the core parses filter_defs with drvs.core.object_types and imports no detector plug-in"
            )
        elif source == "facade" and layer(target) in ROLES and layer(target) != "drvs.robot":
            bad.append(f"{imp}: the drvs package re-exports the robot API only")
        elif source in ROLES and layer(target) in ROLES and layer(target) != source:
            bad.append(f"{imp}: a role imports no other role")
    return bad


def test_the_scan_sees_every_kind_of_import(tmp_path: Path) -> None:
    """The scanner itself: a module with each kind of import statement, in functions too."""
    source = (
        "import drvs.sim.scene\n"
        "from drvs import sim\n"
        "from drvs.core.geometry import Homography\n"
        "from . import config\n"
        "from ..sim.source import SimSource\n"
        "def f():\n"
        "    from drvs_bench.common import x\n"
        "    import importlib\n"
        "    return importlib.import_module('drvs.sim.source')\n"
    )
    path = tmp_path / "probe.py"
    path.write_text(source)
    targets = [imp.target for imp in imports_of("drvs.camera.probe", path)]
    assert targets == [
        "drvs.sim.scene",
        "drvs.sim",
        "drvs.core.geometry",
        "drvs.camera.config",
        "drvs.sim.source",
        "drvs_bench.common",
        "importlib",
        "drvs.sim.source",
    ]
    bad = violations([Import("drvs.camera.probe", t, 1) for t in targets])
    assert len(bad) == 5, bad  # the four simulator imports and the benchmarks'


def test_the_rules_catch_each_kind_of_crossing() -> None:
    cases = {
        ("drvs.camera.aruco", "drvs.sim.scene"): "simulator",
        ("drvs.server.cli", "drvs_bench.common"): "benchmarks",
        ("drvs.core.geometry", "drvs.camera.homography_file"): "imports no role",
        ("drvs.server.registry", "drvs.server.server"): "imports no role",
        ("drvs.camera.cli", "drvs.tools.launch"): "is a tool",
        ("drvs.robot.client", "drvs.server.server"): "no other role",
        ("drvs.camera.node", "matplotlib.pyplot"): "only tools",
        ("drvs", "drvs.camera"): "robot API only",
        ("drvs.sim.scene", "drvs.camera.calibration"): "over the wire",
        ("drvs.sim.office", "drvs.server.cli"): "over the wire",
        ("drvs.core.model", "drvs.detectors"): "no detector plug-in",
        ("drvs.core.filters", "drvs.detectors.hsv"): "no detector plug-in",
        ("drvs.wire.convert", "drvs.detectors.base"): "no detector plug-in",
    }
    for (module, target), why in cases.items():
        (message,) = violations([Import(module, target, 1)])
        assert why in message, message
    allowed = [
        ("drvs.sim.robot", "drvs.robot"),
        ("drvs_bench.service", "drvs.server.server"),
        ("drvs_bench.common", "drvs.sim.scene"),
        ("drvs.camera.node", "drvs.core.geometry"),
        ("drvs", "drvs.robot"),
        ("drvs.robot.client", "drvs.robot.cli"),
        ("drvs.sim.report", "matplotlib"),
        ("drvs.detectors.hsv", "drvs.core.object_types"),
        ("drvs.detectors.aruco", "drvs.detectors.base"),
        ("drvs.camera.node", "drvs.detectors"),
        ("drvs.sim.scenario", "drvs.detectors.aruco"),
    ]
    assert violations([Import(m, t, 1) for m, t in allowed]) == []


def test_no_module_imports_across_the_layers() -> None:
    modules = module_files()
    assert {
        "drvs.core.geometry",
        "drvs.camera.cli",
        "drvs.server.server",
        "drvs.robot.client",
        "drvs.sim.scene",
    } <= set(modules)
    bad = violations(all_imports())
    assert not bad, "imports across the layers (docs/architecture.md, Layers):\n" + "\n".join(bad)


#: What must never be loaded on a host that runs only that role.
NEVER_LOADED_BY_ROLES = (SIMULATOR, BENCHMARKS, "matplotlib")


@pytest.mark.parametrize("role", ROLES)
def test_a_role_loads_no_simulator_benchmarks_or_matplotlib(role: str) -> None:
    """Import every module of the role (its CLI, its servicer, ...) in a fresh interpreter."""
    mods = sorted(name for name in module_files() if under(name, role))
    assert f"{role}.cli" in mods
    code = (
        "import importlib, sys\n"
        f"for name in {mods!r}:\n"
        "    importlib.import_module(name)\n"
        f"print('\\n'.join(sorted(m for m in sys.modules if m.split('.')[0] in {{'matplotlib', 'drvs_bench'}}"
        f" or m == {SIMULATOR!r} or m.startswith({SIMULATOR + '.'!r}))))\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert done.returncode == 0, done.stderr
    loaded = done.stdout.split()
    assert loaded == [], f"importing {role} loaded {loaded} (never: {NEVER_LOADED_BY_ROLES})"


@pytest.mark.parametrize("role", ("drvs.server", "drvs.robot"))
def test_the_server_and_robots_parse_filter_defs_without_loading_a_detector(role: str) -> None:
    """Import every module of the role in a fresh interpreter, then validate a request of every
    built-in type as the server does (drvs.wire.convert.request_from_pb): no drvs.detectors module loads."""
    mods = sorted(name for name in module_files() if under(name, role))
    filter_defs = ("hsv_014110130035225200", "aruco_4x4_50_7", "people", "foreground", "model_yolo_person")
    code = (
        "import importlib, sys\n"
        f"for name in {mods!r}:\n"
        "    importlib.import_module(name)\n"
        "from shapely.geometry import box\n"
        "from drvs.wire.convert import request_from_pb, request_to_pb\n"
        "from drvs.core.model import DetectionRequest\n"
        f"for f in {filter_defs!r}:\n"
        "    request_from_pb(request_to_pb(DetectionRequest('r', 'b', f, box(0, 0, 1, 1), '127.0.0.1:5000')))\n"
        f"loaded = [m for m in sys.modules if m == {DETECTORS!r} or m.startswith({DETECTORS + '.'!r})]\n"
        "print('\\n'.join(sorted(loaded)))\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert done.returncode == 0, done.stderr
    loaded = done.stdout.split()
    assert loaded == [], f"{role} loaded {loaded} to parse filter_defs (drvs.core.object_types needs no detector)"

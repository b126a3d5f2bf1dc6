"""The layers of docs/architecture.md ("Layers"), enforced. A layer is a folder of src/drvs (and an
extra is a folder: drvs.live is the `live` extra, the tools are the optional parts' scripts).

From the bottom up:
  core       drvs.core: pure logic (geometry, model, object_types, filters, errors, net, mobile,
             homography_file, imaging, frames, ...). Imports nothing above it, not even the wire's
             generated messages (drvs.v1).
             drvs.detectors (OpenCV and every plug-in) stands beside it and is for cameras: the rest
             of the core parses filter_defs with the grammar (drvs.core.object_types) and imports no
             detector, so neither the server nor a robot loads one (drvs.core.frames, the frame
             sources' shared part, is the one exception: a Frame is the detectors').
  wire       drvs.wire: the gRPC plumbing every role shares (_grpc, _service, channels, security,
             convert, callback, request streams, health, metrics, logs, _cli). Imports the core only
             (and drvs.v1).
  live       drvs.live: the `live` extra: the live view's hub (the roles' --foxglove views stand on it),
             its token gate, the Foxglove client, drvs-replay. Imports the core and the wire.
  roles      drvs.server, drvs.camera, drvs.robot: each stands on core, wire and live; none imports
             another role, the simulator, the benchmarks or a tool. Of the roles only the camera
             imports a detector.
  ros2       drvs.ros2: the `ros2` extra: drvs-ros2 (a robot program publishing a track on ROS 2
             topics) and the rosbag2 export. Stands on core, wire, live and drvs.robot; nothing imports
             it but the tools, and drvs-replay's --rosbag2, lazily (LAZY_UPWARD).
  tools      drvs.tools (_entry, the console scripts' launcher; launch, demo, certs, meter, fakes), the
             simulator (drvs.sim), the benchmarks (drvs_bench): may use everything below, but the
             simulator talks to servers and cameras only over the wire (it starts their processes): of
             the roles it imports drvs.robot alone (its robot is a robot program).
The `drvs` package itself (drvs/__init__.py) is the robot programmer's front door: it may re-export
the core, the wire (Security) and drvs.robot. The deprecated aliases scripts/migrate_layers.py leaves
at the old flat paths robot programmers import (ALIASES) import only their new module, and nothing
imports them. Every other module lives in a layer's folder: none stands flat in src/drvs.
The extras' libraries are imported at module level only by their folder (drvs.live) and the tools;
below them only inside functions, when the optional part runs, so the base package runs without them.

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

ROOT = Path(__file__).resolve().parents[2]
SOURCES = {"drvs": ROOT / "src" / "drvs", "drvs_bench": ROOT / "benchmarks" / "drvs_bench"}
CORE = "drvs.core"
WIRE = "drvs.wire"
LIVE = "drvs.live"
ROS2 = "drvs.ros2"
ROLES = ("drvs.server", "drvs.camera", "drvs.robot")
SIMULATOR = "drvs.sim"
BENCHMARKS = "drvs_bench"
TOOLS = ("drvs.tools", SIMULATOR, BENCHMARKS)
FACADE = "drvs"
GENERATED = "drvs.v1"
#: What each layer may import of the drvs layers (a role also its own package; tools anything).
MAY_IMPORT = {
    "core": {"core", "detectors"},
    "detectors": {"core", "detectors"},
    "wire": {"core", "wire", "generated"},
    "live": {"core", "wire", "live", "generated"},
    "role": {"core", "wire", "live", "generated", "detectors"},
    "facade": {"core", "wire", "drvs.robot"},
    "ros2": {"core", "wire", "live", "ros2", "generated", "drvs.robot"},
}
#: Imports against the layers' order, inside a function only (run when that option is used), and why.
LAZY_UPWARD = {("drvs.live.replay", "drvs.ros2"): "drvs-replay --rosbag2 hands the recording to the ros2 extra"}
#: Third-party packages that only tools may import: matplotlib draws the office's map and the plots.
TOOL_ONLY_LIBRARIES = ("matplotlib",)
#: The extras' libraries, imported at module level only in their folder (and by the tools).
EXTRA_LIBRARIES = {
    "foxglove": LIVE, "mcap": LIVE, "mcap_protobuf": LIVE, "websockets": LIVE, "aetcd": None,
    "cyclonedds": ROS2, "rosbags": ROS2,
}  # fmt: skip
DETECTORS = "drvs.detectors"
#: Core modules outside drvs.detectors that may import it, and why.
DETECTOR_USERS = {"drvs.core.frames": "the frame sources' newest frame is a drvs.detectors Frame"}
#: scripts/migrate_layers.py's deprecated aliases at the old flat paths carry this line.
SHIM_MARK = "# drvs-layers-shim"
#: The aliases robot programmers' code imports: old path -> new path (for one release).
ALIASES = {
    "drvs.model": "drvs.core.model",  # migrate_layers: keep
    "drvs.geometry": "drvs.core.geometry",  # migrate_layers: keep
    "drvs.errors": "drvs.core.errors",  # migrate_layers: keep
    "drvs.security": "drvs.wire.security",  # migrate_layers: keep
    "drvs.object_types": "drvs.core.object_types",  # migrate_layers: keep
}


def under(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def shims() -> set[str]:
    return {f"drvs.{p.stem}" for p in SOURCES["drvs"].glob("*.py") if SHIM_MARK in p.read_text()}


def layer(module: str) -> str:
    """core, detectors, wire, live, a role's package name, tool, facade, generated, shim, or flat
    (a module standing in src/drvs outside every folder)."""
    for role in ROLES:
        if under(module, role):
            return role
    for package, name in ((CORE, "core"), (DETECTORS, "detectors"), (WIRE, "wire"), (LIVE, "live"), (ROS2, "ros2")):
        if under(module, package):
            return name
    if any(under(module, tool) for tool in TOOLS):
        return "tool"
    if under(module, GENERATED):
        return "generated"
    if module == FACADE:
        return "facade"
    if module in shims():
        return "shim"
    return "flat"


@dataclass(frozen=True)
class Import:
    module: str  # the importing module
    target: str  # what it imports, resolved to a module name
    line: int
    lazy: bool = False  # inside a function: runs when the function does

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
    in_functions = {
        id(inner)
        for node in ast.walk(tree)
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
        for inner in ast.walk(node)
    }
    found: list[Import] = []
    for node in ast.walk(tree):
        lazy = id(node) in in_functions
        if isinstance(node, ast.Import):
            found += [Import(module, alias.name, node.lineno, lazy) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                source = ".".join([*base, node.module] if node.module else base)
            else:
                source = node.module or ""
            for alias in node.names:
                # `from drvs import sim` imports the module drvs.sim; `from drvs.core.geometry import X` does not.
                candidate = f"{source}.{alias.name}"
                found.append(Import(module, candidate if _is_module(candidate) else source, node.lineno, lazy))
        elif (
            isinstance(node, ast.Call)
            and isinstance(node.func, (ast.Name, ast.Attribute))
            and (node.func.id if isinstance(node.func, ast.Name) else node.func.attr) in ("import_module", "__import__")
            and node.args
            and isinstance(node.args[0], ast.Constant)
            and isinstance(node.args[0].value, str)
        ):
            found.append(Import(module, node.args[0].value, node.lineno, lazy))
    return found


def all_imports() -> list[Import]:
    return [imp for name, path in module_files().items() for imp in imports_of(name, path)]


def _kind(layer_name: str) -> str:
    return "role" if layer_name in ROLES else layer_name


def violations(imports: list[Import]) -> list[str]:
    """Each import that breaks a rule of the layers, saying which rule."""
    bad: list[str] = []
    aliases = shims()
    for imp in imports:
        source, target = layer(imp.module), imp.target
        library = target.split(".")[0]
        drvs_target = target.startswith(("drvs.", "drvs_bench")) or target == FACADE
        if source == "flat":
            bad.append(f"{imp}: {imp.module} stands flat in src/drvs: every module lives in a layer's folder")
            continue
        if source == "shim":
            if drvs_target and not target.endswith("." + imp.module.rpartition(".")[2]):
                bad.append(f"{imp}: a deprecated alias imports its new module only")
            continue
        if drvs_target and target in aliases:
            bad.append(f"{imp}: {target} is a deprecated alias: import its new module")
            continue
        if source == "tool":
            if under(imp.module, SIMULATOR) and layer(target) in ROLES and layer(target) != "drvs.robot":
                bad.append(f"{imp}: the simulator reaches servers and cameras over the wire only")
            continue
        if library in TOOL_ONLY_LIBRARIES:
            bad.append(f"{imp}: only tools (the simulator, the benchmarks) may draw with it")
            continue
        if library in EXTRA_LIBRARIES and not imp.lazy and not under(imp.module, EXTRA_LIBRARIES[library] or "-"):
            bad.append(f"{imp}: an extra's library, imported at module level outside its folder (import it lazily)")
            continue
        if not drvs_target or target == FACADE:
            continue
        if imp.lazy and (imp.module, target) in LAZY_UPWARD:
            continue
        wanted = layer(target)
        if wanted == "flat":
            bad.append(f"{imp}: {target} stands flat in src/drvs: every module lives in a layer's folder")
        elif under(target, SIMULATOR) or under(target, BENCHMARKS):
            bad.append(f"{imp}: nothing below the tools may import the simulator or the benchmarks")
        elif wanted == "tool":
            bad.append(f"{imp}: {target} is a tool, above every layer but the tools")
        elif wanted == "detectors" and source not in ("detectors", "drvs.camera") and imp.module not in DETECTOR_USERS:
            bad.append(
                f"{imp}: detectors are for cameras: the rest parses filter_defs with drvs.core.object_types "
                "and imports no detector plug-in"
            )
        elif source == "ros2" and wanted in ROLES:
            if wanted != "drvs.robot":
                bad.append(f"{imp}: the ROS 2 bridge is a robot program: of the roles it imports drvs.robot alone")
        elif source in ROLES and wanted in ROLES:
            if wanted != source:
                bad.append(f"{imp}: a role imports no other role")
        elif source == "facade":
            if wanted not in MAY_IMPORT["facade"]:
                bad.append(f"{imp}: the drvs package re-exports the core, the wire and the robot API only")
        elif _kind(wanted) not in MAY_IMPORT[_kind(source)] and wanted != "detectors":
            below = {"core": "the core (pure logic)", "wire": "the wire", "live": "the live view"}.get(source, source)
            bad.append(f"{imp}: {below} imports only {sorted(MAY_IMPORT[_kind(source)])}, not {wanted}")
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
    found = imports_of("drvs.camera.probe", path)
    targets = [imp.target for imp in found]
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
    assert [imp.lazy for imp in found] == [False] * 5 + [True] * 3
    bad = violations(found)
    assert len(bad) == 5, bad  # the four simulator imports and the benchmarks'


def test_the_rules_catch_each_kind_of_crossing() -> None:
    cases = {
        ("drvs.camera.aruco", "drvs.sim.scene"): "simulator",
        ("drvs.server.cli", "drvs_bench.common"): "benchmarks",
        ("drvs.core.geometry", "drvs.camera.homography_file"): "the core (pure logic) imports only",
        ("drvs.core.model", "drvs.wire.convert"): "the core (pure logic) imports only",
        ("drvs.core.model", "drvs.v1.detection_pb2"): "the core (pure logic) imports only",
        ("drvs.wire.callback", "drvs.server.server"): "the wire imports only",
        ("drvs.wire.security", "drvs.live.liveview"): "the wire imports only",
        ("drvs.live.liveview", "drvs.camera.node"): "the live view imports only",
        ("drvs.camera.cli", "drvs.tools.launch"): "is a tool",
        ("drvs.live.replay", "drvs.tools._entry"): "is a tool",
        ("drvs.robot.client", "drvs.server.server"): "no other role",
        ("drvs.camera.node", "drvs.server.registry"): "no other role",
        ("drvs.camera.node", "matplotlib.pyplot"): "only tools",
        ("drvs.camera.node", "foxglove"): "extra's library",
        ("drvs", "drvs.camera"): "re-exports",
        ("drvs.sim.scene", "drvs.camera.calibration"): "over the wire",
        ("drvs.sim.office", "drvs.server.cli"): "over the wire",
        ("drvs.core.model", "drvs.detectors"): "no detector plug-in",
        ("drvs.core.filters", "drvs.detectors.hsv"): "no detector plug-in",
        ("drvs.wire.convert", "drvs.detectors.base"): "no detector plug-in",
        ("drvs.server.registry", "drvs.detectors.base"): "no detector plug-in",
        ("drvs.camera.node", "drvs.model"): "deprecated alias",  # migrate_layers: keep
        ("drvs.model", "drvs.wire.security"): "its new module only",  # migrate_layers: keep
        ("drvs.camera.node", "drvs.stray"): "flat in src/drvs",
        ("drvs.ros2.bridge", "drvs.server.server"): "drvs.robot alone",
        ("drvs.robot.client", "drvs.ros2.dds"): "not ros2",
        ("drvs.live.replay", "drvs.ros2.bag"): "not ros2",
        ("drvs.live.liveview", "drvs.ros2"): "not ros2",
        ("drvs.robot.client", "cyclonedds"): "an extra's library",
    }
    for (module, target), why in cases.items():
        (message,) = violations([Import(module, target, 1)])
        assert why in message, message
    allowed = [
        ("drvs.sim.robot", "drvs.robot"),
        ("drvs_bench.service", "drvs.server.server"),
        ("drvs_bench.common", "drvs.sim.scene"),
        ("drvs.tools.demo", "drvs.server.registry"),
        ("drvs.camera.node", "drvs.core.geometry"),
        ("drvs.camera.node", "drvs.wire.metrics"),
        ("drvs.camera.node", "drvs.live.liveview"),
        ("drvs.server.server", "drvs.server.registry"),
        ("drvs.wire.convert", "drvs.v1.detection_pb2"),
        ("drvs.live.liveview", "drvs.core.net"),
        ("drvs.live.replay", "drvs.wire.convert"),
        ("drvs.live.liveview", "foxglove"),
        ("drvs", "drvs.robot"),
        ("drvs", "drvs.wire.security"),
        ("drvs.robot.client", "drvs.robot.cli"),
        ("drvs.sim.report", "matplotlib"),
        ("drvs.detectors.hsv", "drvs.core.object_types"),
        ("drvs.detectors.aruco", "drvs.detectors.base"),
        ("drvs.camera.node", "drvs.detectors"),
        ("drvs.core.frames", "drvs.detectors.base"),
        ("drvs.sim.scenario", "drvs.detectors.aruco"),
        ("drvs.model", "drvs.core.model"),  # migrate_layers: keep
        ("drvs.ros2.bridge", "drvs.robot.client"),
        ("drvs.ros2.bridge", "drvs.wire._cli"),
        ("drvs.ros2.dds", "cyclonedds.domain"),
        ("drvs_bench.ros2", "drvs.ros2.bridge"),
    ]
    assert violations([Import(m, t, 1) for m, t in allowed]) == []
    assert violations([Import("drvs.camera.liveview", "foxglove.channels", 1, lazy=True)]) == []
    assert violations([Import("drvs.live.replay", "drvs.ros2", 1, lazy=True)]) == []
    assert violations([Import("drvs.live.replay", "drvs.ros2", 1, lazy=False)])  # lazily only


def test_no_module_imports_across_the_layers() -> None:
    modules = module_files()
    assert {
        "drvs.core.geometry",
        "drvs.wire.security",
        "drvs.live.liveview",
        "drvs.tools._entry",
        "drvs.camera.cli",
        "drvs.server.server",
        "drvs.robot.client",
        "drvs.sim.scene",
    } <= set(modules)
    bad = violations(all_imports())
    assert not bad, "imports across the layers (docs/architecture.md, Layers):\n" + "\n".join(bad)


def test_every_module_lives_in_a_layers_folder() -> None:
    flat = sorted(name for name in module_files() if layer(name) == "flat")
    assert flat == [], f"modules outside every layer's folder (src/drvs/<layer>/): {flat}"


def test_the_deprecated_aliases_are_the_new_modules() -> None:
    """Importing an alias (a shim at the old path) gives the new module itself, with a DeprecationWarning;
    importing the new modules warns nothing."""
    assert set(ALIASES) == shims()
    for old, new in ALIASES.items():
        code = (
            "import importlib, sys, warnings\n"
            "warnings.simplefilter('error')\n"
            f"new = importlib.import_module({new!r})\n"
            "import drvs\n"
            "with warnings.catch_warnings(record=True) as caught:\n"
            "    warnings.simplefilter('always')\n"
            f"    old = importlib.import_module({old!r})\n"
            "assert [w.category for w in caught] == [DeprecationWarning], caught\n"
            f"assert old is new and sys.modules[{old!r}] is new\n"
            f"assert getattr(drvs, {old.rpartition('.')[2]!r}) is new\n"
            "assert all(getattr(old, name) is getattr(new, name) for name in dir(new))\n"
        )
        done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT)
        assert done.returncode == 0, f"{old}: {done.stderr}"


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

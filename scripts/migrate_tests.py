"""Tests mirror the code: moves each test module out of the flat tests/ folder into the folder of the
layer it tests (tests/core, tests/wire, tests/server, ...), the behaviour suites (faults, security,
bad input, load) into tests/behaviour, the checks of the repository itself (docs, layers, sizes)
into tests/meta, the benchmarks' tests into tests/benchmarks, and the tests' fakes into tests/fakes.

    python scripts/migrate_tests.py            # move (git mv, so history follows) and rewrite references
    python scripts/migrate_tests.py --check    # say what it would move; exit 1 if anything is left

Re-runnable and idempotent: only test files still in the tests/ root move, so a branch merged later
(new tests written flat) is placed by running it again. Where a file goes: FOLDERS (by name), else
PREFIXES (by how its name starts), else the layer whose modules it imports most (said in the
output, so a wrong guess is seen; add the file to FOLDERS then). What it rewrites:

- in each moved file: relative imports of the tests' shared modules (`from .helpers import` ->
  `from tests.helpers import`, `.fakes`, a sibling test module: its new package), fakes taken from the
  benchmarks package (`from drvs_bench.fakes import` -> `from tests.fakes import`, but in
  tests/benchmarks, which may import drvs_bench), and paths built from `__file__` (one folder deeper:
  `parents[1]` -> `parents[2]`, `.parent / "scenarios"` -> `.parents[1] / "scenarios"`, ...);
- everywhere git knows (docs, source comments, scripts): `tests/test_x.py` -> `tests/<folder>/test_x.py`
  for every test module in a folder, and `` `test_x.py`` in docs' tables (the security model names
  tests relative to tests/) -> `` `<folder>/test_x.py``.

tests/conftest.py, tests/helpers.py and tests/__init__.py stay in the root (the fixtures apply to every
folder below); each folder gets an __init__.py, so two folders may hold modules of the same name.
"""

from __future__ import annotations

import argparse
import ast
import re
import subprocess
import sys
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TESTS = ROOT / "tests"
#: What stays in the tests/ root.
ROOT_FILES = ("__init__.py", "conftest.py", "helpers.py")
#: Every other module in the root is one of the tests' fakes (stand-in processes, set-ups): it goes
#: to tests/fakes/ (fakes.py itself becomes the package, tests/fakes/__init__.py).
FAKES = "fakes"


def fake_target(name: str) -> str:
    return f"{FAKES}/__init__.py" if name == f"{FAKES}.py" else f"{FAKES}/{name}"


#: Each test module's folder, by name.
FOLDERS: dict[str, str] = {
    # the core: pure logic
    "test_backoff.py": "core",
    "test_filters.py": "core",
    "test_geometry.py": "core",
    "test_homography_file.py": "core",
    "test_net.py": "core",
    "test_object_types.py": "core",
    "test_object_type_grammar.py": "core",
    "test_model_names.py": "core",
    "test_upright.py": "core",
    # the wire
    "test_convert.py": "wire",
    "test_request_stream.py": "wire",
    "test_grpc_errors.py": "wire",
    "test_batches.py": "wire",
    # detectors
    "test_aruco_detector.py": "detectors",
    "test_detection.py": "detectors",
    "test_foreground.py": "detectors",
    "test_people.py": "detectors",
    "test_model_detector.py": "detectors",
    "test_foreground_floor.py": "detectors",
    # the camera
    "test_aruco.py": "camera",
    "test_calibration.py": "camera",
    "test_camera_config.py": "camera",
    "test_camera_settings.py": "camera",
    "test_camera_liveview.py": "camera",
    "test_prefetch.py": "camera",
    "test_mobile_camera.py": "camera",
    "test_camera_check.py": "camera",
    "test_degrade.py": "camera",
    # the server
    "test_admission.py": "server",
    "test_claims.py": "server",
    "test_registry.py": "server",
    "test_registry_fill.py": "server",
    "test_registry_poison.py": "server",
    "test_registration.py": "server",
    "test_etcd.py": "server",
    "test_shared_registry.py": "server",
    "test_server.py": "server",
    "test_server_fusion.py": "server",
    "test_server_lists.py": "server",
    "test_server_settings.py": "server",
    "test_fusion.py": "server",
    "test_tracking.py": "server",
    "test_mobile_routing.py": "server",
    "test_mobile_pickup.py": "server",
    "test_routing_errors.py": "server",
    "test_frames.py": "server",
    "test_workers.py": "server",
    "test_role_config.py": "server",
    # the robot
    "test_robot_api.py": "robot",
    "test_robot_fusion.py": "robot",
    "test_client_regions.py": "robot",
    "test_cli.py": "robot",
    # the live view
    "test_liveview.py": "live",
    "test_replay.py": "live",
    # the simulator
    "test_scenario.py": "sim",
    "test_scouts.py": "sim",
    "test_sim_markers.py": "sim",
    "test_sim_moving.py": "sim",
    "test_sim_predict.py": "sim",
    "test_planner.py": "sim",
    "test_office.py": "sim",
    "test_office_moving.py": "sim",
    "test_coverage.py": "sim",
    # the tools
    "test_launch.py": "tools",
    "test_meter.py": "tools",
    # behaviour suites: faults, exhaustion, hostile and bad input, security, the network
    "test_faults.py": "behaviour",
    "test_exhaustion.py": "behaviour",
    "test_bad_input.py": "behaviour",
    "test_hostile_inputs.py": "behaviour",
    "test_security.py": "behaviour",
    "test_camera_trust.py": "behaviour",
    "test_report_trust.py": "behaviour",
    "test_report_intake_bounds.py": "behaviour",
    "test_tls_lists.py": "behaviour",
    "test_etcd_access.py": "behaviour",
    "test_netns.py": "behaviour",
    "test_end_to_end.py": "behaviour",
    "test_observability.py": "behaviour",
    "test_liveview_abuse.py": "behaviour",
    "test_mobile_bounds.py": "behaviour",
    # the repository's own rules: docs agree with the code, the layers, sizes, generated code, extras
    "test_architecture_doc.py": "meta",
    "test_docs_links.py": "meta",
    "test_layers.py": "meta",
    "test_module_size.py": "meta",
    "test_generated_code.py": "meta",
    "test_validation_doc.py": "meta",
    "test_security_table.py": "meta",
    "test_migrate_layers.py": "meta",
    "test_migrate_tests.py": "meta",
    "test_test_layout.py": "meta",
    "test_extras.py": "meta",
}
#: A name not in FOLDERS: its folder by how the name starts (first match).
PREFIXES = (
    ("test_bench", "benchmarks"),
    ("test_ros2", "ros2"),
    ("test_sim_", "sim"),
    ("test_office", "sim"),
    ("test_server_", "server"),
    ("test_registry", "server"),
    ("test_fusion", "server"),
    ("test_tracking", "server"),
    ("test_camera_", "camera"),
    ("test_robot_", "robot"),
    ("test_client_", "robot"),
    ("test_liveview", "live"),
    ("test_replay", "live"),
    ("test_detector", "detectors"),
    ("test_model_detector", "detectors"),
    ("test_docs", "meta"),
    ("test_migrate", "meta"),
    ("test_faults", "behaviour"),
    ("test_hostile", "behaviour"),
    ("test_bad_input", "behaviour"),
    ("test_security", "behaviour"),
)
#: The folder of each layer of src/drvs (and the benchmarks), for a guess by imports.
LAYER_FOLDERS = {
    "drvs.core": "core",
    "drvs.wire": "wire",
    "drvs.detectors": "detectors",
    "drvs.camera": "camera",
    "drvs.server": "server",
    "drvs.robot": "robot",
    "drvs.live": "live",
    "drvs.sim": "sim",
    "drvs.tools": "tools",
    "drvs.ros2": "ros2",
    "drvs_bench": "benchmarks",
}
#: Modules nearly every test imports (errors, process launching, the recorded scene, the messages):
#: they say nothing of what a test tests, so the guess by imports leaves them out.
INFRASTRUCTURE = ("drvs.core.errors", "drvs.tools.launch", "drvs.sim.scene", "drvs.v1")
#: Folders whose tests may import the benchmarks package (its fakes included).
MAY_IMPORT_BENCHMARKS = ("benchmarks",)
#: Data folders next to the tests that moved tests reach through `__file__`.
DATA = ("scenarios", "plugins", "data")


def folder_for(path: Path) -> tuple[str, str]:
    """(folder, why) for a test module in the tests/ root."""
    name = path.name
    if name in FOLDERS:
        return FOLDERS[name], "table"
    for prefix, folder in PREFIXES:
        if name.startswith(prefix):
            return folder, f"name starts {prefix}"
    counts: Counter[str] = Counter()
    for node in ast.walk(ast.parse(path.read_text())):
        modules = (
            [a.name for a in node.names]
            if isinstance(node, ast.Import)
            else [node.module or ""]
            if isinstance(node, ast.ImportFrom) and node.level == 0
            else []
        )
        for module in modules:
            if any(module == m or module.startswith(m + ".") for m in INFRASTRUCTURE):
                continue
            layer = next((k for k in LAYER_FOLDERS if module == k or module.startswith(k + ".")), None)
            if layer is not None:
                counts[LAYER_FOLDERS[layer]] += 1
    if not counts:
        raise SystemExit(f"migrate_tests: {name}: no rule places it and it imports no layer; add it to FOLDERS")
    folder, n = counts.most_common(1)[0]
    return folder, f"guessed: most of its imports ({n}) are {folder}'s; add it to FOLDERS if wrong"


def moves() -> dict[Path, Path]:
    """Every file still to move: tests/x -> tests/folder/x."""
    planned: dict[Path, Path] = {}
    for path in sorted(TESTS.glob("*.py")):
        if path.name not in ROOT_FILES and not path.name.startswith("test_"):
            planned[path] = TESTS / fake_target(path.name)
    for path in sorted(TESTS.glob("test_*.py")):
        folder, _ = folder_for(path)
        planned[path] = TESTS / folder / path.name
    return planned


def located() -> dict[str, str]:
    """Every test module already in a folder: file name -> its path from tests/ ("server/test_x.py")."""
    found: dict[str, str] = {}
    for path in sorted(TESTS.glob("*/test_*.py")):
        found[path.name] = path.relative_to(TESTS).as_posix()
    return found


def rewrite_imports(text: str, folder: str, where: dict[str, str]) -> str:
    """A test module's imports of the shared modules, its siblings and the fakes, as a module in a
    folder writes them. Idempotent, so it runs over every test module in a folder on every run (an
    edit merged from a branch that wrote them flat is mended too)."""
    text = re.sub(r"^(\s*)from \.(helpers|fakes|conftest) import", r"\1from tests.\2 import", text, flags=re.M)
    for stem in fake_modules():
        text = re.sub(rf"^(\s*)from \.{stem} import", rf"\1from tests.{FAKES}.{stem} import", text, flags=re.M)

    def sibling(m: re.Match[str]) -> str:
        module = m.group(2)
        package = where.get(f"{module}.py", f"{folder}/{module}.py").rsplit("/", 1)[0]
        return f"{m.group(1)}from tests.{package}.{module} import"

    text = re.sub(r"^(\s*)from \.(test_\w+) import", sibling, text, flags=re.M)
    if folder == "fakes":  # the fakes themselves (fault_roles runs as a script: no tests package)
        text = re.sub(r"^(\s*)from drvs_bench\.fakes import", r"\1from drvs.tools.fakes import", text, flags=re.M)
    elif folder not in MAY_IMPORT_BENCHMARKS:
        text = re.sub(r"^(\s*)from drvs_bench\.fakes import", r"\1from tests.fakes import", text, flags=re.M)
    return text


def rewrite_moved(text: str, folder: str, where: dict[str, str]) -> str:
    """A moved test module's own references: its imports (rewrite_imports) and paths from `__file__`,
    one folder deeper now (only when it moves: that part is not idempotent)."""
    text = rewrite_imports(text, folder, where)
    text = re.sub(r"Path\(__file__\)((?:\.resolve\(\))?)\.parents\[1\]", r"Path(__file__)\1.parents[2]", text)
    text = re.sub(r"Path\(__file__\)((?:\.resolve\(\))?)\.parent\.parent\b", r"Path(__file__)\1.parents[2]", text)
    data = "|".join(DATA)
    text = re.sub(
        rf'Path\(__file__\)((?:\.resolve\(\))?)\.parent / "({data})"', r'Path(__file__)\1.parents[1] / "\2"', text
    )
    for stem in fake_modules():  # a stand-in process found beside the tests, now in tests/fakes
        text = re.sub(
            rf'Path\(__file__\)((?:\.resolve\(\))?)\.with_name\("{stem}\.py"\)',
            rf'Path(__file__)\1.parents[1] / "{FAKES}" / "{stem}.py"',
            text,
        )
    return text


def rewrite_references(text: str, where: dict[str, str]) -> str:
    """References to test modules by path: tests/test_x.py, and `test_x.py` in a docs table."""
    if not where:
        return text
    names = "|".join(re.escape(n) for n in sorted(where, key=len, reverse=True))
    text = re.sub(rf"\btests/({names})\b", lambda m: f"tests/{where[m.group(1)]}", text)
    text = re.sub(rf"`({names})(?=`|::)", lambda m: f"`{where[m.group(1)]}", text)
    modules = "|".join(re.escape(n.removesuffix(".py")) for n in sorted(where, key=len, reverse=True))
    text = re.sub(
        rf"\btests\.({modules})\b", lambda m: "tests." + where[m.group(1) + ".py"][:-3].replace("/", "."), text
    )
    return text


def fake_modules() -> list[str]:
    """The modules in tests/fakes/ but the package itself (fault_roles, ...), by name."""
    return sorted(p.stem for p in (TESTS / FAKES).glob("*.py") if p.name != "__init__.py")


def rewrite_fake_references(text: str) -> str:
    """References to a fake that stood in the root: tests/x.py and tests.x (`python -m tests.x`)."""
    for stem in fake_modules():
        text = re.sub(rf"\btests/{stem}\.py\b", f"tests/{FAKES}/{stem}.py", text)
        text = re.sub(rf"\btests\.{stem}\b", f"tests.{FAKES}.{stem}", text)
    return text


def git_files() -> list[Path]:
    out = subprocess.run(
        ["git", "ls-files", "--cached", "--others", "--exclude-standard"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    return [ROOT / line for line in out.splitlines() if line]


#: Files whose text is never rewritten: this script (its table) and its test (the samples).
SKIP = ("scripts/migrate_tests.py", "tests/test_test_layout.py", "tests/meta/test_test_layout.py")
TEXT_SUFFIXES = (".py", ".md", ".toml", ".cfg", ".ini", ".txt", ".yaml", ".yml", ".sh", "")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--check", action="store_true", help="say what would move; exit 1 if anything is left")
    args = parser.parse_args(argv)
    planned = moves()
    if args.check:
        for source, target in planned.items():
            print(f"would move {source.relative_to(ROOT)} -> {target.relative_to(ROOT)}")
        return 1 if planned else 0
    for source, target in planned.items():
        why = folder_for(source)[1] if source.name.startswith("test_") else "the tests' fakes"
        target.parent.mkdir(parents=True, exist_ok=True)
        init = target.parent / "__init__.py"
        if not init.exists() and target.name != "__init__.py":
            init.write_text("")
            subprocess.run(["git", "add", str(init)], cwd=ROOT, check=True)
        tracked = subprocess.run(["git", "ls-files", "--error-unmatch", str(source)], cwd=ROOT, capture_output=True)
        if tracked.returncode == 0:
            subprocess.run(["git", "mv", str(source), str(target)], cwd=ROOT, check=True)
        else:
            source.rename(target)
        print(f"moved {source.relative_to(ROOT)} -> {target.relative_to(ROOT)} ({why})")
    where = located()
    for target in planned.values():
        if target.relative_to(ROOT).as_posix() in SKIP:
            continue
        folder = target.parent.relative_to(TESTS).as_posix().split("/")[0]
        text = target.read_text()
        new = rewrite_moved(text, folder, where)
        if new != text:
            target.write_text(new)
    moved = set(planned.values())
    for path in sorted(TESTS.glob("*/**/*.py")):
        rel = path.relative_to(ROOT).as_posix()
        if path in moved or rel in SKIP:
            continue
        text = path.read_text()
        new = rewrite_imports(text, path.relative_to(TESTS).parts[0], where)
        if new != text:
            path.write_text(new)
            print(f"mended the imports of {rel}")
    changed = 0
    for path in git_files():
        rel = path.relative_to(ROOT).as_posix()
        if rel in SKIP or path.suffix not in TEXT_SUFFIXES or not path.is_file() or rel.startswith(".git/"):
            continue
        try:
            text = path.read_text()
        except UnicodeDecodeError:
            continue
        new = rewrite_fake_references(rewrite_references(text, where))
        if new != text:
            path.write_text(new)
            changed += 1
    print(f"rewrote references in {changed} file(s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

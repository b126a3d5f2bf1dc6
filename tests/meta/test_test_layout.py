"""Tests mirror the code: every test module sits in the folder of the layer it tests (tests/core,
tests/server, ...), a behaviour suite's folder (tests/behaviour) or tests/meta, tests/benchmarks;
the tests/ root holds only what every folder shares (conftest.py's fixtures, helpers.py), and the
fakes are tests/fakes. scripts/migrate_tests.py places a new flat test module (`--check` lists any)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[2]
TESTS = ROOT / "tests"
#: What may stand in the tests/ root besides folders.
ROOT_FILES = {"__init__.py", "conftest.py", "helpers.py"}


def migrate_tests() -> ModuleType:
    spec = importlib.util.spec_from_file_location("migrate_tests", ROOT / "scripts" / "migrate_tests.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def test_no_python_module_sits_in_the_tests_root_but_the_shared_ones() -> None:
    flat = sorted(p.name for p in TESTS.glob("*.py") if p.name not in ROOT_FILES)
    assert not flat, f"move these into their layer's folder (python scripts/migrate_tests.py): {flat}"
    assert (TESTS / "conftest.py").is_file(), "conftest.py stays in the root: its fixtures apply to every folder"


def test_every_test_folder_is_a_package_and_its_names_are_unique() -> None:
    """Each folder has an __init__.py, so pytest imports tests.server.test_x, not a bare test_x."""
    folders = {p.parent for p in TESTS.rglob("test_*.py")}
    assert len(folders) >= 8, folders
    assert not [f for f in folders if not (f / "__init__.py").is_file()]
    names = [p.name for p in TESTS.rglob("test_*.py")]
    assert len(names) == len(set(names)), "two test modules share a name: the table in migrate_tests maps by name"


def test_the_migration_has_nothing_left_and_knows_every_folder() -> None:
    module = migrate_tests()
    assert module.moves() == {}
    known = set(module.FOLDERS.values()) | {f for _, f in module.PREFIXES} | set(module.LAYER_FOLDERS.values())
    folders = {p.parent.relative_to(TESTS).parts[0] for p in TESTS.rglob("test_*.py")}
    assert folders <= known | {"fakes"}, folders - known


def test_the_migration_rewrites_a_moved_modules_references(tmp_path: Path) -> None:
    module = migrate_tests()
    text = (
        "from .helpers import MAX_RANGE\n"
        "from .fakes import start_recorded_camera\n"
        "from drvs_bench.fakes import AckingCamera\n"
        "from .test_registry import Clock\n"
        "ROOT = Path(__file__).resolve().parents[1]\n"
        'SMALL = Path(__file__).parent / "scenarios" / "small_room.yaml"\n'
        'ROLES = Path(__file__).with_name("fault_roles.py")\n'
    )
    out = module.rewrite_moved(text, "server", {"test_registry.py": "server/test_registry.py"})
    assert out == (
        "from tests.helpers import MAX_RANGE\n"
        "from tests.fakes import start_recorded_camera\n"
        "from tests.fakes import AckingCamera\n"
        "from tests.server.test_registry import Clock\n"
        "ROOT = Path(__file__).resolve().parents[2]\n"
        'SMALL = Path(__file__).parents[1] / "scenarios" / "small_room.yaml"\n'
        'ROLES = Path(__file__).parents[1] / "fakes" / "fault_roles.py"\n'
    )
    assert module.rewrite_moved(text, "benchmarks", {}).count("from drvs_bench.fakes import") == 1
    # The imports part runs over every module in a folder on every run: a second pass changes nothing.
    mended = module.rewrite_imports(text, "server", {})
    assert "from tests.helpers import" in mended and "parents[1]" in mended
    assert module.rewrite_imports(mended, "server", {}) == mended
    assert "from drvs.tools.fakes import" in module.rewrite_imports(text, "fakes", {})
    where = {"test_claims.py": "server/test_claims.py"}
    doc = "see tests/test_claims.py and `test_claims.py::test_a` and tests.test_claims; tests/server/test_claims.py"
    once = module.rewrite_references(doc, where)
    assert once == (
        "see tests/server/test_claims.py and `server/test_claims.py::test_a` and tests.server.test_claims; "
        "tests/server/test_claims.py"
    )
    assert module.rewrite_references(once, where) == once  # a second pass changes nothing
    # A stand-in process that stood beside the tests is in tests/fakes now.
    assert "fault_roles" in module.fake_modules()
    fake = module.rewrite_fake_references("python tests/fault_roles.py; python -m tests.fault_roles")
    assert fake == "python tests/fakes/fault_roles.py; python -m tests.fakes.fault_roles"
    assert module.rewrite_fake_references(fake) == fake


def test_a_new_flat_test_is_placed_by_its_name_or_its_imports(tmp_path: Path) -> None:
    module = migrate_tests()
    assert module.folder_for(tmp_path / "test_bench_ros2.py")[0] == "benchmarks"
    assert module.folder_for(tmp_path / "test_server_rooms.py")[0] == "server"
    guess = tmp_path / "test_whatever.py"
    guess.write_text("from drvs.camera.node import CameraNode\nfrom drvs.camera.config import load_config\n")
    folder, why = module.folder_for(guess)
    assert folder == "camera" and "guessed" in why

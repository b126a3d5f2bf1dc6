"""scripts/migrate_layers.py's rewriting, on samples of each kind of reference (the script skips this
file: its samples name the old paths on purpose)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[2]


def script() -> ModuleType:
    spec = importlib.util.spec_from_file_location("migrate_layers", ROOT / "scripts" / "migrate_layers.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["migrate_layers"] = module
    spec.loader.exec_module(module)
    return module


def rewritten(rel: str, text: str) -> str:
    m = script()
    once = m.rewrite(ROOT / rel, text)
    assert m.rewrite(ROOT / rel, once) == once  # idempotent
    return str(once)


def test_every_flat_module_has_one_new_home() -> None:
    m = script()
    assert len(set(m.MAPPING.values())) == len(m.MAPPING)
    assert all(new.rpartition(".")[0] in m.LAYERS for new in m.MAPPING.values())
    assert set(m.SHIMS) <= set(m.MAPPING)


def test_dotted_names_paths_and_strings() -> None:
    text = (
        "import drvs.geometry as g\n"
        "from drvs.registry import Registry\n"
        'patch("drvs.tracking.Tracker.step")\n'
        "python -m drvs.demo --help; see src/drvs/fusion.py and drvs/_cli.py\n"
        "drvs.server.registry drvs.live.liveview drvs.model_type drvs_bench.registry /drvs/registry\n"
    )
    assert rewritten("tests/x.py", text) == (
        "import drvs.core.geometry as g\n"
        "from drvs.server.registry import Registry\n"
        'patch("drvs.server.tracking.Tracker.step")\n'
        "python -m drvs.tools.demo --help; see src/drvs/server/fusion.py and drvs/wire/_cli.py\n"
        "drvs.server.registry drvs.live.liveview drvs.model_type drvs_bench.registry /drvs/registry\n"
    )


def test_from_drvs_import_splits_by_package() -> None:
    text = (
        "from drvs import DrvsClient, _grpc, errors as e\n"
        "def f():\n"
        "    from drvs import (\n"
        "        liveview,  # the hub\n"
        "        sim,\n"
        "    )\n"
        'code = "from drvs import registry, sim\\n"\n'
        "from drvs import sim\n"
    )
    assert rewritten("src/drvs/server/x.py", text) == (
        "from drvs import DrvsClient\n"
        "from drvs.wire import _grpc\n"
        "from drvs.core import errors as e\n"
        "def f():\n"
        "    from drvs.live import liveview\n"
        "    from drvs import sim\n"
        'code = "from drvs.server import registry; from drvs import sim\\n"\n'
        "from drvs import sim\n"
    )


def test_relative_imports_that_reach_a_moved_module_become_absolute() -> None:
    text = "from ..registry import Registry\nfrom .. import fusion, sim\nfrom .config import X\nfrom .. import sim\n"
    assert rewritten("src/drvs/server/x.py", text) == (
        "from drvs.server.registry import Registry\n"
        "from drvs.server import fusion\nfrom drvs import sim\n"
        "from .config import X\nfrom .. import sim\n"
    )


def test_a_line_marked_keep_is_left_alone_and_pyproject_gets_the_packages() -> None:
    assert rewritten("docs/x.md", "drvs.model stays <!-- migrate_layers: keep -->\ndrvs.model\n") == (
        "drvs.model stays <!-- migrate_layers: keep -->\ndrvs.core.model\n"
    )
    toml = 'packages = ["drvs", "drvs.v1", "drvs.server"]\ndrvs-demo = "drvs._entry:demo"\n'
    assert rewritten("pyproject.toml", toml) == (
        'packages = ["drvs", "drvs.core", "drvs.wire", "drvs.live", "drvs.tools", "drvs.v1", "drvs.server"]\n'
        'drvs-demo = "drvs.tools._entry:demo"\n'
    )

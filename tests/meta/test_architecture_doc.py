"""docs/architecture.md against the code: every file it names exists, and every `Class.member`
and `module.function` it names resolves in the source (by reading it, not importing it), so the
request's walk through the rooms cannot drift from the code unnoticed."""

from __future__ import annotations

import ast
import re
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "architecture.md"
SOURCES = (ROOT / "src" / "drvs", ROOT / "benchmarks" / "drvs_bench")


def index() -> tuple[dict[str, set[str]], dict[str, set[str]], set[str]]:
    """(class name -> its members, module basename -> its top-level names, every .py path relative
    to src/drvs or benchmarks/, as the doc writes them)."""
    classes: dict[str, set[str]] = defaultdict(set)
    modules: dict[str, set[str]] = defaultdict(set)
    paths: set[str] = set()
    for base in SOURCES:
        for path in base.rglob("*.py"):
            if "v1" in path.relative_to(base).parts[:1]:
                continue
            rel = path.relative_to(base).as_posix()
            paths.update({rel, path.name, f"{base.name}/{rel}"})
            tree = ast.parse(path.read_text())
            names = modules[path.stem]
            for node in tree.body:
                if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
                    names.add(node.name)
                elif isinstance(node, ast.Assign | ast.AnnAssign):
                    for target in node.targets if isinstance(node, ast.Assign) else [node.target]:
                        if isinstance(target, ast.Name):
                            names.add(target.id)
                if isinstance(node, ast.ClassDef):
                    members = classes[node.name]
                    for item in ast.walk(node):
                        if isinstance(item, ast.FunctionDef | ast.AsyncFunctionDef):
                            members.add(item.name)
                        elif isinstance(item, ast.Attribute) and isinstance(item.value, ast.Name):
                            if item.value.id in ("self", "cls"):
                                members.add(item.attr)
                        elif isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name):
                            members.add(item.target.id)
                        elif isinstance(item, ast.Assign):
                            members.update(t.id for t in item.targets if isinstance(t, ast.Name))
    return classes, modules, paths


def named() -> list[str]:
    return re.findall(r"`([^`\n]+)`", DOC.read_text())


def test_every_file_the_architecture_names_exists() -> None:
    _, _, paths = index()
    files = {t for t in named() if re.fullmatch(r"[\w/]+\.py", t)}
    assert len(files) > 20, "docs/architecture.md names fewer files than it did"
    missing = sorted(f for f in files if f not in paths and not (ROOT / f).exists())
    assert not missing, f"docs/architecture.md names files that do not exist: {missing}"


def test_every_class_member_and_module_function_the_architecture_names_resolves() -> None:
    classes, modules, _ = index()
    checked = 0
    wrong = []
    for token in named():
        m = re.fullmatch(r"([A-Za-z_]\w*)\.([A-Za-z_]\w*)(?:\(\))?", token)
        if not m:
            continue
        owner, member = m.groups()
        if member in ("py", "proto"):
            continue
        if owner in classes:
            checked += 1
            if member not in classes[owner]:
                wrong.append(token)
        elif owner in modules and owner[0].islower():
            checked += 1
            if member not in modules[owner]:
                wrong.append(token)
    assert checked > 40, f"docs/architecture.md names only {checked} functions of the code"
    assert not wrong, f"docs/architecture.md names what the code does not have: {sorted(set(wrong))}"

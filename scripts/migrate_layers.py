"""Issue 29, item 1: layers as folders (folder = layer = extra). Moves src/drvs's flat modules into
drvs.core, drvs.wire, drvs.server, drvs.live and drvs.tools, and rewrites every reference to them.

    python scripts/migrate_layers.py            # move the files, rewrite the references, tidy imports (ruff)
    python scripts/migrate_layers.py --check    # say what it would change; exit 1 if anything is left

Re-runnable and idempotent: a module already moved is skipped, and the references are rewritten by
pattern over every text file git knows (tracked, or untracked and not ignored), so new modules written
since (a server split's drvs/server/*.py importing drvs.registry, say) are rewritten too. What it rewrites:

- dotted module names anywhere (imports, strings, comments, docs, pyproject's entry points, Dockerfiles):
  `drvs.geometry`, `drvs.geometry.Homography`, `patch("drvs.registry.X")`, `python -m drvs.demo`;
- `from drvs import a, b as c` (split into one import per package when the names move apart);
- relative imports inside src/drvs that reach a moved module (`from ..registry import X`, `from . import x`
  in a flat module): made absolute; a file is moved only after its own relative imports were made absolute;
- file paths `src/drvs/geometry.py` and `drvs/geometry.py`;
- pyproject.toml's [tool.setuptools] packages (the new packages are added).

A line that names an old path on purpose carries `migrate_layers: keep` (in a comment) and is left alone.

It leaves a deprecated alias at the old path of the modules robot programmers import (SHIMS): a tiny module
that warns and puts the new module in its place in sys.modules, so `import drvs.model`, `drvs.model.X` and
`from drvs.model import X` keep working, on the very same module object. Nothing in the repository imports
them (the rewrite sees to that; the shims themselves carry SHIM_MARK and are never rewritten).
"""

from __future__ import annotations

import argparse
import difflib
import re
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src"

#: Each flat module's new package. A module keeps its name; only its folder (its layer) changes.
LAYERS: dict[str, tuple[str, ...]] = {
    # Pure logic: no gRPC, no I/O beyond reading a file a person wrote. Imports nothing above it.
    "drvs.core": (
        "errors",
        "geometry",
        "model",
        "object_types",
        "filters",
        "backoff",
        "mobile",
        "net",
        "homography_file",
        "_files",
        "imaging",
        "frames",
    ),
    # What every role stands on to run on the network: gRPC, TLS, the wire<->domain conversion, health,
    # metrics, logs, the entry points' shared set-up. Imports the core only.
    "drvs.wire": (
        "_grpc",
        "_service",
        "health",
        "channels",
        "security",
        "convert",
        "callback",
        "request_stream",
        "report_auth",
        "report_bounds",
        "metrics",
        "logs",
        "_cli",
    ),
    # Used by the server alone (and by the tools and tests above it).
    "drvs.server": ("registry", "fusion", "tracking", "etcd", "etcd_auth"),
    # The `live` extra: the live view's hub and token gate, the Foxglove client, drvs-replay.
    "drvs.live": ("liveview", "liveview_gate", "foxglove_client", "replay"),
    # Tools: the console scripts' launcher, process launching, the demo, certificates, the byte meter.
    "drvs.tools": ("_entry", "launch", "demo", "certs", "meter"),
}

#: old module -> new module
MAPPING: dict[str, str] = {f"drvs.{name}": f"{package}.{name}" for package, names in LAYERS.items() for name in names}

#: Old paths robot programmers (third parties) import: a deprecated alias stays there for one release.
SHIMS = ("drvs.model", "drvs.geometry", "drvs.errors", "drvs.security", "drvs.object_types")
SHIM_MARK = "# drvs-layers-shim: a deprecated alias, not rewritten by scripts/migrate_layers.py"

#: A line that names an old path on purpose (the aliases' tests and docs) carries this, and is kept.
KEEP = "migrate_layers: keep"

PACKAGE_DOCS = {
    "drvs.core": "The core: pure logic (geometry, the domain model, the object-type grammar, filters, errors,\n"
    "addresses, backoff). It imports nothing above it (docs/architecture.md, Layers).",
    "drvs.wire": "The wire: the gRPC plumbing every role shares (status codes, services, channels, security,\n"
    "wire<->domain conversion, report streams, health, metrics, logs). It imports the core only.",
    "drvs.live": "The live view and recordings: the `live` extra (pip install 'drvs[live]'): the Foxglove hub\n"
    "and its token gate, the Foxglove client, drvs-replay. Its libraries load only when a view starts.",
    "drvs.tools": "The tools: the console scripts' launcher (_entry), process launching, the demo, certificates,\n"
    "the byte meter. They may use every layer below them.",
}

NEW_PACKAGES = tuple(LAYERS)
SKIP_PREFIXES = ("src/drvs/v1/", "scripts/migrate_layers.py", "tests/meta/test_migrate_layers.py", ".git/")
SKIP_SUFFIXES = (".png", ".jpg", ".jpeg", ".gif", ".mcap", ".onnx", ".npz", ".npy", ".pb", ".whl", ".mp4", ".avi")

_NAMES = "|".join(sorted((re.escape(old.split(".", 1)[1]) for old in MAPPING), key=len, reverse=True))
DOTTED = re.compile(rf"(?<![\w.])drvs\.({_NAMES})(?!\w)")
SRC_PATH = re.compile(rf"(?<![\w])src/drvs/({_NAMES})(?![\w/])")
FILE_PATH = re.compile(rf"(?<![\w./])drvs/({_NAMES})\.py\b")
# `from drvs import a, b as c`: a statement at a line's start, or inside a string or inline code.
FROM_DRVS = re.compile(
    r"(?P<prefix>^[ \t]*|[\"'`])from drvs import (?P<names>\([^)]*\)|\w+(?: as \w+)?(?:[ \t]*,[ \t]*\w+(?: as \w+)?)*)",
    re.MULTILINE,
)
RELATIVE = re.compile(r"^(?P<indent>[ \t]*)from (?P<dots>\.+)(?P<module>[\w.]*) import ", re.MULTILINE)


def new_name(old_short: str) -> str:
    return MAPPING[f"drvs.{old_short}"]


def module_path(module: str) -> Path:
    return SRC.joinpath(*module.split(".")).with_suffix(".py")


def module_of(path: Path) -> tuple[str, str]:
    """A file under src/ -> (its module name, the package its relative imports start from)."""
    parts = list(path.relative_to(SRC).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
        return ".".join(parts), ".".join(parts)
    return ".".join(parts), ".".join(parts[:-1])


def is_shim(path: Path) -> bool:
    try:
        return SHIM_MARK in path.read_text()
    except (OSError, UnicodeDecodeError):
        return False


# --- rewriting ------------------------------------------------------------------------------------------


def rewrite_relative(text: str, package: str, *, all_relative: bool) -> str:
    """Relative imports that reach a moved module (or, with all_relative, every one) made absolute."""

    def absolute(match: re.Match[str]) -> str:
        level = len(match["dots"])
        base = package.split(".")
        if level - 1 > len(base) - 1:
            return match[0]
        base = base[: len(base) - level + 1]
        target = ".".join([*base, match["module"]] if match["module"] else base)
        if all_relative or target in MAPPING or (target == "drvs" and _imports_moved(text, match.end())):
            return f"{match['indent']}from {target} import "
        return match[0]

    return RELATIVE.sub(absolute, text)


def _imports_moved(text: str, start: int) -> bool:
    """Whether `from drvs import <the names at start>` names a moved module."""
    end = text.find(")", start) if text[start : start + 1] == "(" else text.find("\n", start)
    names, _ = _split_names(text[start : end + 1 if text[start : start + 1] == "(" else (end if end >= 0 else None)])
    return any(f"drvs.{name.split(' as ')[0].strip()}" in MAPPING for name in names)


def _split_names(names: str) -> tuple[list[str], str]:
    """The names of `from drvs import ...` (parenthesised or not), and whether it was parenthesised."""
    paren = names.startswith("(")
    body = names[1:-1] if paren else names
    body = re.sub(r"#[^\n]*", "", body)
    return [" ".join(n.split()) for n in body.split(",") if n.strip()], "(" if paren else ""


def rewrite_from_drvs(text: str, *, python: bool) -> str:
    def split(match: re.Match[str]) -> str:
        names, _ = _split_names(match["names"])
        groups: dict[str, list[str]] = {}
        for name in names:
            module = name.split(" as ")[0].strip()
            package = new_name(module).rpartition(".")[0] if f"drvs.{module}" in MAPPING else "drvs"
            groups.setdefault(package, []).append(name)
        if list(groups) == ["drvs"]:
            return match[0]
        prefix = match["prefix"]
        statements = [f"from {package} import {', '.join(group)}" for package, group in groups.items()]
        if prefix.strip() == "" and python:
            return prefix + ("\n" + prefix).join(statements)
        return prefix + "; ".join(statements)

    return FROM_DRVS.sub(split, text)


def rewrite_pyproject(text: str) -> str:
    match = re.search(r"^packages = \[(?P<list>[^\]]*)\]", text, re.MULTILINE)
    if match is None:
        return text
    present = re.findall(r'"([\w.]+)"', match["list"])
    missing = [p for p in NEW_PACKAGES if p not in present]
    if not missing:
        return text
    names = [*present[:1], *missing, *present[1:]] if present[:1] == ["drvs"] else [*present, *missing]
    return text[: match.start("list")] + ", ".join(f'"{n}"' for n in names) + text[match.end("list") :]


def rewrite(path: Path, text: str) -> str:
    """The file's text with the references rewritten; a line carrying KEEP is left as it is."""
    kept: list[str] = []

    def keep(match: re.Match[str]) -> str:
        kept.append(match[0])
        return f"\0KEEP{len(kept) - 1}\0"

    text = re.sub(rf"^[^\n]*{re.escape(KEEP)}[^\n]*$", keep, text, flags=re.MULTILINE)
    text = _rewrite(path, text)
    return re.sub(r"\0KEEP(\d+)\0", lambda m: kept[int(m[1])], text)


def _rewrite(path: Path, text: str) -> str:
    rel = path.relative_to(ROOT).as_posix()
    python = path.suffix in (".py", ".pyi")
    if python and rel.startswith("src/drvs/"):
        _, package = module_of(path)
        text = rewrite_relative(text, package, all_relative=False)
    text = rewrite_from_drvs(text, python=python)
    text = DOTTED.sub(lambda m: new_name(m[1]), text)
    text = SRC_PATH.sub(lambda m: "src/" + new_name(m[1]).replace(".", "/"), text)
    text = FILE_PATH.sub(lambda m: new_name(m[1]).replace(".", "/") + ".py", text)
    if rel == "pyproject.toml":
        text = rewrite_pyproject(text)
    return text


# --- the files --------------------------------------------------------------------------------------------


def text_files() -> list[Path]:
    listed = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        cwd=ROOT,
        capture_output=True,
        check=True,
    ).stdout.decode()
    files = []
    for rel in sorted(set(filter(None, listed.split("\0")))):
        path = ROOT / rel
        if rel.startswith(SKIP_PREFIXES) or rel.endswith(SKIP_SUFFIXES) or not path.is_file() or path.is_symlink():
            continue
        files.append(path)
    return files


def shim_text(old: str, new: str) -> str:
    package, _, name = new.rpartition(".")
    return f'''"""Deprecated alias of {new} (the layers as folders, docs/architecture.md).

{old} moved to {new}; this alias goes in the next release."""

{SHIM_MARK}
import sys
import warnings
from typing import TYPE_CHECKING

from {package} import {name} as _new

if TYPE_CHECKING:
    from {new} import *  # noqa: F403

warnings.warn("{old} is deprecated: import {new}", DeprecationWarning, stacklevel=2)
# `import {old}` and `from {old} import X` get the new module itself.
sys.modules[__name__] = _new
'''


def package_init(package: str) -> str:
    return f'"""{PACKAGE_DOCS[package]}"""\n'


def git(*args: str) -> None:
    subprocess.run(["git", *args], cwd=ROOT, check=True)


def plan_moves() -> list[tuple[str, Path, Path]]:
    """(old module, old path, new path) for each module still at its old path."""
    moves = []
    for old, new in MAPPING.items():
        source, target = module_path(old), module_path(new)
        if not source.exists() or is_shim(source):
            continue
        if target.exists():
            sys.exit(f"{source.relative_to(ROOT)} and {target.relative_to(ROOT)} both exist: merge them by hand first")
        moves.append((old, source, target))
    return moves


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="only say what would change; exit 1 if anything")
    parser.add_argument("--no-ruff", action="store_true", help="do not tidy the rewritten imports with ruff")
    args = parser.parse_args()
    pending: list[str] = []

    moves = plan_moves()
    for package in NEW_PACKAGES:
        init = module_path(package).with_suffix("") / "__init__.py"
        if not init.exists():
            pending.append(f"create {init.relative_to(ROOT)}")
            if not args.check:
                init.parent.mkdir(parents=True, exist_ok=True)
                init.write_text(package_init(package))
                git("add", str(init.relative_to(ROOT)))
    for _old, source, target in moves:
        pending.append(f"git mv {source.relative_to(ROOT)} {target.relative_to(ROOT)}")
        if not args.check:
            # Its own relative imports are made absolute first, against the package it leaves.
            text = source.read_text()
            fixed = rewrite_relative(text, module_of(source)[1], all_relative=True)
            if fixed != text:
                source.write_text(fixed)
            git("mv", str(source.relative_to(ROOT)), str(target.relative_to(ROOT)))
    for old in SHIMS:
        source = module_path(old)
        if not source.exists() and module_path(MAPPING[old]).exists():
            pending.append(f"create the deprecated alias {source.relative_to(ROOT)} -> {MAPPING[old]}")
            if not args.check:
                source.write_text(shim_text(old, MAPPING[old]))
                git("add", str(source.relative_to(ROOT)))

    changed: list[Path] = []
    for path in text_files():
        if path.suffix == ".py" and is_shim(path):
            continue
        try:
            text = path.read_text()
        except UnicodeDecodeError:
            continue
        new = rewrite(path, text)
        if new != text:
            changed.append(path)
            lines = difflib.unified_diff(text.splitlines(), new.splitlines(), lineterm="", n=0)
            count = sum(1 for line in lines if line.startswith("-") and not line.startswith("---"))
            pending.append(f"rewrite {path.relative_to(ROOT)} ({count} line(s))")
            if not args.check:
                path.write_text(new)

    for line in pending:
        print(line)
    if args.check:
        print(f"{len(pending)} change(s) pending" if pending else "nothing to do: the layers are in place")
        return 1 if pending else 0

    python_files = [str(p) for p in changed if p.suffix == ".py"]
    if python_files and not args.no_ruff:
        ruff = shutil.which("ruff") or str(Path(sys.executable).with_name("ruff"))
        if Path(ruff).exists() or shutil.which(ruff):
            # Imports moved between packages: sort them again (isort rules only), then format.
            subprocess.run([ruff, "check", "--fix", "--select", "I", "--quiet", *python_files], cwd=ROOT, check=False)
            subprocess.run([ruff, "format", "--quiet", *python_files], cwd=ROOT, check=False)
        else:
            print("ruff not found: run `ruff check --fix --select I` and `ruff format` on the rewritten files")
    print(f"done: {len(moves)} module(s) moved, {len(changed)} file(s) rewritten")
    return 0


if __name__ == "__main__":
    sys.exit(main())

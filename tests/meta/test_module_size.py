"""No module over about 700 lines: a module that grows past it holds more than one job and is split
by job (the server's rooms, the robot client's rooms). Generated code (protoc's and grpcio-tools'
output, which says so in its first lines) is left out; so are the modules in ALLOWED, each with why.
"""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
#: Where the project's own modules live (scripts too: they are code people carry on).
TREES = ("src", "benchmarks", "scripts")
MAX_LINES = 700
#: A generated module says so in its first lines.
GENERATED_MARKS = ("DO NOT EDIT",)
#: Modules allowed past MAX_LINES for now, relative to ROOT, and why.
ALLOWED: dict[str, str] = {}


def generated(path: Path) -> bool:
    with path.open() as f:
        head = "".join(f.readline() for _ in range(3))
    return any(mark in head for mark in GENERATED_MARKS)


def line_counts() -> dict[str, int]:
    counts: dict[str, int] = {}
    for tree in TREES:
        for path in sorted((ROOT / tree).rglob("*.py")):
            if not generated(path):
                counts[path.relative_to(ROOT).as_posix()] = len(path.read_text().splitlines())
    return counts


def test_no_module_is_over_700_lines() -> None:
    counts = line_counts()
    assert "src/drvs/server/server.py" in counts, "the scan found none of the project's modules"
    over = {path: n for path, n in counts.items() if n > MAX_LINES and path not in ALLOWED}
    assert not over, f"modules over {MAX_LINES} lines (split them by job): {over}"


def test_generated_code_is_recognised_and_left_out() -> None:
    generated_modules = [p for p in (ROOT / "src" / "drvs" / "v1").glob("*.py") if p.name.endswith("_pb2.py")]
    assert generated_modules and all(generated(p) for p in generated_modules)
    assert not generated(ROOT / "src" / "drvs" / "server" / "server.py")


def test_every_allowed_module_exists_and_still_needs_it() -> None:
    """An allowance outlives its reason once the module is split: then it goes."""
    counts = line_counts()
    stale = [path for path in ALLOWED if counts.get(path, 0) <= MAX_LINES]
    assert not stale, f"no longer over {MAX_LINES} lines (or gone): drop from ALLOWED: {stale}"

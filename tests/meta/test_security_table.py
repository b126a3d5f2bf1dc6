"""docs/operations.md's security model (who may do what, with which credential) names, on every
row, the tests with real processes that check it: each named test must exist, so a row cannot
point at nothing and a renamed or deleted test cannot leave a rule unchecked unnoticed."""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "operations.md"
HEADER = "| who | may | with | default (no credentials configured) | checked by (tests/) |"


def security_rows() -> list[list[str]]:
    lines = DOC.read_text().splitlines()
    start = lines.index(HEADER) + 2  # past the header and its separator
    rows = []
    for line in lines[start:]:
        if not line.startswith("|"):
            break
        rows.append([cell.strip() for cell in line.strip().strip("|").split("|")])
    return rows


def defined_tests(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    return {
        n.name
        for n in tree.body
        if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef) and n.name.startswith("test_")
    }


def test_every_row_of_the_security_model_names_tests_that_exist() -> None:
    rows = security_rows()
    assert len(rows) >= 10, "the security model table is shorter than the rules it had"
    for row in rows:
        assert len(row) == 5, f"a row of the security model lacks its 'checked by' cell: {row[:2]}"
        names = re.findall(r"`([^`]+)`", row[4])
        assert names, f"the security model row {row[0]!r} ({row[1][:60]}) names no test"
        for name in names:
            module, _, function = name.partition("::")
            path = ROOT / "tests" / module
            assert path.is_file(), f"row {row[0]!r}: tests/{module} does not exist"
            if function:
                assert function in defined_tests(path), f"row {row[0]!r}: tests/{module} has no {function}"
            else:
                assert defined_tests(path), f"row {row[0]!r}: tests/{module} holds no test"

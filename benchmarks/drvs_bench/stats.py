"""Repeated, interleaved runs and how their figures are published: median and spread, never one run.

A shared 2-core machine drifts: a figure from one run of mode A and a later run of mode B mixes the
difference between the modes with whatever else the machine did in between. The benchmarks run the
modes interleaved (A B C A B C …) for several rounds and publish, for each figure and for each ratio
(taken within a round, so both sides saw the same machine), the median and the spread (min, max).
"""

from __future__ import annotations

import statistics
import sys
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any, Literal, TypeVar

T = TypeVar("T")

#: Rounds of the interleaved modes: a full run and a `--quick` smoke run.
FULL_ROUNDS = 5
QUICK_ROUNDS = 3


def interleaved(modes: Sequence[T], rounds: int) -> Iterator[tuple[int, T]]:
    """(round, mode) in the order A B C A B C …: each round runs every mode once."""
    for r in range(rounds):
        for mode in modes:
            yield r, mode


def out_dir(given: Path | None) -> Path:
    """Where a benchmark writes: --out, else a new bench-YYYYmmdd-HHMMSS folder here."""
    return given or Path(time.strftime("bench-%Y%m%d-%H%M%S"))


def measured(name: str, work: Callable[[], T]) -> T | None:
    """`work()`'s result, or None when its work check failed (WorkMismatch), said on stderr as
    `drvs-bench NAME: FAILED: …` (the benchmark then exits 1)."""
    try:
        return work()
    except WorkMismatch as exc:
        print(f"drvs-bench {name}: FAILED: {exc}", file=sys.stderr)
        return None


def rounds(quick: bool) -> int:
    """Rounds of a comparison: QUICK_ROUNDS with --quick, else FULL_ROUNDS."""
    return QUICK_ROUNDS if quick else FULL_ROUNDS


def describe(values: Iterable[float]) -> dict[str, Any]:
    """Median, min, max and the spread (max - min) of one figure over the rounds, and the values."""
    vs = [float(v) for v in values]
    if not vs:
        raise ValueError("describe: no values (no round produced this figure)")
    return {
        "median": statistics.median(vs),
        "min": min(vs),
        "max": max(vs),
        "spread": max(vs) - min(vs),
        "runs": vs,
    }


def publish(out: dict[str, Any], key: str, values: Iterable[float]) -> dict[str, Any]:
    """Write `key` (the median, so existing keys keep one number), `key_median`, `key_spread` ([min, max])
    and `key_runs` into `out`; returns the description."""
    d = describe(values)
    out[key] = d["median"]
    out[f"{key}_median"] = d["median"]
    out[f"{key}_spread"] = [d["min"], d["max"]]
    out[f"{key}_runs"] = d["runs"]
    return d


Verdict = Literal["met", "missed", "spread crosses target"]


def verdict(values: Iterable[float], target: float, higher_is_better: bool = True) -> Verdict:
    """Whether every round meets the target, none does, or the spread crosses it."""
    vs = [float(v) for v in values]
    ok = [(v >= target) if higher_is_better else (v <= target) for v in vs]
    if all(ok):
        return "met"
    if not any(ok):
        return "missed"
    return "spread crosses target"


def per_round_ratio(
    rounds: Sequence[dict[str, dict[str, Any]]], numerator: Callable[[dict[str, Any]], float], num_mode: str,
    den_mode: str, denominator: Callable[[dict[str, Any]], float] | None = None,
) -> list[float]:  # fmt: skip
    """The ratio of a figure of `num_mode` over one of `den_mode`, within each round."""
    den = denominator or numerator
    return [numerator(r[num_mode]) / den(r[den_mode]) for r in rounds]


class WorkMismatch(RuntimeError):
    """A run did not do the work it was meant to: its figures would compare unlike with unlike."""


def check_work(name: str, expected: dict[str, float], got: dict[str, float]) -> None:
    """Raise WorkMismatch naming every count that differs from what the mode was meant to do."""
    wrong = [f"{k}: expected {expected[k]:g}, got {got.get(k)}" for k in expected if got.get(k) != expected[k]]
    if wrong:
        raise WorkMismatch(f"{name}: the work done does not match, no ratio published: " + "; ".join(wrong))

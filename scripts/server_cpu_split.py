"""One-off breakdown of the server's CPU per request by thread: its event loop's against gRPC's own.

The processes of `drvs-bench fusion --parts cost` (a drvs-server, two drvs-cameras playing the
fusion scene's still discs, and the bare floor's server and cameras), and its robot runs, in turn,
per round: per-camera delivery, fused delivery, the bare floor. Around each run (robot start-up and
warm-up included) the script reads each server thread's CPU from /proc; it prints, per mode, the
server's CPU per request (START to DONE, as the benchmark counts it), the event loop thread's share
of the run's CPU, and that share applied to the CPU per request: the event loop's ms a request,
and the rest (gRPC's poller and event-engine threads). Medians over the rounds, [min, max].

    PYTHONPATH=src:benchmarks .venv/bin/python scripts/server_cpu_split.py [--requests 300] [--rounds 3]

Not a benchmark (no target, no JSON): docs/benchmarks.md ("Cheaper requests") gives its result.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import statistics
import sys
import tempfile
from pathlib import Path

from drvs_bench import fusion_cost

from drvs.tools.launch import ManagedProcess

MODES = ("per_camera", "fused", "bare")


def thread_cpu(pid: int) -> tuple[float, float]:
    """(the main thread's, every other thread's) CPU seconds so far."""
    main = rest = 0.0
    tick = os.sysconf("SC_CLK_TCK")
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            fields = Path(f"/proc/{pid}/task/{tid}/stat").read_text().rsplit(")", 1)[1].split()
        except FileNotFoundError:  # a thread that ended
            continue
        used = (int(fields[11]) + int(fields[12])) / tick
        if int(tid) == pid:
            main += used
        else:
            rest += used
    return main, rest


async def main(requests: int, rounds: int) -> None:
    procs: list[ManagedProcess] = []
    out: dict[str, dict[str, list[float]]] = {m: {"ms": [], "loop_share": []} for m in MODES}
    with tempfile.TemporaryDirectory(prefix="drvs-cpu-split-") as tmp:
        try:
            started = await fusion_cost.start_cost_processes(Path(tmp), procs)
            for r in range(rounds):
                for mode in MODES:
                    pid = started.pids["bare" if mode == "bare" else "server"][0]
                    before = thread_cpu(pid)
                    run = await fusion_cost.run_robot(mode, started.target(mode), requests, started.pids)
                    after = thread_cpu(pid)
                    main_s, rest_s = after[0] - before[0], after[1] - before[1]
                    served = run.get("server_requests", requests)
                    out[mode]["ms"].append(1000 * run["server_cpu_s"] / served)
                    out[mode]["loop_share"].append(main_s / (main_s + rest_s))
                    print(f"round {r + 1}/{rounds} {mode}: done", file=sys.stderr, flush=True)
        finally:
            for proc in reversed(procs):
                await proc.stop()
    for mode in MODES:
        ms, share = out[mode]["ms"], out[mode]["loop_share"]
        loop = [m * s for m, s in zip(ms, share, strict=True)]
        rest = [m * (1 - s) for m, s in zip(ms, share, strict=True)]
        print(
            f"{mode}: server {_fmt(ms)} ms a request; event loop thread {_fmt(loop)} ms "
            f"({_fmt([100 * s for s in share])} %), other threads {_fmt(rest)} ms"
        )


def _fmt(values: list[float]) -> str:
    return f"{statistics.median(values):.2f} [{min(values):.2f}, {max(values):.2f}]"


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--requests", type=int, default=300, help="requests per run, at 30 Hz (default 300)")
    parser.add_argument("--rounds", type=int, default=3, help="rounds of the three modes (default 3)")
    args = parser.parse_args()
    if args.requests < 30 or args.rounds < 1:
        parser.error("--requests: at least 30; --rounds: at least 1")
    asyncio.run(main(args.requests, args.rounds))

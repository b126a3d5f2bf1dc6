"""drvs-bench: `paper` (the paper's comparison), `service` (DRVS's own costs), `load` (many robots at
once), `detectors` (each detector's costs and accuracy), `fusion` (fused delivery: accuracy, tracking,
the server's cost), `mobile` (what mobile cameras cost routing), `cluster` (several servers on etcd),
`liveview` (what the live view and recording cost the office), `ros2` (what drvs-ros2 adds between a
snapshot and a ROS 2 subscriber); the rest are the benchmarks'
internal processes."""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
from pathlib import Path

from drvs.core._files import folder_problem

from .bare import add_bare_parsers
from .cluster import add_cluster_parser
from .fusion import add_fusion_parser
from .helpers import add_helper_parsers
from .liveview import add_liveview_parser
from .load import add_load_parser
from .mobile import add_mobile_parser
from .ros2 import add_ros2_parser
from .stats import measured, out_dir
from .workload import add_workload_arguments, workload_main


def bad_rounds(benchmark: str, rounds: int) -> bool:
    """Whether `--rounds` is negative (0 is the benchmark's default), said on stderr when it is."""
    if rounds < 0:
        print(f"drvs-bench {benchmark}: --rounds must be >= 0 (0: the default)", file=sys.stderr)
    return rounds < 0


def paper_main(args: argparse.Namespace) -> int:
    from .paper import run_paper
    from .paper_figures import FULL_REQUESTS, PEOPLE_FULL_REQUESTS, PEOPLE_QUICK_REQUESTS, QUICK_REQUESTS
    from .stats import FULL_ROUNDS, QUICK_ROUNDS

    requests = args.requests or (QUICK_REQUESTS if args.quick else FULL_REQUESTS)
    rounds = args.rounds or (QUICK_ROUNDS if args.quick else FULL_ROUNDS)
    people = args.people_requests or (PEOPLE_QUICK_REQUESTS if args.quick else PEOPLE_FULL_REQUESTS)
    if requests < 1 or rounds < 1 or not args.rate > 0 or people < 1:
        print("drvs-bench paper: --requests, --rounds, --people-requests and --rate must be > 0", file=sys.stderr)
        return 2
    if args.fused and args.track_only:
        print("drvs-bench paper: --fused and --track-only: choose one", file=sys.stderr)
        return 2
    out = out_dir(args.out)
    result = measured(
        "paper", lambda: asyncio.run(run_paper(out, requests, args.rate, rounds, people, args.fused, args.track_only))
    )
    if result is None:
        return 1
    summary: dict[str, object] = {
        k: v
        for k, v in result.items()
        if (
            "ratio" in k
            or k.endswith(("_over_bare_path", "_over_floor", "_over_per_camera", "_over_receive_floor"))
            or "_per_request_" in k
        )
        and not k.endswith("_runs")
    }
    for mode, data in result["modes"].items():
        summary[f"{mode}_bytes_per_s"] = round(data["bytes_per_s"])
        summary[f"{mode}_payload_bytes_per_s"] = round(data["payload_bytes_per_s"])
        summary[f"{mode}_cpu_s"] = round(data["cpu_s"], 3)
    for mode, data in result.get("people", {}).get("modes", {}).items():
        summary[f"{mode}_cpu_s"] = round(data["cpu_s"], 3)
    summary["targets"] = {k: v["verdict"] for k, v in result["targets"].items()}
    print(json.dumps(summary, indent=1))
    plots = "" if args.track_only else f", {out / 'bandwidth.png'}, {out / 'cpu.png'}"
    print(f"written: {out / 'paper.json'}{plots}")
    return 0


def service_main(args: argparse.Namespace) -> int:
    from .service import run_service

    if bad_rounds("service", args.rounds):
        return 2
    out = out_dir(args.out)
    result = asyncio.run(run_service(out, args.quick, args.rounds))
    # The medians (every figure's spread and rounds are in service.json) and the verdicts.
    keys = [
        k
        for k in result
        if (
            k.endswith(("_over_floor", "_over_echo", "_over_bare_proxy", "_over_100", "_over_20", "_over_20_moving"))
            or k.startswith("camera_marginal_cpu_ms_per_request_")
            or "rss" in k
        )
        and not k.endswith(("_median", "_spread", "_runs"))
    ]
    summary = {k: result[k] for k in keys}
    summary["verdicts"] = {k: v["verdict"] for k, v in result.get("verdicts", {}).items()}
    print(json.dumps(summary, indent=1))
    print(f"written: {out / 'service.json'}, {out / 'latency.png'}")
    return 0


def detectors_main(args: argparse.Namespace) -> int:
    from drvs.detectors import REGISTRY

    from .detectors import INPUTS, run_detectors

    only = [d.strip() for d in args.detectors.split(",") if d.strip()] if args.detectors else None
    unknown = [d for d in only or [] if d not in REGISTRY and d not in INPUTS]
    if only is not None and (unknown or not only):
        print(f"drvs-bench detectors: --detectors: {', '.join(unknown) or 'none'}: name some of "
              f"{', '.join(dict.fromkeys([*REGISTRY, *INPUTS]))}", file=sys.stderr)  # fmt: skip
        return 2
    if bad_rounds("detectors", args.rounds):
        return 2
    out = out_dir(args.out)
    result = measured("detectors", lambda: asyncio.run(run_detectors(out, args.quick, only, args.rounds)))
    if result is None:
        return 1
    # The medians (every figure's spread and rounds are in detectors.json) and the accuracy.
    summary: dict[str, object] = {}
    for name, entry in result["detectors"].items():
        summary[name] = {
            k: (round(v, 4) if isinstance(v, float) else v)
            for k, v in entry.items()
            if not isinstance(v, (str, bool)) and not k.endswith(("_median", "_runs"))
        }
    memory = result.get("memory", {})
    summary["memory"] = {k: v for k, v in memory.items() if not k.endswith(("_median", "_runs"))}
    summary["left_out"] = result["left_out"]
    print(json.dumps(summary, indent=1))
    print(f"written: {out / 'detectors.json'}, {out / 'detectors.png'}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="drvs-bench", description="DRVS benchmarks: JSON and PNG into --out.")
    sub = parser.add_subparsers(dest="bench", required=True)
    p = sub.add_parser("paper", help="the paper's robot CPU and network comparison (Exp. C, D)")
    p.add_argument(
        "--quick", action="store_true", help="3 rounds of 90 requests a mode instead of 5 of 600: a smoke run"
    )
    p.add_argument("--requests", type=int, default=0, help="override the number of requests per run")
    p.add_argument("--rounds", type=int, default=0, help="override the number of interleaved rounds")
    p.add_argument(
        "--people-requests", type=int, default=0, help="override the people modes' requests per run (at 2 Hz)"
    )
    p.add_argument("--rate", type=float, default=30.0, help="requests per second (default 30)")
    p.add_argument(
        "--fused",
        action="store_true",
        help="also run the boxes-only requests with fused delivery (drvs_boxes_fused) in the same rounds",
    )
    p.add_argument(
        "--track-only",
        action="store_true",
        help="run only the fused track and its receive floor (drvs_track, track_floor): "
        "robot_cpu_track_over_receive_floor alone, in a fraction of the time",
    )
    p.add_argument("--out", type=Path, default=None)
    p.set_defaults(func=paper_main)
    s = sub.add_parser("service", help="DRVS's own latency, routing throughput, lookup scaling, CPU and memory")
    s.add_argument("--quick", action="store_true", help="a smoke run: 3 interleaved rounds of short runs (full: 5)")
    s.add_argument("--rounds", type=int, default=0, help="override the number of interleaved rounds")
    s.add_argument("--out", type=Path, default=None)
    s.set_defaults(func=service_main)
    d = sub.add_parser("detectors", help="each detector's ms per frame, camera CPU at 10 requests/s, memory, accuracy")
    d.add_argument("--quick", action="store_true", help="a smoke run: 3 rounds of short runs (full: 5)")
    d.add_argument("--rounds", type=int, default=0, help="override the number of interleaved rounds")
    d.add_argument(
        "--detectors", default=None, help="comma-separated detector prefixes (default: every registered one)"
    )
    d.add_argument("--out", type=Path, default=None)
    d.set_defaults(func=detectors_main)
    add_fusion_parser(sub)
    add_load_parser(sub)
    add_mobile_parser(sub)
    add_cluster_parser(sub)
    add_liveview_parser(sub)
    add_ros2_parser(sub)
    add_helper_parsers(sub)
    add_bare_parsers(sub)
    r = sub.add_parser("robot", help="(internal) the paper benchmark's robot process")
    add_workload_arguments(r)
    r.set_defaults(func=workload_main)
    args = parser.parse_args(argv)
    out = getattr(args, "out", None)
    if out is not None and (problem := folder_problem(out)) is not None:
        print(f"drvs-bench {args.bench}: --out {args.out}: {problem}", file=sys.stderr)
        return 2
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())

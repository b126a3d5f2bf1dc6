"""drvs-bench load: many robots at once, for a while (issue 6, "Load and soak").

A drvs-server and three drvs-camera processes on the benchmark scene's recorded video; robots are
DrvsClient instances spread over worker processes (`drvs-bench load-robots`), so no one Python
process carries them all. Each robot sends single-shot requests over all three cameras' region at
a fixed rate, open loop (on schedule, whether or not earlier requests have been answered), and
waits up to --timeout for every camera's final report. A report that does not arrive in that time,
or that carries an error (a `busy` refusal is one), is lost; a request is complete only when every
camera's final report came without error. Latency is timed from each request's scheduled send
time, so a robot that falls behind its schedule counts its lag. Requests scheduled in the warm-up
are left out of every count. RSS of the server and the cameras is sampled from /proc every half
second; growth is end over start, minus one, where start is the median over a window right after
the warm-up and end the median over a window at the end, and peak growth is the largest sample
after the warm-up over that start.

With --abuse the run is made twice on fresh processes, without and then with the abuse mix of
drvs_bench.abuse beside the same robots, and load.json gains `baseline_*` and `abuse_*` figures.

Every request after the warm-up has one outcome (issue 27; `outcomes` sums to `requests`):
complete; refused (ResourceExhausted raised: by the server, or locally by the client's adaptive
throttle, told apart by its `throttle.refused_locally` count around the call; the time from the
scheduled send to the refusal is recorded); incomplete (dispatched, but a camera's report, or a
fused snapshot's missing camera, carried an error: counted by code); lost (DeadlineExceeded,
Unavailable, or a camera's final report that never came). Goodput is complete requests a second.
`--delivery fused` asks `snapshot(...)` fused single shots instead (complete: a snapshot that
names no missing camera); `--delivery fused-unary` sends them as unary DetectObjects calls on a plain
gRPC stub, one connection per robot, as a client without DrvsClient does (no request stream, no
client-side throttle): a refusal that reached such a robot as UNAVAILABLE (REFUSED_STREAM) or
CANCELLED (dropped by gRPC before the server took the call in) counts as refused but misses the
overload target, which asks for RESOURCE_EXHAUSTED. `--server-arg` passes a flag to drvs-server.
`--overload 2,4` runs --robots (taken as capacity) and then 2x and 4x the
robots, each on fresh processes, and judges issue 27's overload targets; `--sweep` bisects the most
robots that complete every request, each probe a short run on fresh processes. Both write a
`capacity` section: robots per server core at capacity, per delivery.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import math
import os
import signal
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from drvs.robot.throttle import DEFAULT_K
from drvs.tools.launch import LIVE_READY, ManagedProcess, running_etcd, start_camera, start_server

from .abuse import add_abuse_parser
from .common import bench_process, machine, record_scene

# The worker process is drvs_bench.load_robots and the figures drvs_bench.load_figures; the names
# imported `as` themselves stay importable from here, where they were before the split.
from .load_figures import (
    ABUSE_KEYS,
    OVERLOAD_GOODPUT_SHARE,
    OVERLOAD_P99_FACTOR,
    OVERLOAD_P99_MAX_MS,
    OVERLOAD_REFUSAL_MAX_MS,
    Sampler,
    capacity_entry,
    capacity_section,
    check_load_work,
    level_figures,
    log_warnings,
    overload_verdicts,
    plot_curve,
    summarise,
    write_outputs,
    zero_loss,
)
from .load_robots import CAMERAS, DELIVERIES, add_worker_parser
from .load_robots import expected_requests as expected_requests
from .load_robots import schedule as schedule
from .stats import interleaved, out_dir

#: The capacity the last full sweep found on the 2-core development machine (docs/benchmarks.md,
#: "Where the limit is": 12 robots at 30 Hz, 360 requests a second, lost nothing): the knee.
#: Update it from `drvs-bench load --sweep` when the sweep is run again. It is also --overload's
#: default capacity.
KNEE_ROBOTS = 12
#: `--quick` runs at 80 % of the knee (10 robots), below capacity, so that a CI machine busy with
#: other work does not push it over; the sweep (`--sweep`), not CI, measures where the knee is.
QUICK_ROBOTS = round(0.8 * KNEE_ROBOTS)


# --- the coordinator ------------------------------------------------------------------------------


async def run_load(
    out_dir: Path,
    *,
    robots: int,
    workers: int,
    rate: float,
    seconds: float,
    warmup: float,
    timeout: float,
    abuse: list[str] | None = None,
    name: str = "load",
    delivery: str = "per-camera",
    throttle: bool = True,
    deployed: bool = False,
    server_flags: tuple[str, ...] = (),
) -> dict[str, Any]:
    """One run: fresh server and cameras, the robots, and with `abuse` (the abuser's extra
    arguments) the abuse mix beside them from the start to the end of the robots' schedule.
    `delivery`: per-camera reports or fused snapshots; `throttle` False: the robots' client-side
    throttling off (throttle_k=inf), so only the server's door refuses. `deployed`: the server on an
    etcd registry (a real etcd, started here) with its live view on, as a building runs it: what
    the abuse mix's etcd churn and live-view floods need to reach. `server_flags`: more drvs-server flags."""
    workers = max(1, min(workers, robots))
    procs: list[ManagedProcess] = []
    abuser: ManagedProcess | None = None
    abuse_done: dict[str, Any] = {}
    live_view = ""
    with tempfile.TemporaryDirectory(prefix="drvs-bench-load-") as tmp:
        scene = record_scene(Path(tmp), cameras=CAMERAS)
        async with contextlib.AsyncExitStack() as stack:
            try:
                server_args: list[str] = []
                if deployed:
                    members = await stack.enter_async_context(running_etcd())
                    server_args = ["--registry", "etcd://" + members[0].address, "--foxglove", "127.0.0.1:0"]
                server, address = await start_server(*server_args, *server_flags)
                procs.append(server)
                if deployed:
                    live_view = next(m.group(1) for line in server.lines if (m := LIVE_READY.search(line)))
                cameras = []
                for camera_id, rec in scene.items():
                    cameras.append(
                        await start_camera(camera_id, rec.video, rec.homography_file, address, "--max-range", "6")
                    )
                procs.extend(cameras)
                go = Path(tmp) / "go"
                crew = []
                offset = 0
                for w in range(workers):
                    count = robots // workers + (1 if w < robots % workers else 0)
                    worker_args = [
                        "--server", address, "--name", f"w{w}", "--robots", str(count), "--index-offset", str(offset),
                        "--total-robots", str(robots), "--rate", str(rate), "--warmup", str(warmup),
                        "--seconds", str(seconds), "--timeout", str(timeout), "--go-file", str(go),
                        "--delivery", delivery, "--throttle-k", str(DEFAULT_K if throttle else math.inf),
                    ]  # fmt: skip
                    crew.append(bench_process(f"robots-{w}", "load-robots", *worker_args))
                    offset += count
                for proc in crew:
                    await proc.start()
                    procs.append(proc)
                for proc in crew:
                    await proc.wait_for_line(r"^READY$", timeout=120)
                pids = {"server": server.pid, **{c.name: c.pid for c in cameras}}
                sampler = Sampler(pids)
                t0 = time.time() + 0.5
                if abuse is not None:
                    view = ["--live-view", live_view] if live_view else []
                    abuser = bench_process("abuser", "load-abuse", "--server", address,
                                           "--seconds", str(warmup + seconds + 0.5), *abuse, *view)  # fmt: skip
                    await abuser.start()
                    procs.append(abuser)
                    await abuser.wait_for_line(r"^READY$", timeout=60)
                go.write_text(repr(t0))
                for proc in crew:
                    os.kill(proc.pid, signal.SIGUSR1)
                sampler.start(t0)
                try:
                    await asyncio.sleep(max(0.0, t0 + warmup - time.time()))
                    after_warmup = sampler.sample(warmup)
                    done = [
                        json.loads(
                            (await p.wait_for_line(r"^DONE (.*)", timeout=warmup + seconds + timeout + 600)).group(1)
                        )
                        for p in crew
                    ]
                    at_end = sampler.sample(time.time() - t0)
                finally:
                    await sampler.stop()
                if abuser is not None:
                    line = await abuser.wait_for_line(r"^DONE (.*)", timeout=120)
                    abuse_done = json.loads(line.group(1))
                for proc in crew:
                    await proc.wait(timeout=60)
            finally:
                for proc in reversed(procs):
                    await proc.stop()
    records = [r for d in done for r in d["records"]]
    warnings = {p.name: log_warnings(p) for p in (server, *cameras)}
    logs = out_dir / "logs" / name
    logs.mkdir(parents=True, exist_ok=True)
    for proc in (server, *cameras, *([abuser] if abuser else [])):
        (logs / f"{proc.name}.log").write_text(proc.output() + "\n")
    result = summarise(records, after_warmup, at_end, sampler, [c.name for c in cameras], warmup)
    check_load_work(f"load ({name})", result, robots, rate, warmup, seconds)
    result["cpu_cores_after_warmup"]["robot_workers"] = round(sum(d["cpu_s"] / d["wall_s"] for d in done), 3)
    # Goodput: complete requests a second over the measured seconds (the schedule after the warm-up).
    result["offered_request_hz"] = round(result["requests"] / seconds, 1)
    result["goodput_hz"] = round(result["outcomes"]["complete"] / seconds, 1)
    # The clients' own count of local refusals against the records' (warm-up included in both).
    counted = sum(d["refused_locally"] for d in done)
    recorded = sum(1 for r in records if len(r) > 7 and r[7] == "refused_local")
    result["refused_locally_client_count"] = counted
    result["local_refusals_match_client_count"] = counted == recorded
    if delivery == "fused-unary":
        client_throttle = "none: a plain gRPC stub, the retry hint ignored"
    else:
        client_throttle = f"adaptive, throttle_k={DEFAULT_K:g}" if throttle else "off (throttle_k=inf)"
    result = {
        "benchmark": "load",
        "delivery": delivery,
        "client_throttle": client_throttle,
        "server_flags": list(server_flags),
        "robots": robots,
        "workers": workers,
        "rate_hz": rate,
        "seconds": seconds,
        "warmup_s": warmup,
        "report_timeout_s": timeout,
        "cameras": CAMERAS,
        **result,
        "warnings_logged": warnings,
        "machine": machine(),
    }
    if abuser is not None:
        result["abuser"] = abuse_done
    return result


async def run_sweep(out: Path, base: str, start: int, most: int, settings: dict[str, Any]) -> dict[str, Any]:
    """Bisect the most robots with zero loss: double from `start` until a probe fails (or `most`
    passes), halve if the first fails, then bisect between the last pass and the first failure.
    Every probe is a run of its own on fresh processes."""
    probes: dict[int, dict[str, Any]] = {}

    async def passes(robots: int) -> bool:
        name = f"{base}-sweep-{robots}"
        result = await run_load(out, **{**settings, "robots": robots}, name=name)
        result["file"] = f"{name}.json"
        write_outputs(result, out, name)
        probes[robots] = result
        print(f"sweep: {robots} robots: {result['outcomes']} goodput {result['goodput_hz']}/s, "
              f"p99 {result['latency_p99_ms']} ms", file=sys.stderr, flush=True)  # fmt: skip
        return zero_loss(result)

    good, bad = 0, 0
    n = max(1, min(start, most))
    if await passes(n):
        good = n
        while good < most:
            n = min(most, good * 2)
            if not await passes(n):
                bad = n
                break
            good = n
    else:
        bad = n
        while n > 1:
            n //= 2
            if await passes(n):
                good = n
                break
            bad = n
    while bad and good and bad - good > 1:
        mid = (good + bad) // 2
        if await passes(mid):
            good = mid
        else:
            bad = mid
    return {"capacity_robots": good, "first_failing_robots": bad or None, "probes": probes}


def load_main(args: argparse.Namespace) -> int:
    out = out_dir(args.out)
    multiples: list[float] = []
    if args.overload:
        try:
            multiples = [float(m) for m in args.overload.split(",")]
        except ValueError:
            multiples = [0.0]
        if not all(m > 1 and math.isfinite(m) for m in multiples):
            print("drvs-bench load: --overload takes multiples above 1, comma-separated (e.g. 2,4)", file=sys.stderr)
            return 2
    if sum(map(bool, (args.sweep, args.overload, args.abuse))) > 1:
        print("drvs-bench load: --sweep, --overload and --abuse are separate runs: give one", file=sys.stderr)
        return 2
    short = args.sweep  # the sweep's probes are short runs
    default_robots = QUICK_ROBOTS if args.quick else KNEE_ROBOTS if (args.overload or args.sweep) else 50
    robots = args.robots or default_robots
    seconds = args.seconds or (10.0 if args.quick or short else 60.0)
    warmup = args.warmup if args.warmup is not None else (2.0 if args.quick or short else 5.0)
    workers = args.workers or (2 if args.quick else 5)
    # 0 picks the default above; a negative count or a rate or timeout of 0 is a mistake, refused
    # before any process starts.
    if (
        min(robots, workers, args.repeat, args.sweep_max) < 1
        or seconds <= 0
        or warmup < 0
        or not (args.rate > 0 and args.timeout > 0)
    ):
        print("drvs-bench load: --robots, --workers, --repeat, --sweep-max, --seconds, --rate and --timeout must "
              "be > 0, --warmup >= 0", file=sys.stderr)  # fmt: skip
        return 2
    throttle = not args.no_throttle
    delivered = "" if args.delivery == "per-camera" else f"-{args.delivery}"
    base = "load" + delivered + ("" if throttle else "-no-throttle")
    key = args.delivery + ("" if throttle else " (no client throttle)")
    settings = dict(workers=workers, rate=args.rate, seconds=seconds, warmup=warmup, timeout=args.timeout,
                    delivery=args.delivery, throttle=throttle, server_flags=tuple(args.server_arg))  # fmt: skip
    extra_keys: list[str] = []
    if args.sweep:
        sweep = asyncio.run(run_sweep(out, base, robots, args.sweep_max, settings))
        probes = sweep.pop("probes")
        at = probes.get(sweep["capacity_robots"]) or probes[min(probes)]
        result = dict(at)
        levels = [level_figures([probes[n]], probes[n]["robots"] / robots) for n in sorted(probes)]
        for lv in levels:
            lv.pop("multiple")
            lv["zero_loss"] = zero_loss(probes[lv["robots"]])
        result["sweep"] = {
            **sweep,
            "criterion": "zero loss: every request after the warm-up complete (none refused, incomplete or lost)",
            "processes": "fresh: a new server, cameras and robot workers for every probe",
            "search": f"from {robots} robots, doubled until a probe failed (at most {args.sweep_max}), halved if the "
            "first failed, then bisected between the last pass and the first failure",
            "probe_seconds": seconds,
            "probe_warmup_s": warmup,
            "probes": levels,
        }
        if sweep["capacity_robots"]:
            source = f"--sweep: the most robots with zero loss ({seconds:g} s probes on fresh processes)"
            result["capacity"] = capacity_section(out, key, capacity_entry([at], source))
        plot_curve(levels, out / f"{base}-sweep.png", f"sweep, {args.delivery}: capacity {sweep['capacity_robots']}")
        extra_keys = ["sweep", "capacity"] if "capacity" in result else ["sweep"]
    elif multiples:
        all_multiples = [1.0, *multiples]
        runs: dict[float, list[dict[str, Any]]] = {m: [] for m in all_multiples}
        for r, m in interleaved(all_multiples, args.repeat):
            name = f"{base}-{m:g}x" + (f"-run{r + 1}" if args.repeat > 1 else "")
            run = asyncio.run(run_load(out, **settings, robots=max(1, round(robots * m)), name=name))
            run["file"] = f"{name}.json"
            write_outputs(run, out, name)
            runs[m].append(run)
        levels = [level_figures(runs[m], m) for m in all_multiples]
        result = dict(runs[1.0][0])
        result["overload"] = {
            "capacity_robots": robots,
            "capacity_from": "--robots, taken as capacity",
            "processes": "fresh: a new server, cameras and robot workers for every run",
            "levels": levels,
            **overload_verdicts(levels),
            "targets": (
                f"at each multiple of the capacity, goodput at least {OVERLOAD_GOODPUT_SHARE:.0%} of goodput at "
                f"capacity; the p99 of complete requests within {OVERLOAD_P99_FACTOR:g}x its value at capacity and "
                f"under {OVERLOAD_P99_MAX_MS:g} ms; every other request refused (RESOURCE_EXHAUSTED) within "
                f"{OVERLOAD_REFUSAL_MAX_MS:g} ms of its scheduled send; none lost"
            ),
        }
        source = f"--overload: --robots {robots} taken as capacity ({seconds:g} s runs on fresh processes)"
        result["capacity"] = capacity_section(out, key, capacity_entry(runs[1.0], source))
        plot_curve(levels, out / f"{base}-overload.png",
                   f"{args.delivery}, {robots} robots × {args.rate:g} Hz as capacity, then ×" +
                   ", ×".join(f"{m:g}" for m in multiples))  # fmt: skip
        extra_keys = ["overload", "capacity"]
    else:
        result = asyncio.run(run_load(out, **settings, robots=robots, name=base, deployed=bool(args.abuse)))
    if args.quick and not args.robots:
        result["quick_robots_source"] = (
            f"{QUICK_ROBOTS} robots: 80 % of {KNEE_ROBOTS}, the capacity (knee) the last full sweep found on a "
            "2-core machine (docs/benchmarks.md, 'Where the limit is'), so CI runs below capacity"
        )
    if args.abuse:
        abused = asyncio.run(
            run_load(out, **settings, robots=robots, abuse=ABUSE_ARGS, name=f"{base}-abuse", deployed=True)
        )
        for short_key, full_key in ABUSE_KEYS.items():
            result[f"baseline_{short_key}"] = result[full_key]
            result[f"abuse_{short_key}"] = abused[full_key]
        result["abuser"] = abused["abuser"]
        result["abuse_definition"] = (
            "the same robots, schedule and checks on fresh processes, the server on an etcd registry with its "
            "live view on in both runs, with drvs-bench load-abuse beside them for the whole run: "
            + " ".join(ABUSE_ARGS)
            + " (a registration flood far from the robots' region, "
            "oversized-region requests and continuous requests whose reports go to a listener that never reads, "
            "DetectStream calls that are never read, mobile cameras teleporting into the robots' region, forged "
            "reports with 1 MB request ids into the server's report intake, live-view publishers and subscribers "
            "that never read, register/deregister churn); baseline_*: the run without it"
        )
        write_outputs(abused, out, f"{base}-abuse")
    write_outputs(result, out, base)
    keys = [
        "delivery", "client_throttle", "robots", "rate_hz", "seconds", "requests", "achieved_request_hz",
        "reports_expected", "reports_received", "reports_lost", "reports_with_error", "outcomes", "goodput_hz",
        "refused_by_reason", "incomplete_cameras_by_code", "lost_by_kind", "latency_p50_ms", "latency_p99_ms",
        "refusal_latency_p99_ms", "refusal_latency_max_ms", "send_lag_p99_ms", "server_rss_growth",
        "camera_rss_growth", "server_rss_peak_growth", "camera_rss_peak_growth", "cpu_cores_after_warmup", "targets",
        "local_refusals_match_client_count",
    ]  # fmt: skip
    keys += [k for k in result if k.startswith(("baseline_", "abuse_")) and k != "abuse_definition"]
    summary = {k: result[k] for k in keys}
    for k in extra_keys:
        summary[k] = brief(result[k])
    print(json.dumps(summary, indent=1))
    written = [out / f"{base}.json", out / f"{base}.png"]
    if args.sweep:
        written.append(out / f"{base}-sweep.png")
    if multiples:
        written.append(out / f"{base}-overload.png")
    print("written: " + ", ".join(map(str, written)), file=sys.stderr)
    return 0


def brief(section: Any) -> Any:
    """A section as printed: without per-run lists and per-run CPU (they are in the JSON)."""
    if isinstance(section, dict):
        return {
            k: brief(v)
            for k, v in section.items()
            if not k.endswith(("_runs", "_spread", "_median", "files", "camera_cores"))
        }
    if isinstance(section, list):
        return [brief(v) for v in section]
    return section


#: The abuse mix, bounded: at most 2000 registrations (200 a second), 5 oversized (20 000-point)
#: requests a second, 8 continuous requests and 8 never-read DetectStream calls of 500 requests each.
ABUSE_ARGS = ["--registrations", "2000", "--registration-rate", "200", "--vertices", "20000",
              "--oversized-rate", "5", "--continuous", "8", "--stalled", "8", "--stalled-requests", "500",
              "--teleports", "4", "--report-floods", "2", "--flood-reports", "300", "--flood-id-bytes", "1000000",
              "--view-floods", "2", "--view-message-bytes", "65536", "--churn", "4", "--churn-rate", "20"]  # fmt: skip


def add_load_parser(sub: Any) -> None:
    p = sub.add_parser("load", help="many robots at once: lost reports, latency, server and camera memory growth")
    p.add_argument(
        "--quick",
        action="store_true",
        help=f"{QUICK_ROBOTS} robots (80 %% of the last sweep's capacity, {KNEE_ROBOTS}) for 10 s (2 workers)",
    )
    p.add_argument(
        "--robots",
        type=int,
        default=0,
        help=f"simulated robots (default 50; --overload: the capacity, default {KNEE_ROBOTS}; --sweep: the start)",
    )
    p.add_argument(
        "--delivery",
        choices=DELIVERIES,
        default="per-camera",
        help="per-camera reports (subscribe; default), fused single shots (snapshot()), or fused single shots as "
        "unary DetectObjects calls on a plain gRPC stub (fused-unary: a client without DrvsClient)",
    )
    p.add_argument(
        "--server-arg",
        action="append",
        default=[],
        metavar="FLAG",
        help="a drvs-server flag or value for every run (repeat it: --server-arg=--max-pending-calls --server-arg=0)",
    )
    p.add_argument(
        "--overload",
        default="",
        metavar="M,M",
        help="the goodput curve: the run at --robots (taken as capacity), then at these multiples of it (e.g. 2,4)",
    )
    p.add_argument(
        "--sweep",
        action="store_true",
        help="bisect the most robots at --rate with zero loss, each probe a short run on fresh processes "
        "(default 10 s after 2 s)",
    )
    p.add_argument("--sweep-max", type=int, default=64, help="the most robots the sweep tries (default 64)")
    p.add_argument("--repeat", type=int, default=1, help="--overload: runs per level, interleaved (default 1)")
    p.add_argument(
        "--no-throttle",
        action="store_true",
        help="the robots without client-side throttling (throttle_k=inf): the server's door alone refuses",
    )
    p.add_argument("--workers", type=int, default=0, help="worker processes the robots are spread over (default 5)")
    p.add_argument("--rate", type=float, default=30.0, help="requests a second per robot (default 30)")
    p.add_argument("--seconds", type=float, default=0.0, help="measured run after the warm-up (default 60)")
    p.add_argument("--warmup", type=float, default=None, help="seconds before the RSS baseline (default 5)")
    p.add_argument("--timeout", type=float, default=5.0, help="a report later than this is lost (default 5 s)")
    p.add_argument(
        "--abuse", action="store_true", help="run twice: without, then with the abuse mix (abuse_* and baseline_*)"
    )
    p.add_argument("--out", type=Path, default=None)
    p.set_defaults(func=load_main)
    add_worker_parser(sub)
    add_abuse_parser(sub)

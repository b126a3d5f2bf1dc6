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
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import re
import signal
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from drvs.errors import DrvsError
from drvs.launch import ManagedProcess, start_camera, start_server
from drvs.robot import DrvsClient

from .abuse import add_abuse_parser
from .common import ALL_REGION, YELLOW, bench_process, cpu_seconds, machine, pyplot, record_scene
from .helpers import percentile
from .stats import check_work

CAMERAS = 3
#: `--quick` sits at the capacity the last full sweep found (docs/benchmarks.md, "Where the limit
#: is": 12 robots at 30 Hz, 360 requests a second, lost nothing), not below it. Update it from the
#: sweep when the sweep is run again.
QUICK_ROBOTS = 12
#: How often the coordinator samples RSS and CPU of the server and cameras.
SAMPLE_S = 0.5


def rss_bytes(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    return 0


# --- the worker process: N robots -----------------------------------------------------------------


def schedule(robot: int, robots: int, rate: float, end: float) -> list[float]:
    """A robot's send times, as offsets (s) from the start: robots spread evenly over one period,
    so the load is smooth, not all of them at once. The coordinator counts the work from it too."""
    phase = robot / robots / rate
    offsets = []
    k = 0
    while (offset := phase + k / rate) < end:
        offsets.append(offset)
        k += 1
    return offsets


def expected_requests(robots: int, rate: float, warmup: float, seconds: float) -> int:
    """Requests the robots must send after the warm-up: what the counts are checked against."""
    return sum(1 for g in range(robots) for o in schedule(g, robots, rate, warmup + seconds) if not o < warmup)


async def robots_worker(args: argparse.Namespace) -> None:
    """`drvs-bench load-robots`: start N robots, say READY, wait for the start time in --go-file,
    run the schedule, print DONE with one record per request."""
    loop = asyncio.get_running_loop()
    clients = [DrvsClient(args.server, robot_id=f"{args.name}-{i}", listen="127.0.0.1:0") for i in range(args.robots)]
    for client in clients:
        await client.start()
    try:
        for client in clients:
            await client.detect(YELLOW, ALL_REGION, timeout_s=10)  # connections up, one round each
        go = asyncio.Event()
        loop.add_signal_handler(signal.SIGUSR1, go.set)
        print("READY", flush=True)
        await go.wait()  # the coordinator has written the start time (wall clock) into --go-file
        start_wall = float(await asyncio.to_thread(Path(args.go_file).read_text))
        start = loop.time() + (start_wall - time.time())
        end_offset = args.warmup + args.seconds
        # Per request: scheduled offset from the start (s), lag of the send behind schedule (ms),
        # final reports without error, with error, the latency from the scheduled send time to the
        # last final report (ms, or -1 unless every camera's final report came without error), the
        # failure of the request itself ("" if none), and whether it was scheduled in the warm-up.
        records: list[list[Any]] = []

        async def one(client: DrvsClient, offset: float) -> None:
            scheduled = start + offset
            sent = loop.time()
            record: list[Any] = [
                round(offset, 4),
                round((sent - scheduled) * 1000, 2),
                0,
                0,
                -1.0,
                "",
                offset < args.warmup,
            ]
            records.append(record)
            try:
                sub = await client.subscribe(YELLOW, ALL_REGION, timeout_s=args.timeout)
                result = await sub.collect()
            except DrvsError as exc:
                record[5] = type(exc).__name__
                return
            record[2] = sum(1 for r in result.reports if r.final and not r.error)
            record[3] = sum(1 for r in result.reports if r.final and r.error)
            if result.complete and len(result.camera_ids) == CAMERAS and record[2] == CAMERAS:
                record[4] = round((loop.time() - scheduled) * 1000, 2)

        tasks: list[asyncio.Task[None]] = []
        # This process's CPU time from the end of the warm-up (it exits before the coordinator's last sample).
        cpu_at_warmup = [time.process_time()]
        loop.call_at(start + args.warmup, lambda: cpu_at_warmup.__setitem__(0, time.process_time()))

        async def robot(index: int, client: DrvsClient) -> None:
            for offset in schedule(args.index_offset + index, args.total_robots, args.rate, end_offset):
                delay = start + offset - loop.time()
                if delay > 0:
                    await asyncio.sleep(delay)
                tasks.append(loop.create_task(one(client, offset)))

        await asyncio.gather(*(robot(i, c) for i, c in enumerate(clients)))
        await asyncio.gather(*tasks)
        cpu_s = time.process_time() - cpu_at_warmup[0]
        wall_s = loop.time() - (start + args.warmup)
        print("DONE " + json.dumps({"records": records, "cpu_s": cpu_s, "wall_s": wall_s}), flush=True)
    finally:
        for client in clients:
            await client.close()


def add_worker_parser(sub: Any) -> None:
    w = sub.add_parser("load-robots", help="(internal) the load benchmark's robots, one worker process")
    w.add_argument("--server", required=True)
    w.add_argument("--name", required=True)
    w.add_argument("--robots", type=int, required=True)
    w.add_argument("--index-offset", type=int, default=0)
    w.add_argument("--total-robots", type=int, required=True)
    w.add_argument("--rate", type=float, required=True)
    w.add_argument("--warmup", type=float, required=True)
    w.add_argument("--seconds", type=float, required=True)
    w.add_argument("--timeout", type=float, required=True)
    w.add_argument("--go-file", required=True, help="holds the start time (time.time()) once SIGUSR1 arrives")
    w.set_defaults(func=lambda args: asyncio.run(robots_worker(args)) or 0)


# --- the coordinator ------------------------------------------------------------------------------


class Sampler:
    """RSS and CPU time of named processes every SAMPLE_S."""

    def __init__(self, pids: dict[str, int]) -> None:
        self.pids = pids
        self.samples: list[tuple[float, dict[str, int], dict[str, float]]] = []
        self._task: asyncio.Task[None] | None = None

    def sample(self, t: float) -> tuple[float, dict[str, int], dict[str, float]]:
        rss, cpu = {}, {}
        for name, pid in self.pids.items():
            try:
                rss[name], cpu[name] = rss_bytes(pid), cpu_seconds(pid)
            except (FileNotFoundError, ProcessLookupError):
                continue
        entry = (t, rss, cpu)
        self.samples.append(entry)
        return entry

    def start(self, t0: float) -> None:
        async def run() -> None:
            while True:
                self.sample(time.time() - t0)
                await asyncio.sleep(SAMPLE_S)

        self._task = asyncio.get_running_loop().create_task(run())

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)


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
) -> dict[str, Any]:
    """One run: fresh server and cameras, the robots, and with `abuse` (the abuser's extra
    arguments) the abuse mix beside them from the start to the end of the robots' schedule."""
    workers = max(1, min(workers, robots))
    procs: list[ManagedProcess] = []
    abuser: ManagedProcess | None = None
    abuse_done: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="drvs-bench-load-") as tmp:
        scene = record_scene(Path(tmp), cameras=CAMERAS)
        try:
            server, address = await start_server()
            procs.append(server)
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
                abuser = bench_process("abuser", "load-abuse", "--server", address,
                                       "--seconds", str(warmup + seconds + 0.5), *abuse)  # fmt: skip
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
    result = {
        "benchmark": "load",
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


def check_load_work(name: str, result: dict[str, Any], robots: int, rate: float, warmup: float, seconds: float) -> None:
    """Every request the schedule holds after the warm-up was sent and accounted for, and every
    expected report is received, carried an error, or is lost: else WorkMismatch."""
    check_work(
        name,
        {
            "requests": expected_requests(robots, rate, warmup, seconds),
            "reports_expected": CAMERAS * result["requests"],
        },
        {"requests": result["requests"], "reports_expected": result["reports_received"] + result["reports_lost"]},
    )


def log_warnings(proc: ManagedProcess) -> dict[str, int]:
    """WARNING and ERROR lines a process logged, counted by message with ids and numbers blanked
    (the whole logs are written to logs/ beside load.json)."""
    counts: dict[str, int] = {}
    for line in proc.lines:
        m = re.search(r" (WARNING|ERROR) (.*)", line)
        if m:
            key = re.sub(r"request \S+:", "request …:", m.group(2))
            key = re.sub(r"\d+(\.\d+)?", "N", key)[:200]
            counts[key] = counts.get(key, 0) + 1
    return dict(sorted(counts.items(), key=lambda kv: -kv[1])[:20])


def summarise(
    records: list[list[Any]],
    after_warmup: tuple[float, dict[str, int], dict[str, float]],
    at_end: tuple[float, dict[str, int], dict[str, float]],
    sampler: Sampler,
    camera_names: list[str],
    warmup: float = 0.0,
) -> dict[str, Any]:
    """The figures of one run. Requests scheduled in the warm-up (r[6]) count nowhere but the
    timeline; a report with an error is lost, and only error-free complete requests have latency."""
    timeline_records = records
    records = [r for r in records if not (len(r) > 6 and r[6])]
    expected = CAMERAS * len(records)
    received = sum(r[2] for r in records)
    latencies = [r[4] for r in records if r[4] >= 0]
    lags = [r[1] for r in records]
    span = max((r[0] for r in records), default=0.0) - min((r[0] for r in records), default=0.0)
    t_warm, _, cpu_warm = after_warmup
    t_end, _, cpu_end = at_end
    wall = max(t_end - t_warm, 1e-9)
    # RSS moves by a few MB from one sample to the next (frames decoded, buffers recycled): start and
    # end are each the median of the samples in a window right after the warm-up and at the end.
    window = min(5.0, max(1.0, wall / 4))

    def median_rss(lo: float, hi: float) -> dict[str, int]:
        chosen = [rss for t, rss, _ in sampler.samples if lo - 1e-6 <= t <= hi + 1e-6]
        return {k: int(statistics.median(r[k] for r in chosen if k in r)) for k in chosen[0]}

    rss_warm = median_rss(t_warm, t_warm + window)
    rss_end = median_rss(t_end - window, t_end)
    # The largest sample over the whole run after the warm-up.
    after = [rss for t, rss, _ in sampler.samples if t >= t_warm - 1e-6]
    rss_peak = {k: max(r[k] for r in after if k in r) for k in rss_warm}

    def growth(name: str) -> float:
        return round(rss_end[name] / rss_warm[name] - 1, 4)

    def peak_growth(name: str) -> float:
        return round(rss_peak[name] / rss_warm[name] - 1, 4)

    def cores(name: str) -> float:
        return round((cpu_end[name] - cpu_warm[name]) / wall, 3)

    second: dict[int, list[list[Any]]] = {}
    for r in timeline_records:
        second.setdefault(math.floor(r[0]), []).append(r)
    timeline = []
    for s in sorted(second):
        rs = second[s]
        lat = [r[4] for r in rs if r[4] >= 0]
        timeline.append({
            "t": s,
            "requests": len(rs),
            "lost": sum(CAMERAS - r[2] for r in rs),
            "latency_p50_ms": percentile(lat, 50) if lat else None,
            "latency_p99_ms": percentile(lat, 99) if lat else None,
        })  # fmt: skip
    rss_timeline = [
        {"t": round(t, 2), **{k: v for k, v in rss.items() if k == "server" or k in camera_names}}
        for t, rss, _ in sampler.samples
    ]
    return {
        "requests": len(records),
        "warmup_requests": len(timeline_records) - len(records),
        "requests_failed": sum(1 for r in records if r[5]),
        "request_failures": sorted({r[5] for r in records if r[5]}),
        "achieved_request_hz": round(len(records) / span, 1) if span else 0.0,
        "reports_expected": expected,
        "reports_received": received,
        "reports_lost": expected - received,
        "reports_with_error": sum(r[3] for r in records),
        "requests_with_error": sum(1 for r in records if r[3]),
        "complete_requests": len(latencies),
        "latency_p50_ms": percentile(latencies, 50),
        "latency_p90_ms": percentile(latencies, 90),
        "latency_p99_ms": percentile(latencies, 99),
        "latency_max_ms": max(latencies, default=math.nan),
        "send_lag_p99_ms": percentile(lags, 99),
        "send_lag_max_ms": max(lags, default=math.nan),
        "latency_from": "each request's scheduled send time",
        "rss_window_s": window,
        "server_rss_start_bytes": rss_warm["server"],
        "server_rss_end_bytes": rss_end["server"],
        "server_rss_growth": growth("server"),
        "server_rss_peak_bytes": rss_peak["server"],
        "server_rss_peak_growth": peak_growth("server"),
        "camera_rss_start_bytes": [rss_warm[c] for c in camera_names],
        "camera_rss_end_bytes": [rss_end[c] for c in camera_names],
        "camera_rss_growth": max(growth(c) for c in camera_names),
        "camera_rss_peak_bytes": [rss_peak[c] for c in camera_names],
        "camera_rss_peak_growth": max(peak_growth(c) for c in camera_names),
        "cpu_cores_after_warmup": {
            "server": cores("server"),
            "cameras": [cores(c) for c in camera_names],
        },
        "targets": {
            "no_report_lost": expected == received,
            "rss_growth_under_10_percent": max(growth("server"), *(growth(c) for c in camera_names)) < 0.10,
            "rss_peak_growth_under_10_percent": max(peak_growth("server"), *(peak_growth(c) for c in camera_names))
            < 0.10,
        },
        "timeline": timeline,
        "rss_timeline": rss_timeline,
    }


def write_outputs(result: dict[str, Any], out: Path, name: str = "load") -> None:
    plt = pyplot()

    out.mkdir(parents=True, exist_ok=True)
    timeline = result["timeline"]
    fig, (ax1, ax2, ax3) = plt.subplots(3, 1, figsize=(9, 9), dpi=100, sharex=True)
    t = [p["t"] for p in timeline]
    for key, style in (("latency_p50_ms", "-"), ("latency_p99_ms", "--")):
        ax1.plot(t, [p[key] if p[key] is not None else math.nan for p in timeline], style, label=key[8:11])
    ax1.set_yscale("log")
    ax1.set_ylabel("request → last final report (ms)\n(complete requests only)")
    ax1.axvline(result["warmup_s"], color="grey", lw=1, ls=":", label="end of warm-up")
    ax1.legend(fontsize=8)
    ax1.grid(True, which="both", alpha=0.3)
    ax1.set_title(
        f"{result['robots']} robots × {result['rate_hz']:g} Hz, {result['cameras']} cameras: "
        f"{result['reports_received']}/{result['reports_expected']} reports"
    )
    cameras = result["cameras"]
    ax2.plot(t, [p["requests"] for p in timeline], label="requests sent")
    ax2.plot(t, [cameras * p["requests"] - p["lost"] for p in timeline], label="reports received")
    ax2.plot(t, [p["lost"] for p in timeline], label="reports lost")
    ax2.set_ylabel("per second")
    ax2.legend(fontsize=8)
    ax2.grid(True, alpha=0.3)
    rss = result["rss_timeline"]
    for process in [k for k in (rss[0] if rss else {}) if k != "t"]:
        ax3.plot([p["t"] for p in rss], [p.get(process, math.nan) / 2**20 for p in rss], label=process)
    ax3.set_ylabel("RSS (MiB)")
    ax3.set_xlabel("seconds from start")
    ax3.legend(fontsize=8)
    ax3.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / f"{name}.png")
    plt.close(fig)
    (out / f"{name}.json").write_text(json.dumps(result, indent=1) + "\n")


#: The abuse run's figures of the normal robots, published beside the baseline's as abuse_* and baseline_*.
ABUSE_KEYS = {
    "reports_expected": "reports_expected",
    "reports_lost": "reports_lost",
    "reports_with_error": "reports_with_error",
    "p50_ms": "latency_p50_ms",
    "p99_ms": "latency_p99_ms",
    "requests_failed": "requests_failed",
    "server_rss_peak_growth": "server_rss_peak_growth",
    "camera_rss_peak_growth": "camera_rss_peak_growth",
}


def load_main(args: argparse.Namespace) -> int:
    out = args.out or Path(time.strftime("bench-%Y%m%d-%H%M%S"))
    robots = args.robots or (QUICK_ROBOTS if args.quick else 50)
    seconds = args.seconds or (10.0 if args.quick else 60.0)
    warmup = args.warmup if args.warmup is not None else (2.0 if args.quick else 5.0)
    workers = args.workers or (2 if args.quick else 5)
    # 0 picks the default above; a negative count or a rate or timeout of 0 is a mistake, refused
    # before any process starts.
    if min(robots, workers) < 1 or seconds <= 0 or warmup < 0 or not (args.rate > 0 and args.timeout > 0):
        print("drvs-bench load: --robots, --workers, --seconds, --rate and --timeout must be > 0, --warmup >= 0",
              file=sys.stderr)  # fmt: skip
        return 2
    settings = dict(robots=robots, workers=workers, rate=args.rate, seconds=seconds, warmup=warmup,
                    timeout=args.timeout)  # fmt: skip
    result = asyncio.run(run_load(out, **settings))
    if args.quick and not args.robots:
        result["quick_robots_source"] = (
            f"{QUICK_ROBOTS} robots: the capacity the last full sweep found (docs/benchmarks.md, 'Where the limit is')"
        )
    if args.abuse:
        abused = asyncio.run(run_load(out, **settings, abuse=ABUSE_ARGS, name="load-abuse"))
        for short, key in ABUSE_KEYS.items():
            result[f"baseline_{short}"] = result[key]
            result[f"abuse_{short}"] = abused[key]
        result["abuser"] = abused["abuser"]
        result["abuse_definition"] = (
            "the same robots, schedule and checks on fresh processes, with drvs-bench load-abuse beside them "
            "for the whole run: " + " ".join(ABUSE_ARGS) + " (a registration flood far from the robots' region, "
            "oversized-region requests and continuous requests whose reports go to a listener that never reads, "
            "DetectStream calls that are never read); baseline_*: the run without it"
        )
        write_outputs(abused, out, "load-abuse")
    write_outputs(result, out, "load")
    keys = [
        "robots", "rate_hz", "seconds", "requests", "achieved_request_hz", "reports_expected", "reports_received",
        "reports_lost", "reports_with_error", "latency_p50_ms", "latency_p99_ms", "send_lag_p99_ms",
        "server_rss_growth", "camera_rss_growth", "server_rss_peak_growth", "camera_rss_peak_growth",
        "cpu_cores_after_warmup", "targets",
    ]  # fmt: skip
    keys += [k for k in result if k.startswith(("baseline_", "abuse_")) and k != "abuse_definition"]
    print(json.dumps({k: result[k] for k in keys}, indent=1))
    print(f"written: {out / 'load.json'}, {out / 'load.png'}", file=sys.stderr)
    return 0


#: The abuse mix, bounded: at most 2000 registrations (200 a second), 5 oversized (20 000-point)
#: requests a second, 8 continuous requests and 8 never-read DetectStream calls of 500 requests each.
ABUSE_ARGS = ["--registrations", "2000", "--registration-rate", "200", "--vertices", "20000",
              "--oversized-rate", "5", "--continuous", "8", "--stalled", "8", "--stalled-requests", "500"]  # fmt: skip


def add_load_parser(sub: Any) -> None:
    p = sub.add_parser("load", help="many robots at once: lost reports, latency, server and camera memory growth")
    p.add_argument(
        "--quick", action="store_true", help=f"{QUICK_ROBOTS} robots (the last sweep's capacity) for 10 s (2 workers)"
    )
    p.add_argument("--robots", type=int, default=0, help="simulated robots (default 50)")
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

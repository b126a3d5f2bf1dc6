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
names no missing camera). `--overload 2,4` runs --robots (taken as capacity) and then 2x and 4x the
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
import re
import signal
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from drvs.core.errors import DrvsError, ResourceExhausted
from drvs.robot import DetectionResult, DrvsClient, Snapshot
from drvs.robot.throttle import DEFAULT_K
from drvs.tools.launch import LIVE_READY, ManagedProcess, running_etcd, start_camera, start_server

from .abuse import add_abuse_parser
from .common import ALL_REGION, YELLOW, bench_process, cpu_seconds, machine, pyplot, record_scene
from .helpers import percentile
from .stats import check_work, interleaved, publish, verdict

CAMERAS = 3
#: The capacity the last full sweep found on the 2-core development machine (docs/benchmarks.md,
#: "Where the limit is": 12 robots at 30 Hz, 360 requests a second, lost nothing): the knee.
#: Update it from `drvs-bench load --sweep` when the sweep is run again. It is also --overload's
#: default capacity.
KNEE_ROBOTS = 12
#: `--quick` runs at 80 % of the knee (10 robots), below capacity, so that a CI machine busy with
#: other work does not push it over; the sweep (`--sweep`), not CI, measures where the knee is.
QUICK_ROBOTS = round(0.8 * KNEE_ROBOTS)
DELIVERIES = ("per-camera", "fused")
#: Outcomes of one request, in the order they are published.
OUTCOMES = ("complete", "refused_server", "refused_local", "incomplete", "lost")
#: Issue 27's overload targets, at each multiple of the capacity.
OVERLOAD_GOODPUT_SHARE = 0.9
OVERLOAD_P99_FACTOR = 2.0
OVERLOAD_P99_MAX_MS = 100.0
OVERLOAD_REFUSAL_MAX_MS = 50.0
#: A refusal's reason, from its message (diagnostics only: outcomes do not depend on it).
REFUSAL_REASONS = (
    ("client-side throttling", "client_throttle"),
    ("overloaded: the server", "server_loop"),
    ("overloaded: camera", "camera_link"),
    ("overloaded: fused delivery", "fused_delivery"),
    ("busy: camera", "camera_queue"),
)
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


def refusal_reason(exc: ResourceExhausted) -> str:
    """What a refusal's message says refused it (REFUSAL_REASONS); `no_retry_hint` for one
    without a hint (a per-robot budget), `other` for the rest."""
    text = str(exc)
    for needle, reason in REFUSAL_REASONS:
        if needle in text:
            return reason
    return "no_retry_hint" if exc.retry_after_s == 0 else "other"


async def robots_worker(args: argparse.Namespace) -> None:
    """`drvs-bench load-robots`: start N robots, say READY, wait for the start time in --go-file,
    run the schedule, print DONE with one record per request."""
    loop = asyncio.get_running_loop()
    fused = args.delivery == "fused"
    clients = [
        DrvsClient(
            args.server,
            robot_id=f"{args.name}-{i}",
            listen=None if fused else "127.0.0.1:0",  # a fused robot dials out only
            throttle_k=args.throttle_k,
        )
        for i in range(args.robots)
    ]
    for client in clients:
        await client.start()
    try:
        for client in clients:  # connections up, one round each
            if fused:
                await client.snapshot(YELLOW, ALL_REGION, timeout_s=10)
            else:
                await client.detect(YELLOW, ALL_REGION, timeout_s=10)
        go = asyncio.Event()
        loop.add_signal_handler(signal.SIGUSR1, go.set)
        print("READY", flush=True)
        await go.wait()  # the coordinator has written the start time (wall clock) into --go-file
        start_wall = float(await asyncio.to_thread(Path(args.go_file).read_text))
        start = loop.time() + (start_wall - time.time())
        end_offset = args.warmup + args.seconds
        refused_locally_before = sum(c.throttle.refused_locally for c in clients)
        # Per request: [0] scheduled offset from the start (s), [1] lag of the send behind schedule
        # (ms), [2] final reports (fused: cameras merged) without error, [3] with error (fused:
        # missing cameras), [4] the latency from the scheduled send time to the last final report
        # or the snapshot (ms, or -1 unless complete), [5] the exception the request raised ("" if
        # none), [6] whether it was scheduled in the warm-up, [7] its outcome (OUTCOMES), [8] the
        # time from the scheduled send to a refusal (ms, or -1), [9] what: a refusal's reason, an
        # incomplete request's error codes (comma-separated, one per camera), a lost one's kind.
        records: list[list[Any]] = []

        def classify_result(record: list[Any], result: DetectionResult, scheduled: float) -> None:
            record[2] = sum(1 for r in result.reports if r.final and not r.error)
            record[3] = sum(1 for r in result.reports if r.final and r.error)
            if result.complete and len(result.camera_ids) == CAMERAS and record[2] == CAMERAS:
                record[4] = round((loop.time() - scheduled) * 1000, 2)
                record[7] = "complete"
            elif result.unfinished_cameras:  # a final report that never came (deadline, stream ended)
                record[7], record[9] = "lost", "missing_final_report"
            else:
                codes = sorted(e.code for e in result.camera_errors.values())
                record[7] = "incomplete"
                record[9] = ",".join(codes) or f"dispatched_to_{len(result.camera_ids)}_cameras"

        def classify_snapshot(record: list[Any], snapshot: Snapshot, scheduled: float) -> None:
            missing = {m.camera_id for m in snapshot.missing_cameras}
            record[2] = min(CAMERAS, len(set(snapshot.camera_ids) - missing))
            record[3] = len(snapshot.missing_cameras)
            if not missing and len(snapshot.camera_ids) == CAMERAS:
                record[4] = round((loop.time() - scheduled) * 1000, 2)
                record[7] = "complete"
            else:
                codes = sorted(m.code for m in snapshot.missing_cameras)
                record[7] = "incomplete"
                record[9] = ",".join(codes) or f"merged_{len(snapshot.camera_ids)}_cameras"

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
                "lost",
                -1.0,
                "",
            ]
            records.append(record)
            # A local refusal is raised before the call's first await, so no other request of this
            # client can move the count in between; a server refusal carries a retry hint.
            refused_before = client.throttle.refused_locally
            try:
                if fused:
                    snapshot = await client.snapshot(YELLOW, ALL_REGION, timeout_s=args.timeout)
                else:
                    sub = await client.subscribe(YELLOW, ALL_REGION, timeout_s=args.timeout)
                    result = await sub.collect()
            except ResourceExhausted as exc:
                local = client.throttle.refused_locally > refused_before and exc.retry_after_s == 0
                record[5] = type(exc).__name__
                record[7] = "refused_local" if local else "refused_server"
                record[8] = round((loop.time() - scheduled) * 1000, 2)
                record[9] = refusal_reason(exc)
                return
            except DrvsError as exc:
                record[5] = record[9] = type(exc).__name__
                return
            if fused:
                classify_snapshot(record, snapshot, scheduled)
            else:
                classify_result(record, result, scheduled)

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
        # The clients' own count of requests they refused over the whole schedule (warm-up included):
        # the coordinator checks the records' refused_local against it.
        refused_locally = sum(c.throttle.refused_locally for c in clients) - refused_locally_before
        done = {"records": records, "cpu_s": cpu_s, "wall_s": wall_s, "refused_locally": refused_locally}
        print("DONE " + json.dumps(done), flush=True)
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
    w.add_argument("--delivery", choices=DELIVERIES, default="per-camera")
    w.add_argument("--throttle-k", type=float, default=DEFAULT_K, help="DrvsClient's throttle_k (inf: off)")
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
    delivery: str = "per-camera",
    throttle: bool = True,
    deployed: bool = False,
) -> dict[str, Any]:
    """One run: fresh server and cameras, the robots, and with `abuse` (the abuser's extra
    arguments) the abuse mix beside them from the start to the end of the robots' schedule.
    `delivery`: per-camera reports or fused snapshots; `throttle` False: the robots' client-side
    throttling off (throttle_k=inf), so only the server's door refuses. `deployed`: the server on an
    etcd registry (a real etcd, started here) with its live view on, as a building runs it: what
    the abuse mix's etcd churn and live-view floods need to reach."""
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
                server, address = await start_server(*server_args)
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
    result = {
        "benchmark": "load",
        "delivery": delivery,
        "client_throttle": f"adaptive, throttle_k={DEFAULT_K:g}" if throttle else "off (throttle_k=inf)",
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
    # Every request has exactly one outcome: none is left out of the counts.
    by_outcome = sum(result["outcomes"].values())
    check_work(name, {"requests_by_outcome": result["requests"]}, {"requests_by_outcome": by_outcome})


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
    timeline; a report with an error is lost, and only error-free complete requests have latency.
    Each request's outcome (r[7], OUTCOMES) is counted, and refusals' latency (r[8]) summarised."""
    timeline_records = records
    records = [r for r in records if not (len(r) > 6 and r[6])]
    outcomes = dict.fromkeys(OUTCOMES, 0)
    refused_by_reason: dict[str, int] = {}
    incomplete_by_code: dict[str, int] = {}
    lost_by_kind: dict[str, int] = {}
    for r in records:
        kind = outcome(r)
        outcomes[kind] += 1
        detail = r[9] if len(r) > 9 else ""
        if kind.startswith("refused"):
            refused_by_reason[detail or "unknown"] = refused_by_reason.get(detail or "unknown", 0) + 1
        elif kind == "incomplete":
            for code in (detail or "unknown").split(","):
                incomplete_by_code[code] = incomplete_by_code.get(code, 0) + 1
        elif kind == "lost":
            what = detail or r[5] or "missing_final_report"
            lost_by_kind[what] = lost_by_kind.get(what, 0) + 1
    refusals = {
        who: [r[8] for r in records if len(r) > 8 and outcome(r) == f"refused_{who}" and r[8] >= 0]
        for who in ("server", "local")
    }
    all_refusals = refusals["server"] + refusals["local"]
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
            **{f"requests_{kind}": sum(1 for r in rs if outcome(r) == kind) for kind in OUTCOMES},
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
        "outcomes": outcomes,
        "refused_by_reason": dict(sorted(refused_by_reason.items())),
        "incomplete_cameras_by_code": dict(sorted(incomplete_by_code.items())),
        "lost_by_kind": dict(sorted(lost_by_kind.items())),
        "refusal_latency_p50_ms": percentile(all_refusals, 50),
        "refusal_latency_p99_ms": percentile(all_refusals, 99),
        "refusal_latency_max_ms": max(all_refusals, default=math.nan),
        **{f"refusal_latency_{who}_p99_ms": percentile(refusals[who], 99) for who in refusals},
        **{f"refusal_latency_{who}_max_ms": max(refusals[who], default=math.nan) for who in refusals},
        "refusal_latency_from": "each request's scheduled send time to the ResourceExhausted it raised",
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


def outcome(record: list[Any]) -> str:
    """A record's outcome (OUTCOMES); records without one (r[7]) are classified from their counts."""
    if len(record) > 7:
        return str(record[7])
    if record[5]:
        return "refused_server" if record[5] == "ResourceExhausted" else "lost"
    if record[4] >= 0:
        return "complete"
    return "incomplete" if record[3] else "lost"


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


def level_figures(runs: list[dict[str, Any]], multiple: float) -> dict[str, Any]:
    """One load level over its runs: medians and spreads of goodput and p99, the largest refusal
    latency, outcomes summed over the runs, and the server's and cameras' CPU."""
    level: dict[str, Any] = {
        "multiple": multiple,
        "robots": runs[0]["robots"],
        "offered_request_hz": runs[0]["offered_request_hz"],
        "repeats": len(runs),
    }
    publish(level, "goodput_hz", [r["goodput_hz"] for r in runs])
    publish(level, "latency_p99_ms", [r["latency_p99_ms"] for r in runs])
    publish(level, "refusal_latency_p99_ms", [r["refusal_latency_p99_ms"] for r in runs])
    level["refusal_latency_max_ms"] = max(r["refusal_latency_max_ms"] for r in runs)
    level["send_lag_p99_ms"] = max(r["send_lag_p99_ms"] for r in runs)
    level["requests"] = sum(r["requests"] for r in runs)
    level["outcomes"] = {k: sum(r["outcomes"][k] for r in runs) for k in OUTCOMES}
    for key in ("refused_by_reason", "incomplete_cameras_by_code", "lost_by_kind"):
        merged: dict[str, int] = {}
        for r in runs:
            for k, v in r[key].items():
                merged[k] = merged.get(k, 0) + v
        level[key] = dict(sorted(merged.items()))
    level["cpu_cores_after_warmup_runs"] = [r["cpu_cores_after_warmup"] for r in runs]
    publish(level, "server_cores", [r["cpu_cores_after_warmup"]["server"] for r in runs])
    level["local_refusals_match_client_count"] = all(r["local_refusals_match_client_count"] for r in runs)
    level["files"] = [r["file"] for r in runs]
    return level


def overload_verdicts(levels: list[dict[str, Any]]) -> dict[str, Any]:
    """Issue 27's targets at each multiple above 1, against the 1x level (capacity)."""
    base = levels[0]
    out: dict[str, Any] = {}
    for level in levels[1:]:
        tag = f"{level['multiple']:g}x"
        goodput_ratios = [g / base["goodput_hz"] if base["goodput_hz"] else math.nan for g in level["goodput_hz_runs"]]
        p99_ratios = [p / base["latency_p99_ms"] for p in level["latency_p99_ms_runs"]]
        others = level["requests"] - level["outcomes"]["complete"]
        refused = level["outcomes"]["refused_server"] + level["outcomes"]["refused_local"]
        out[f"goodput_ratio_{tag}"] = round(statistics.median(goodput_ratios), 3)
        out[f"goodput_ratio_{tag}_runs"] = [round(r, 3) for r in goodput_ratios]
        out[f"latency_p99_ratio_{tag}"] = round(statistics.median(p99_ratios), 3)
        out[f"verdict_{tag}"] = {
            "goodput_at_least_90_percent_of_capacity": verdict(goodput_ratios, OVERLOAD_GOODPUT_SHARE),
            "p99_within_2x_of_capacity": verdict(p99_ratios, OVERLOAD_P99_FACTOR, higher_is_better=False),
            "p99_under_100_ms": verdict(level["latency_p99_ms_runs"], OVERLOAD_P99_MAX_MS, higher_is_better=False),
            # Every request not complete was refused (none incomplete, none lost), the slowest
            # refusal within 50 ms of its scheduled send.
            "every_other_request_refused_within_50_ms": (
                "met"
                if refused == others and not level["refusal_latency_max_ms"] > OVERLOAD_REFUSAL_MAX_MS
                else "missed"
            ),
            "none_lost": "met" if level["outcomes"]["lost"] == 0 else "missed",
        }
    return out


def capacity_entry(runs: list[dict[str, Any]], source: str) -> dict[str, Any]:
    """Robots per server core at capacity, from the runs at capacity (the server's CPU from /proc)."""
    cores = statistics.median(r["cpu_cores_after_warmup"]["server"] for r in runs)
    robots = runs[0]["robots"]
    return {
        "robots": robots,
        "rate_hz": runs[0]["rate_hz"],
        "server_cores": cores,
        "robots_per_server_core": round(robots / cores, 1) if cores > 0 else math.nan,
        "zero_loss": all(r["outcomes"]["complete"] == r["requests"] for r in runs),
        "camera_cores": [r["cpu_cores_after_warmup"]["cameras"] for r in runs],
        "robot_worker_cores": [r["cpu_cores_after_warmup"]["robot_workers"] for r in runs],
        "source": source,
    }


def capacity_section(out: Path, key: str, entry: dict[str, Any]) -> dict[str, Any]:
    """The capacity section: this run's entry under `key`, beside the other deliveries' entries
    already measured into the same directory (their load*.json), and the machine's cores."""
    section: dict[str, Any] = {}
    for path in sorted(out.glob("load*.json")):
        try:
            other = json.loads(path.read_text()).get("capacity", {})
        except (OSError, ValueError):
            continue
        for k, v in other.items():
            if k != "machine_cores" and isinstance(v, dict) and k != key:
                section[k] = {**v, "from_file": v.get("from_file", path.name)}
    section[key] = entry
    section["machine_cores"] = os.cpu_count()
    return section


def plot_curve(levels: list[dict[str, Any]], path: Path, title: str) -> None:
    """Goodput and p99 of complete requests against offered load: each run, and the medians."""
    plt = pyplot()
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8, 7), dpi=100, sharex=True)
    offered = [lv["offered_request_hz"] for lv in levels]
    for lv in levels:
        ax1.plot([lv["offered_request_hz"]] * len(lv["goodput_hz_runs"]), lv["goodput_hz_runs"], "o", color="C0",
                 alpha=0.4)  # fmt: skip
        ax2.plot([lv["offered_request_hz"]] * len(lv["latency_p99_ms_runs"]), lv["latency_p99_ms_runs"], "o",
                 color="C1", alpha=0.4)  # fmt: skip
    ax1.plot(offered, [lv["goodput_hz"] for lv in levels], "-", color="C0", label="goodput (median)")
    ax1.plot(offered, offered, ":", color="grey", label="offered")
    refused = [
        lv["offered_request_hz"] * (lv["outcomes"]["refused_server"] + lv["outcomes"]["refused_local"]) / lv["requests"]
        for lv in levels
    ]
    ax1.plot(offered, refused, "-", color="C2", label="refused (all runs)")
    if levels[0]["goodput_hz"] > 0 and len(levels) > 1 and levels[0].get("multiple") == 1:
        ax1.axhline(OVERLOAD_GOODPUT_SHARE * levels[0]["goodput_hz"], color="C3", lw=1, ls="--",
                    label="90 % of goodput at capacity")  # fmt: skip
    ax1.set_ylabel("complete requests / s")
    ax1.legend(fontsize=8)
    ax1.grid(True, alpha=0.3)
    ax1.set_title(title)
    ax2.plot(offered, [lv["latency_p99_ms"] for lv in levels], "-", color="C1", label="p99, complete requests")
    ax2.axhline(OVERLOAD_P99_MAX_MS, color="C3", lw=1, ls="--", label="100 ms")
    ax2.set_yscale("log")
    ax2.set_ylabel("ms from the scheduled send")
    ax2.set_xlabel("offered load (requests / s)")
    ax2.legend(fontsize=8)
    ax2.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def zero_loss(result: dict[str, Any]) -> bool:
    """The sweep's criterion: every request after the warm-up complete (none refused, incomplete or lost)."""
    return bool(result["requests"] > 0 and result["outcomes"]["complete"] == result["requests"])


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
    out = args.out or Path(time.strftime("bench-%Y%m%d-%H%M%S"))
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
    base = "load" + ("-fused" if args.delivery == "fused" else "") + ("" if throttle else "-no-throttle")
    key = args.delivery + ("" if throttle else " (no client throttle)")
    settings = dict(workers=workers, rate=args.rate, seconds=seconds, warmup=warmup, timeout=args.timeout,
                    delivery=args.delivery, throttle=throttle)  # fmt: skip
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
        help="per-camera reports (subscribe; default) or fused single shots (snapshot())",
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

"""The load benchmark's figures: RSS sampling, each run's summary (outcomes, latency, growth), the
overload levels' verdicts, the capacity section and the plots (drvs_bench.load runs them)."""

from __future__ import annotations

import asyncio
import json
import math
import os
import re
import statistics
import time
from pathlib import Path
from typing import Any

from drvs.tools.launch import ManagedProcess

from .common import cpu_seconds, pyplot
from .helpers import percentile
from .load_robots import CAMERAS, NOT_RESOURCE_EXHAUSTED, OUTCOMES, expected_requests
from .stats import check_work, publish, verdict

#: Issue 27's overload targets, at each multiple of the capacity.
OVERLOAD_GOODPUT_SHARE = 0.9
OVERLOAD_P99_FACTOR = 2.0
OVERLOAD_P99_MAX_MS = 100.0
OVERLOAD_REFUSAL_MAX_MS = 50.0
#: How often the coordinator samples RSS and CPU of the server and cameras.
SAMPLE_S = 0.5


def rss_bytes(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    return 0


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
        # A refusal counts only if it came as RESOURCE_EXHAUSTED: not UNAVAILABLE (REFUSED_STREAM),
        # not CANCELLED (dropped by gRPC before the server took the call in).
        not_exhausted = sum(level["refused_by_reason"].get(k, 0) for k in NOT_RESOURCE_EXHAUSTED)
        refused = level["outcomes"]["refused_server"] + level["outcomes"]["refused_local"] - not_exhausted
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

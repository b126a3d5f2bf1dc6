"""drvs-bench service: what DRVS itself costs. Every figure is a ratio to something measured
in the same run on the same machine: this machine is shared and noisy.

The comparisons (DRVS latency against its floor, routing against an echo and a bare proxy, a
registry lookup at 10 000 against 100 cameras, camera CPU at 200 against 20 requests a second)
run interleaved, mode by mode, for stats.FULL_ROUNDS rounds (QUICK_ROUNDS with --quick; --rounds N). Each
figure and each ratio (taken within a round) is published as its median (under its old key, and
`_median`), its spread ([min, max], `_spread`) and every round's value (`_runs`). Each run's work
is counted and checked: a request that was refused, answered `busy`, reported an error or missed
a camera is a failure, never a delivered request, and a comparison run that did not do all of
its work raises stats.WorkMismatch instead of publishing a ratio.
"""

from __future__ import annotations

import asyncio
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from shapely.geometry import box

from drvs.camera.source import VideoSource
from drvs.core.geometry import FieldOfView
from drvs.detectors import CameraView, Frame, FrameAnalysis, HsvDetector
from drvs.robot import DrvsClient
from drvs.server.registry import Registry
from drvs.tools.launch import ManagedProcess, start_camera, start_server

from .common import (
    ALL_REGION,
    NO_RATE_LIMIT,
    YELLOW,
    bench_process,
    cpu_seconds,
    machine,
    peak_rss_bytes,
    pyplot,
    record_scene,
)
from .helpers import BLUE, WARMUP_REQUESTS, grid_position, moving_all_region, moving_filter, percentile
from .service_churn import measure_churn
from .stats import WorkMismatch, check_work, interleaved, publish, rounds, verdict

LATENCY_RATES = (30.0, 60.0, 120.0, 240.0, 480.0)
#: --quick tries one rate above 30 Hz: a smoke run of the sweep.
QUICK_SWEEP = (120.0,)
#: The comparison rate: latency against the floor, DRVS and the bare path alike.
LATENCY_RATE = 30.0
#: Targets: key -> (target, higher is better).
TARGETS: dict[str, tuple[float, bool]] = {
    "latency_p50_over_floor": (2.0, False),
    "latency_moving_p50_over_floor": (2.0, False),
    "routing_over_echo": (0.5, True),
    "routing_moving_over_echo": (0.5, True),
    "lookup_10k_over_100": (3.0, False),
    "camera_cpu_200_over_20": (3.0, False),
    "camera_cpu_200_over_20_moving": (3.0, False),
}
#: The service benchmark measures capacity and cost, not policy: besides the per-robot rate limit,
#: it lifts load shedding (`busy` past 64 queued forwards, and admission: `--admission-target 0`) and
#: the 2 s forward timeout, after which a
#: camera leaves routing until its next heartbeat (fake cameras never send one). On this shared
#: machine a stall of a fraction of a second would otherwise turn into refusals, and any refusal
#: fails the run's work check. It lifts the per-robot budget of forwarded bytes too, and has no
#: warm-up after start (a fresh server has no previous run's cameras to wait for), so replies are
#: what they are in steady state. On a registry in etcd, the per-identity write rates are lifted too.
#: So is the limit of calls open at once on one connection (100; the bare proxy has none): a loaded
#: server counts the calls it has answered and not yet released, and refuses a load process's 64
#: concurrent unary calls with REFUSED_STREAM (UNAVAILABLE) now and then (docs/operations.md, limits).
#: And the calls that may wait to be taken in (64 a method): a load process's 64 concurrent calls
#: may all wait there at once.
CAPACITY_NOT_POLICY = (
    *NO_RATE_LIMIT, "--forward-timeout", "60", "--max-queued-forwards", "100000",
    "--max-forward-bytes", "1e12", "--warm-up", "0", "--admission-target", "0",
    "--registration-rate", "1e9", "--pose-write-rate", "1e9", "--max-streams-per-connection", "0",
    "--max-pending-calls", "0",
)  # fmt: skip
#: Where the floors hold.
FLOOR_HOLDS = (
    "this message layout (DRVS's request, reply, forward and report messages, reports without "
    "detections), grpcio's default channel and server settings as drvs.wire._grpc sets them, loopback, "
    "and this machine at the time of the run; not a bound on every Python robot or router"
)


async def run_helper(name: str, *args: str, timeout: float = 300) -> dict[str, Any]:
    proc = await bench_process(name, *args).start()
    try:
        done = await proc.wait_for_line(r"^DONE (.*)", timeout=timeout)
        await proc.wait(timeout=30)
    finally:
        await proc.stop()
    return dict(json.loads(done.group(1)))


async def ack_server() -> tuple[ManagedProcess, str]:
    proc = await bench_process("ack", "ack-server").start()
    address = (await proc.wait_for_line(r"^LISTENING (\S+)", timeout=30)).group(1)
    return proc, address


async def listening(procs: list[ManagedProcess], name: str, *args: str) -> str:
    proc = await bench_process(name, *args).start()
    procs.append(proc)
    return (await proc.wait_for_line(r"^LISTENING (\S+)", timeout=30)).group(1)


def summarise(values: list[float]) -> dict[str, float]:
    return {f"p{q}": round(percentile(values, q), 3) for q in (50, 90, 99)}


def verdicts(out: dict[str, Any]) -> dict[str, Any]:
    """Each target against every round's value: met, missed, or the spread crosses it."""
    found = {}
    for key, (target, higher) in TARGETS.items():
        if f"{key}_runs" in out:
            found[key] = {
                "target": f"{'>=' if higher else '<='} {target:g}",
                "median": out[key],
                "spread": out[f"{key}_spread"],
                "verdict": verdict(out[f"{key}_runs"], target, higher_is_better=higher),
            }
    return found


class Selection:
    """What the floor puts on a request's path in the camera: selecting the prefetched blobs of a
    frame by the request's region (cameras find blobs as frames arrive, see drvs.camera.prefetch)."""

    def __init__(self, detector: HsvDetector, image: Any) -> None:
        self.detector = detector
        self.analysis = FrameAnalysis(Frame(image, 0.0, 0))
        self.blobs = {f: detector.blobs(self.analysis, f) for f in (YELLOW, BLUE)}
        self.fixed_region = box(*ALL_REGION)
        self.counter = 0

    def measure(self, moving: bool, count: int = 300) -> float:
        """Median ms to select: the same region object every time, or a new region (built and
        prepared, as a camera does with a region it has not seen) and the other filter each time."""
        times = []
        for _ in range(count):
            self.counter += 1
            t0 = time.perf_counter()
            if moving:
                region = box(*moving_all_region(self.counter))
                HsvDetector.select(self.blobs[moving_filter(self.counter)], region)
            else:
                HsvDetector.select(self.blobs[YELLOW], self.fixed_region)
            times.append((time.perf_counter() - t0) * 1000)
        return statistics.median(times)


def check_latency_run(name: str, run: dict[str, Any]) -> None:
    if run.get("error_kinds"):
        name = f"{name} (errors: {run['error_kinds']})"
    check_work(
        name,
        {"complete": run["requests"], "missing": 0, "error_reports": 0, "refused": 0, "no_camera": 0},
        {k: run[k] for k in ("complete", "missing", "error_reports", "refused", "no_camera")},
    )


async def measure_latency(quick: bool, out: dict[str, Any], n_rounds: int) -> None:
    with tempfile.TemporaryDirectory(prefix="drvs-bench-") as tmp:
        scene = record_scene(Path(tmp), cameras=3)
        procs: list[ManagedProcess] = []
        try:
            server, address = await start_server(*CAPACITY_NOT_POLICY)
            procs.append(server)
            for camera_id, rec in scene.items():
                procs.append(await start_camera(camera_id, rec.video, rec.homography_file, address, "--max-range", "6"))
            # The floor's selection, and (for reference only) a whole detection on the same frame.
            rec = scene["cam1"]
            source = VideoSource(str(rec.video))
            source.start()
            frame = await source.wait_first_frame(10)
            source.stop()
            fov = FieldOfView.compute(rec.homography, frame.size, 6.0)
            detector = HsvDetector(CameraView(rec.homography, fov, frame.size))
            times = []
            for i in range(200):
                t0 = time.perf_counter()
                detector.detect(FrameAnalysis(Frame(frame.image, 0.0, i)), YELLOW, box(*ALL_REGION))
                times.append((time.perf_counter() - t0) * 1000)
            detect_ms = statistics.median(times)
            selection = Selection(detector, frame.image)
            # The floor's hops: DRVS's message flow in bare grpc.aio (drvs_bench.bare), a bare server
            # forwarding each request to three bare cameras, one connection and stream per camera as
            # the DRVS server keeps, each camera reporting on a stream it keeps per robot.
            bare_cameras: list[str] = []
            for k in range(3):
                bare = await listening(procs, f"bare-camera{k}", "bare-camera", "--id", f"bare{k}")
                bare_cameras += ["--camera", bare]
            bare_address = await listening(procs, "bare-server", "bare-server", *bare_cameras)
            ack, ack_address = await ack_server()
            procs.append(ack)
            # Bare round trips on one stream (reference figures, kept from earlier runs' JSON).
            hot = await run_helper("rtt", "rtt", "--target", ack_address, "--calls", "300" if quick else "1000")
            paced = await run_helper(
                "rtt-30", "rtt", "--target", ack_address, "--calls", "90" if quick else "300", "--rate", "30"
            )
            seconds = 2.0 if quick else 10.0
            n = int(LATENCY_RATE * seconds)
            per_round: list[dict[str, Any]] = [{} for _ in range(n_rounds)]
            pooled: dict[str, dict[str, list[float]]] = {"drvs": {}, "drvs_moving": {}}
            modes = ("drvs", "drvs_moving", "bare", "bare_back_to_back")
            for r, mode in interleaved(modes, n_rounds):
                fig = per_round[r]
                rate_arg = str(LATENCY_RATE)
                if mode in ("drvs", "drvs_moving"):
                    extra = ["--moving", "--first-index", str(WARMUP_REQUESTS + 100_000 * (r + 1))]
                    run = await run_helper(
                        f"latency-{mode}", "latency", "--server", address, "--rate", rate_arg, "--requests", str(n),
                        "--warmup", str(WARMUP_REQUESTS), *(extra if mode == "drvs_moving" else []),
                    )  # fmt: skip
                    check_latency_run(f"latency {mode} at {rate_arg} Hz, round {r + 1}", run)
                    fig[f"{mode}_first_p50"] = percentile(run["first_ms"], 50)
                    fig[f"{mode}_last_p50"] = percentile(run["last_ms"], 50)
                    pooled[mode].setdefault("first", []).extend(run["first_ms"])
                    pooled[mode].setdefault("last", []).extend(run["last_ms"])
                    if mode == "drvs" and r == 0:
                        out["robot_client_peak_rss_bytes"] = run["peak_rss_bytes"]
                else:
                    back_to_back = mode == "bare_back_to_back"
                    count = 200 if back_to_back else n
                    run = await run_helper(
                        f"bare-robot-{mode}", "bare-robot", "--server", bare_address, "--cameras", "3",
                        "--requests", str(count), "--rate", "0" if back_to_back else rate_arg,
                        "--warmup", str(WARMUP_REQUESTS),
                    )  # fmt: skip
                    check_work(f"latency {mode}, round {r + 1}", {"completed": count}, {"completed": run["completed"]})
                    fig[f"{mode}_first_p50"] = percentile(run["first_ms"], 50)
                    fig[f"{mode}_last_p50"] = percentile(run["last_ms"], 50)
                    if not back_to_back:
                        fig["select_ms"] = selection.measure(moving=False)
                        fig["select_moving_ms"] = selection.measure(moving=True)
            floor: dict[str, Any] = {}
            floors = {
                "floor_ms": [f["bare_first_p50"] + f["select_ms"] for f in per_round],
                "floor_moving_ms": [f["bare_first_p50"] + f["select_moving_ms"] for f in per_round],
                "floor_last_final_ms": [f["bare_last_p50"] + f["select_ms"] for f in per_round],
                "floor_back_to_back_ms": [f["bare_back_to_back_first_p50"] + f["select_ms"] for f in per_round],
                "bare_path_first_report_ms_p50": [f["bare_first_p50"] for f in per_round],
                "bare_path_last_report_ms_p50": [f["bare_last_p50"] for f in per_round],
                "select_ms_p50": [f["select_ms"] for f in per_round],
                "select_moving_ms_p50": [f["select_moving_ms"] for f in per_round],
            }
            for key, values in floors.items():
                publish(floor, key, values)
            floor.update({
                "detect_ms_p50": round(detect_ms, 3),
                "rtt_ms_p50_at_30hz": round(float(paced["rtt_ms_p50"]), 3),
                "rtt_ms_p50_back_to_back": round(float(hot["rtt_ms_p50"]), 3),
                "definition": "the work that must sit on a request's path: the hops, measured as DRVS's "
                "message flow in bare grpc.aio with no DRVS code (robot -> bare server on a long-lived "
                "DetectStream, the reply, a forward on one long-lived stream per camera to three bare "
                "cameras in processes of their own, each acknowledging and sending one report without "
                "detections on a report stream it keeps per robot), timed to the first report (floor_ms) "
                "and to the last (floor_last_final_ms); plus the selection: the median time to select a "
                "frame's prefetched blobs by the request's region (HsvDetector.select; a new region and "
                "alternating filter for floor_moving_ms). Same rate (30 Hz, one request at a time, timed "
                "from its scheduled send), same warm-up (50 back-to-back requests, not counted), no "
                "relays, as the DRVS runs. Not in it: a whole detection (cameras prefetch blobs as "
                "frames arrive; detect_ms_p50 is given for reference), encoding detections into reports. "
                "rtt_ms_* are bare round trips on one stream, for reference.",
                "holds_for": FLOOR_HOLDS,
            })  # fmt: skip
            out["latency_floor"] = floor
            pairs = {
                "latency_p50_over_floor": ("drvs_first_p50", "floor_ms"),
                "latency_moving_p50_over_floor": ("drvs_moving_first_p50", "floor_moving_ms"),
                "latency_p50_over_back_to_back_floor": ("drvs_first_p50", "floor_back_to_back_ms"),
                "latency_last_final_p50_over_floor": ("drvs_last_p50", "floor_last_final_ms"),
                "latency_moving_last_final_p50_over_floor": ("drvs_moving_last_p50", "floor_last_final_ms"),
            }
            ratios = {
                key: [f[num] / fl for f, fl in zip(per_round, floors[den], strict=True)]
                for key, (num, den) in pairs.items()
            }
            for key, values in ratios.items():
                publish(out, key, values)
            for key in ("drvs_first_p50", "drvs_last_p50", "drvs_moving_first_p50", "drvs_moving_last_p50"):
                publish(out, f"latency_{key}_ms", [f[key] for f in per_round])
            runs: dict[str, Any] = {}

            def entry(rate: float, first: list[float], last: list[float], achieved: float, failed: int) -> Any:
                return {
                    "sustained": failed == 0 and achieved >= 0.95 * rate,
                    "achieved_hz": round(achieved, 1),
                    "missing": failed,
                    "first_report_ms": summarise(first),
                    "last_final_ms": summarise(last),
                    "_first": first,
                    "_last": last,
                }

            rate_key = f"{LATENCY_RATE:g}"
            # 30 Hz: every round's requests pooled (each round's work was checked: none missing).
            runs[rate_key] = entry(LATENCY_RATE, pooled["drvs"]["first"], pooled["drvs"]["last"], LATENCY_RATE, 0)
            runs[rate_key]["rounds"] = n_rounds
            moving = pooled["drvs_moving"]
            out["latency_moving"] = {rate_key: entry(LATENCY_RATE, moving["first"], moving["last"], LATENCY_RATE, 0)}
            # The rates above: one run each, to find the highest rate sustained (a capacity search:
            # a failed request marks the rate not sustained instead of failing the benchmark).
            sweep_seconds = 2.0 if quick else 10.0
            for rate in QUICK_SWEEP if quick else LATENCY_RATES[1:]:
                run = await run_helper(
                    f"latency-{rate:g}", "latency", "--server", address, "--rate", str(rate),
                    "--requests", str(int(rate * sweep_seconds)), "--warmup", str(WARMUP_REQUESTS),
                )  # fmt: skip
                failed = run["requests"] - run["complete"]
                rate_key = f"{rate:g}"
                runs[rate_key] = entry(rate, run["first_ms"], run["last_ms"], run["achieved_hz"], failed)
                runs[rate_key]["failed"] = {k: run[k] for k in ("missing", "error_reports", "refused", "no_camera")}
                if not runs[rate_key]["sustained"] or percentile(run["last_ms"], 99) > 1000:
                    break
            out["latency"] = runs
            best = max((float(r) for r, v in runs.items() if v["sustained"]), default=0.0)
            out["latency_highest_sustained_hz"] = best
            out["camera_peak_rss_bytes"] = max(peak_rss_bytes(p.pid) for p in procs[1:4])
            out["server_peak_rss_bytes_3_cameras"] = peak_rss_bytes(server.pid)
        finally:
            for p in reversed(procs):
                await p.stop()


ROUTING_MODES = (
    ("echo_stream", "echo", "stream", False),
    ("routing_stream", "routing", "stream", False),
    ("routing_moving_stream", "routing", "stream", True),
    ("bare_proxy_stream", "bare_proxy", "stream", False),
    ("echo_unary", "echo", "unary", False),
    ("routing_unary", "routing", "unary", False),
)


async def measure_routing(quick: bool, out: dict[str, Any], n_rounds: int) -> None:
    cameras = 1000
    seconds = "1.5" if quick else "8"
    procs: list[ManagedProcess] = []
    try:
        ack, ack_address = await ack_server()
        procs.append(ack)
        server, address = await start_server("--lease-ttl", "3600", *CAPACITY_NOT_POLICY)
        procs.append(server)
        await run_helper("register", "register", "--server", address, "--camera-address", ack_address,
                         "--count", str(cameras))  # fmt: skip
        # The floor of any grpc.aio router: a bare proxy that answers each request on its stream and
        # forwards it on a long-lived stream to one of 1000 cameras in turn, with no DRVS code.
        bare_address = await listening(procs, "bare-proxy", "bare-server", "--camera", ack_address, "--fanout", "one",
                                       "--streams", str(cameras))  # fmt: skip
        targets = {"echo": ack_address, "routing": address, "bare_proxy": bare_address}
        # Warm-up, not counted: the server opens a connection to each of the 1000 cameras on its first
        # forward there, and the bare proxy its 1000 streams. Under load some of those first connects
        # time out; the server then skips that camera until it heartbeats, so the fake cameras
        # register again (as a heartbeat would) before the measured runs.
        for target in (address, bare_address):
            await run_helper("load-warmup", "routing-load", "--target", target, "--seconds", "3" if quick else "6")
        await run_helper("register", "register", "--server", address, "--camera-address", ack_address,
                         "--count", str(cameras))  # fmt: skip
        per_round: list[dict[str, float]] = [{} for _ in range(n_rounds)]
        errors = 0
        # --quick runs the unary modes (reference figures) in one round only.
        plan = list(interleaved(ROUTING_MODES, n_rounds))
        if quick:
            plan = [(r, m) for r, m in plan if m[2] == "stream" or r == 0]
        for r, (name, target, mode, moving) in plan:
            extra = ["--moving", "--first-index", str(1_000_000 * (r + 1))] if moving else []
            run = await run_helper(
                f"load-{name}", "routing-load", "--target", targets[target], "--seconds", seconds,
                "--mode", mode, *extra,
            )  # fmt: skip
            errors += run["errors"]
            check_work(
                f"routing {name}, round {r + 1} (errors: {run['error_kinds']})",
                {"errors": 0},
                {"errors": run["errors"]},
            )
            if run["calls"] <= 0:
                raise WorkMismatch(f"routing {name}, round {r + 1}: no request completed")
            per_round[r][name] = run["rps"]
        routing: dict[str, Any] = {"registered_cameras": cameras, "cameras_per_request": 1, "rounds": n_rounds}
        for name, *_ in ROUTING_MODES:
            publish(routing, f"{name}_rps", [f[name] for f in per_round if name in f])
        routing["errors"] = errors
        routing["definition"] = (
            "requests a second from 64 workers, each waiting for its reply; stream: each worker sends on its "
            "own DetectStream (as DrvsClient does), unary: DetectObjects calls; routing_moving: every request "
            "moves its region (up to 0.4 m) and alternates the filter, so request compaction and the region "
            "caches miss; bare_proxy: bare grpc.aio that answers each request and forwards it to one of the "
            "1000 cameras in turn. A refused request, an error reply or a reply naming no camera is an error, "
            "and any error fails the run. Modes interleaved, one run of each per round; ratios within a round."
        )
        routing["holds_for"] = FLOOR_HOLDS
        out["routing"] = routing

        def ratio(a: str, b: str) -> list[float]:
            return [f[a] / f[b] for f in per_round if a in f and b in f]

        # Requests travel on DetectStream (the client's way), so that is the headline; unary for reference.
        publish(out, "routing_over_echo", ratio("routing_stream", "echo_stream"))
        publish(out, "routing_moving_over_echo", ratio("routing_moving_stream", "echo_stream"))
        publish(out, "routing_over_echo_unary", ratio("routing_unary", "echo_unary"))
        # The best routing_over_echo a grpc.aio router that forwards each request could reach here,
        # and how much of it DRVS reaches.
        publish(out, "bare_proxy_over_echo", ratio("bare_proxy_stream", "echo_stream"))
        publish(out, "routing_over_bare_proxy", ratio("routing_stream", "bare_proxy_stream"))
        publish(out, "routing_moving_over_bare_proxy", ratio("routing_moving_stream", "bare_proxy_stream"))
    finally:
        for p in reversed(procs):
            await p.stop()


def measure_lookup(quick: bool, out: dict[str, Any], n_rounds: int) -> None:
    from drvs.core.geometry import homography_from_pose

    h_cache = {}
    registries = {}
    counts = (100, 1000, 10000)
    for count in counts:
        registry = Registry(lease_ttl_s=3600)
        for i in range(count):
            x, y = grid_position(i)
            key = (x, y)
            if key not in h_cache:
                h_cache[key] = homography_from_pose((x, y, 3.0), 90.0, 40.0, 60.0, (640, 480))
            registry.register(f"c{i}", "127.0.0.1:9", h_cache[key], (640, 480), {"hsv"}, 6.0)
        registry.cameras_seeing(box(0, 0, 1, 1))  # builds the index
        registries[count] = registry
    per_round: list[dict[int, float]] = [{} for _ in range(n_rounds)]
    for r, count in interleaved(counts, n_rounds):
        registry = registries[count]
        repeats = 4
        # New region objects every time: this measures the index, not the registry's memory of
        # regions it has routed before (which repeat in real use).
        rounds_of_regions = [
            [box(x - 0.5, y + 3.0, x + 0.5, y + 4.0) for x, y in (grid_position(i % count) for i in range(500))]
            for _ in range(repeats)
        ]
        t0 = time.perf_counter()
        for regions in rounds_of_regions:
            for region in regions:
                registry.cameras_seeing(region, "hsv")
        per_round[r][count] = (time.perf_counter() - t0) / (repeats * 500) * 1e6
    lookup: dict[str, Any] = {}
    for count in counts:
        publish(lookup, str(count), [round(f[count], 2) for f in per_round])
    out["lookup_us"] = {k: v for k, v in lookup.items() if not k.endswith(("_median", "_spread", "_runs"))}
    out["lookup_us_rounds"] = lookup
    publish(out, "lookup_10k_over_100", [f[10000] / f[100] for f in per_round])


CAMERA_MODES = (("idle", 0.0, False), ("20", 20.0, False), ("200", 200.0, False),
                ("20_moving", 20.0, True), ("200_moving", 200.0, True))  # fmt: skip


async def measure_camera_cpu(quick: bool, out: dict[str, Any], n_rounds: int) -> None:
    seconds = 1.5 if quick else 10.0
    with tempfile.TemporaryDirectory(prefix="drvs-bench-") as tmp:
        rec = record_scene(Path(tmp), cameras=1)["cam1"]
        procs: list[ManagedProcess] = []
        try:
            server, address = await start_server(*CAPACITY_NOT_POLICY)
            procs.append(server)
            cam = await start_camera("cam1", rec.video, rec.homography_file, address, "--max-range", "6")
            procs.append(cam)
            per_round: list[dict[str, dict[str, float]]] = [{} for _ in range(n_rounds)]
            counter = 1_000_000
            async with DrvsClient(address, listen="127.0.0.1:0") as client:
                for w in range(WARMUP_REQUESTS):
                    await client.detect(moving_filter(w), ALL_REGION)
                loop = asyncio.get_running_loop()
                for r, (name, rate, moving) in interleaved(CAMERA_MODES, n_rounds):
                    c0, t0 = cpu_seconds(cam.pid), loop.time()
                    n = int(rate * seconds)
                    if n == 0:  # the idle camera: it reads and decodes frames, no request comes
                        await asyncio.sleep(seconds)
                    tasks = []
                    for i in range(n):
                        delay = t0 + i / rate - loop.time()
                        if delay > 0:
                            await asyncio.sleep(delay)
                        counter += 1
                        filter_def = moving_filter(counter) if moving else YELLOW
                        region = moving_all_region(counter) if moving else ALL_REGION
                        tasks.append(loop.create_task(client.detect(filter_def, region, timeout_s=10)))
                    results = await asyncio.gather(*tasks)
                    c1, t1 = cpu_seconds(cam.pid), loop.time()
                    got: dict[str, float] = {
                        "requests": n,
                        "complete": sum(1 for res in results if res.complete and res.camera_ids and not res.errors),
                        "error_reports": sum(len(res.errors) for res in results),
                    }
                    kinds = sorted({e[:200] for res in results for e in res.errors})[:3]
                    what = f"camera CPU {name}, round {r + 1}" + (f" (errors: {kinds})" if kinds else "")
                    check_work(what, {"complete": n, "error_reports": 0}, got)
                    per_round[r][name] = {"cpu_s": c1 - c0, "wall_s": t1 - t0, "requests": n}
            loads: dict[str, Any] = {}
            for name, rate, _moving in CAMERA_MODES:
                entry: dict[str, Any] = {}
                publish(entry, "camera_cpu_per_s", [f[name]["cpu_s"] / f[name]["wall_s"] for f in per_round])
                if rate:
                    # What the requests cost over a camera that only reads frames: this round's idle
                    # CPU rate, over the same wall time, taken off; per request.
                    publish(entry, "marginal_cpu_ms_per_request", [
                        (f[name]["cpu_s"] - f["idle"]["cpu_s"] / f["idle"]["wall_s"] * f[name]["wall_s"])
                        / f[name]["requests"] * 1000
                        for f in per_round
                    ])  # fmt: skip
                    entry["incomplete"] = 0  # checked: every request complete, no error report
                loads[name] = entry
            loads["definition"] = (
                "one drvs-camera on a 20 fps 640x480 video; CPU of its process (all threads, /proc utime + "
                "stime) while one robot sends single-shot requests at the rate for the run's wall time; "
                "idle: no requests. marginal: (CPU - idle CPU rate x the same wall time) / requests. "
                "Fixed: one filter and region (every request shares the frame's blobs and region); moving: "
                "a new region each request and yellow and blue in turn. Modes interleaved per round."
            )
            out["camera_cpu"] = loads

            def ratio(a: str, b: str) -> list[float]:
                return [(f[a]["cpu_s"] / f[a]["wall_s"]) / (f[b]["cpu_s"] / f[b]["wall_s"]) for f in per_round]

            publish(out, "camera_cpu_200_over_20", ratio("200", "20"))
            publish(out, "camera_cpu_200_over_20_moving", ratio("200_moving", "20_moving"))
            for name in ("20", "200", "20_moving", "200_moving"):
                out[f"camera_marginal_cpu_ms_per_request_{name}"] = loads[name]["marginal_cpu_ms_per_request"]
                out[f"camera_marginal_cpu_ms_per_request_{name}_spread"] = loads[name][
                    "marginal_cpu_ms_per_request_spread"
                ]
        finally:
            for p in reversed(procs):
                await p.stop()


async def measure_server_memory(quick: bool, out: dict[str, Any], n_rounds: int) -> None:
    """n_rounds: unused (one registration run), as the other steps take it."""
    count = 2000 if quick else 10000
    procs: list[ManagedProcess] = []
    try:
        ack, ack_address = await ack_server()
        procs.append(ack)
        server, address = await start_server(
            "--lease-ttl", "3600", "--log-level", "INFO", "--max-cameras-per-identity", str(count)
        )  # fmt: skip
        procs.append(server)
        before = peak_rss_bytes(server.pid)
        reg = await run_helper("register", "register", "--server", address, "--camera-address", ack_address,
                               "--count", str(count), timeout=900)  # fmt: skip
        out["server_memory"] = {
            "cameras": count,
            "peak_rss_bytes": peak_rss_bytes(server.pid),
            "peak_rss_bytes_empty": before,
            "registration_s": round(reg["seconds"], 2),
        }
        out[f"server_peak_rss_bytes_{count}_cameras"] = peak_rss_bytes(server.pid)
    finally:
        for p in reversed(procs):
            await p.stop()


async def run_service(out_dir: Path, quick: bool, n_rounds: int = 0) -> dict[str, Any]:
    """n_rounds: the interleaved rounds of every comparison (0: --quick's or the full run's)."""
    n_rounds = n_rounds or rounds(quick)
    result: dict[str, Any] = {"benchmark": "service", "quick": quick, "rounds": n_rounds}
    steps = (
        ("latency", measure_latency),
        ("routing", measure_routing),
        ("camera CPU", measure_camera_cpu),
        ("server memory", measure_server_memory),
    )
    t0 = time.perf_counter()
    for name, step in steps:
        print(f"drvs-bench service: {name} ... ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
        await step(quick, result, n_rounds)
    print(f"drvs-bench service: registry lookup ... ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
    await asyncio.to_thread(measure_lookup, quick, result, n_rounds)
    print(f"drvs-bench service: registry churn ... ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
    await asyncio.to_thread(measure_churn, quick, result, n_rounds)
    print(f"drvs-bench service: done ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
    result["verdicts"] = verdicts(result)
    result["machine"] = machine()
    await asyncio.to_thread(write_outputs, result, out_dir)
    return result


def write_outputs(result: dict[str, Any], out: Path) -> None:
    plt = pyplot()

    out.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(9, 4.5), dpi=100)
    series = [(f"{rate} Hz", run) for rate, run in result.get("latency", {}).items()]
    series += [(f"{rate} Hz moving", run) for rate, run in result.get("latency_moving", {}).items()]
    for name, run in series:
        for key, style in (("_first", "-"), ("_last", "--")):
            values = np.sort(np.asarray(run[key]))
            if len(values):
                label = f"{name}, {'first report' if key == '_first' else 'last final report'}"
                ax.plot(values, np.linspace(0, 1, len(values)), style, label=label, lw=1.2)
    floor = result.get("latency_floor", {}).get("floor_ms")
    if floor:
        ax.axvline(floor, color="black", lw=1, ls=":", label=f"floor {floor:.1f} ms")
    ax.set_xscale("log")
    ax.set_xlabel("latency from request (ms)")
    ax.set_ylabel("fraction of requests")
    ax.set_title("Request to first report and to every camera's final report (3 cameras)")
    ax.legend(fontsize=7)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "latency.png")
    plt.close(fig)
    for run in [*result.get("latency", {}).values(), *result.get("latency_moving", {}).values()]:
        run.pop("_first", None)
        run.pop("_last", None)
    (out / "service.json").write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":  # the churn child's old command line: `python -m drvs_bench.service churn ...`
    from .service_churn import main

    raise SystemExit(main(sys.argv[1:]))

"""drvs-bench fusion's networked part: what fused delivery costs the server, against per-camera delivery.

A drvs-server and two drvs-camera processes play videos of the fusion scene's two overlapping
cameras (three still discs in the overlap, rendered by the simulator). A robot process
(drvs-bench robot, the paper benchmark's) asks single shots at 30 Hz over both cameras, run by run:

- per_camera: the paper's delivery, each camera's report to the robot's listener; a request is
  answered when the last camera's final report has arrived;
- fused: the same requests with fused delivery, the cameras' reports to the server, which fuses them
  and answers with one snapshot on the robot's stream;
- bare: the floor, DRVS's message flow in bare grpc.aio with no DRVS code (drvs_bench.bare): a bare
  server that answers each request and forwards it to two bare cameras, which report straight to the
  robot; the same rate, and requests, one at a time;
- idle: no robot, the same wall time: the server's CPU when nothing is asked (heartbeats, timers).

Each run's server CPU (/proc utime + stime, all threads) from the robot's START (after its warm-up)
to its DONE, per request, and over the idle rate (the marginal CPU per request); the bare server's
over the bare robot's whole run (its few warm-up requests counted as requests: it prints no START);
the robot's latency from its call to its answer (p50, p99). Ratios and differences are taken within
a round, the modes interleaved.
"""

from __future__ import annotations

import asyncio
import json
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from drvs.core.homography_file import save_homography
from drvs.sim.scene import write_video
from drvs.tools.launch import ManagedProcess, start_camera, start_server

from .common import YELLOW, bench_process, cpu_seconds
from .fusion_scene import REGION, Cameras, Disc
from .paper import check_drvs, check_fused
from .stats import check_work, interleaved, publish

COST_MODES = ("per_camera", "fused", "bare", "idle")
#: Back-to-back requests the bare robot sends before its paced ones (counted with them, see above).
BARE_WARMUP = 10
#: Requests per run at COST_RATE: 20 s a run in the full benchmark, 4 s with --quick.
FULL_COST_REQUESTS = 600
QUICK_COST_REQUESTS = 120
COST_RATE = 30.0
#: Three still discs well inside both cameras' views: every request finds each by both cameras.
STILL_DISCS = (Disc((-0.8, 3.0), 0.25), Disc((0.9, 4.4), 0.2), Disc((0.2, 5.6), 0.3))
#: Frames of each camera's looping video (20 fps: noise and lighting change; the discs do not).
VIDEO_FRAMES = 40


def record_overlap(directory: Path) -> dict[str, tuple[Path, Path]]:
    """Each camera's looping video of the still discs and its homography file."""
    cams = Cameras(seed=0)
    out = {}
    shapes = [(d.shape, cams.yellow) for d in STILL_DISCS]
    for cam, renderer in zip(cams.cameras, cams.renderers, strict=True):
        if any(cam.id not in cams.seen_by(d) for d in STILL_DISCS):
            raise RuntimeError(f"fusion cost: a still disc is not wholly in {cam.id}'s view")
        video = write_video(
            directory / f"{cam.id}.avi", (renderer.render_objects(shapes, v) for v in range(VIDEO_FRAMES)), cam.fps
        )
        hfile = directory / f"{cam.id}.homography.yaml"
        save_homography(hfile, cam.homography)
        out[cam.id] = (video, hfile)
    return out


async def run_robot(mode: str, server: str, requests: int, pids: dict[str, list[int]]) -> dict[str, Any]:
    """One run of a robot mode; its outcome with the server's and cameras' CPU over its measured interval."""
    loop = asyncio.get_running_loop()
    if mode == "idle":
        before = {k: sum(cpu_seconds(p) for p in v) for k, v in pids.items()}
        t0 = loop.time()
        await asyncio.sleep(requests / COST_RATE)  # measuring an interval with nothing asked, not waiting for anything
        wall = loop.time() - t0
        return {"wall_s": wall, **{f"{k}_cpu_s": sum(cpu_seconds(p) for p in v) - before[k] for k, v in pids.items()}}
    if mode == "bare":
        return await run_bare(pids["bare"], server, requests)
    region = ",".join(f"{v:g}" for v in REGION)
    args = ["robot", "--mode", "drvs", "--server", server, "--cameras", "2", "--requests", str(requests)]
    args += ["--rate", f"{COST_RATE:g}", f"--region={region}", "--filter", YELLOW]  # = : it starts with a minus
    if mode == "fused":
        args.append("--fuse")
    robot = await bench_process(f"robot-{mode}", *args).start()
    try:
        await robot.wait_for_line(r"^READY (\d+)", timeout=60)
        await robot.wait_for_line(r"^START$", timeout=120)
        before = {k: sum(cpu_seconds(p) for p in v) for k, v in pids.items()}
        t0 = loop.time()
        done = await robot.wait_for_line(r"^DONE (.*)", timeout=requests / COST_RATE + 120)
        used = {f"{k}_cpu_s": sum(cpu_seconds(p) for p in v) - before[k] for k, v in pids.items()}
        interval = loop.time() - t0
        outcome = dict(json.loads(done.group(1)))
        assert await robot.wait(timeout=30) == 0, robot.output()
    finally:
        await robot.stop()
    return {**outcome, **used, "interval_s": interval}


async def run_bare(bare_pid: list[int], bare_server: str, requests: int) -> dict[str, Any]:
    """One run of the bare robot against the bare server: its outcome and the bare server's CPU over the
    whole run (warm-up included: the bare robot prints no START)."""
    args = ["--server", bare_server, "--cameras", "2", "--requests", str(requests), "--rate", f"{COST_RATE:g}"]
    robot = await bench_process("bare-robot", "bare-robot", *args, "--warmup", str(BARE_WARMUP)).start()
    try:
        before = sum(cpu_seconds(p) for p in bare_pid)
        done = await robot.wait_for_line(r"^DONE (.*)", timeout=requests / COST_RATE + 120)
        used = sum(cpu_seconds(p) for p in bare_pid) - before
        outcome = {k: v for k, v in json.loads(done.group(1)).items() if not isinstance(v, list)}
        assert await robot.wait(timeout=30) == 0, robot.output()
    finally:
        await robot.stop()
    return {**outcome, "server_cpu_s": used, "server_requests": requests + BARE_WARMUP}


def check_run(mode: str, run: dict[str, Any], requests: int) -> None:
    if mode == "per_camera":
        check_drvs(mode, run, requests, 2, 2 * len(STILL_DISCS))  # each camera sees every disc
    elif mode == "fused":
        check_fused(mode, run, requests, len(STILL_DISCS))  # one world object per disc
    elif mode == "bare":
        check_work(mode, {"completed": requests}, {"completed": run["completed"]})


@dataclass
class CostProcesses:
    """What the cost runs ask: a drvs-server with two drvs-cameras playing the still discs, and the
    bare floor's server with its two bare cameras; `pids` by role (server, cameras, bare)."""

    address: str
    bare_address: str
    pids: dict[str, list[int]]

    def target(self, mode: str) -> str:
        return self.bare_address if mode == "bare" else self.address


async def start_cost_processes(tmp: Path, procs: list[ManagedProcess]) -> CostProcesses:
    """The cost runs' processes, recorded into `tmp`, each appended to `procs` (the caller stops them)."""
    recorded = await asyncio.to_thread(record_overlap, tmp)
    server, address = await start_server("--warm-up", "0")
    procs.append(server)
    camera_pids = []
    for camera_id, (video, hfile) in recorded.items():
        cam = await start_camera(camera_id, video, hfile, address, "--max-range", "6.5")
        procs.append(cam)
        camera_pids.append(cam.pid)
    bare_cameras: list[str] = []
    for k in range(2):
        bare = await bench_process(f"bare-camera{k}", "bare-camera", "--id", f"bare{k}").start()
        procs.append(bare)
        bare_cameras += ["--camera", (await bare.wait_for_line(r"^LISTENING (\S+)", timeout=30)).group(1)]
    bare_server = await bench_process("bare-server", "bare-server", *bare_cameras).start()
    procs.append(bare_server)
    bare_address = (await bare_server.wait_for_line(r"^LISTENING (\S+)", timeout=30)).group(1)
    pids = {"server": [server.pid], "cameras": camera_pids, "bare": [bare_server.pid]}
    return CostProcesses(address, bare_address, pids)


async def run_cost(result: dict[str, Any], rounds: int, quick: bool, requests: int = 0) -> dict[str, Any]:
    requests = requests or (QUICK_COST_REQUESTS if quick else FULL_COST_REQUESTS)
    procs: list[ManagedProcess] = []
    runs: list[dict[str, dict[str, Any]]] = [{} for _ in range(rounds)]
    with tempfile.TemporaryDirectory(prefix="drvs-bench-fusion-") as tmp:
        try:
            started = await start_cost_processes(Path(tmp), procs)
            for r, mode in interleaved(COST_MODES, rounds):
                print(f"drvs-bench fusion: round {r + 1}/{rounds}: cost, {mode} ...", file=sys.stderr, flush=True)
                run = await run_robot(mode, started.target(mode), requests, started.pids)
                check_run(mode, run, requests)
                runs[r][mode] = run
        finally:
            for proc in reversed(procs):
                await proc.stop()
    return summarise_cost(runs, requests)


def _marginal_ms(run: dict[str, dict[str, Any]], mode: str, requests: int) -> float:
    """The server's CPU per request over what it spends idle in the same time, ms."""
    idle_rate = float(run["idle"]["server_cpu_s"]) / float(run["idle"]["wall_s"])
    return 1000 * (float(run[mode]["server_cpu_s"]) - idle_rate * float(run[mode]["interval_s"])) / requests


def summarise_cost(runs: list[dict[str, dict[str, Any]]], requests: int) -> dict[str, Any]:
    out: dict[str, Any] = {
        "requests": requests,
        "rate_hz": COST_RATE,
        "cameras": 2,
        "discs": len(STILL_DISCS),
        "definition": "server_cpu_ms_per_request: the drvs-server's CPU (/proc utime + stime, all threads) from the "
        "robot's START to its DONE over the requests; _marginal_: less the idle server's CPU rate over the same "
        "time; latency: the robot's call to its answer (per-camera: the last camera's final report; fused: the "
        "snapshot); fused_added_latency_ms_*: fused minus per-camera, within each round. Requests ask for "
        "outlines (the API's default: the fusion merges outlines). bare_server_cpu_ms_per_request: the floor, "
        "DRVS's message flow in bare grpc.aio (drvs_bench.bare: answer, forward to two bare cameras, which "
        f"report to the robot) at the same rate, its CPU over the bare robot's whole run per request (its "
        f"{BARE_WARMUP} back-to-back warm-up requests and its connection counted: the floor is if anything "
        "high); *_over_bare_server_cpu: the mode's server CPU per request over the floor's, within each round",
    }
    for mode in ("per_camera", "fused"):
        for key, values in (
            ("server_cpu_ms_per_request", [1000 * r[mode]["server_cpu_s"] / requests for r in runs]),
            ("server_marginal_cpu_ms_per_request", [_marginal_ms(r, mode, requests) for r in runs]),
            ("cameras_cpu_ms_per_request", [1000 * r[mode]["cameras_cpu_s"] / requests for r in runs]),
            ("robot_cpu_ms_per_request", [1000 * r[mode]["cpu_s"] / requests for r in runs]),
            ("latency_ms_p50", [r[mode]["latency_ms_p50"] for r in runs]),
            ("latency_ms_p99", [r[mode]["latency_ms_p99"] for r in runs]),
        ):
            publish(out, f"{mode}_{key}", values)
    # The floor: the bare server's CPU per request, and each mode's over it within a round.
    bare = [1000 * r["bare"]["server_cpu_s"] / r["bare"]["server_requests"] for r in runs]
    publish(out, "bare_server_cpu_ms_per_request", bare)
    publish(out, "bare_robot_cpu_ms_per_request", [1000 * r["bare"]["cpu_s"] / requests for r in runs])
    for mode in ("per_camera", "fused"):
        publish(
            out,
            f"{mode}_over_bare_server_cpu",
            [1000 * r[mode]["server_cpu_s"] / requests / b for r, b in zip(runs, bare, strict=True)],
        )
    publish(out, "idle_server_cpu_cores", [r["idle"]["server_cpu_s"] / r["idle"]["wall_s"] for r in runs])
    publish(
        out,
        "fused_over_per_camera_server_cpu",
        [r["fused"]["server_cpu_s"] / r["per_camera"]["server_cpu_s"] for r in runs],
    )
    for q in ("p50", "p99"):
        key = f"latency_ms_{q}"
        publish(out, f"fused_added_latency_ms_{q}", [r["fused"][key] - r["per_camera"][key] for r in runs])
        publish(out, f"fused_over_per_camera_latency_{q}", [r["fused"][key] / r["per_camera"][key] for r in runs])
    return out

"""drvs-bench paper: the paper's Exp. C and D side by side in one run.

The robot, a process of its own, either asks DRVS (1500 single-shot requests at 30 Hz) or has
both cameras stream every frame (raw, or JPEG at quality 80) and detects on board. Counting TCP
relays in front of the robot measure the bytes its sockets carry; /proc gives its CPU time.
"""

from __future__ import annotations

import asyncio
import json
import re
import sys
import tempfile
from pathlib import Path
from typing import Any

from drvs.launch import ManagedProcess, start_camera, start_server
from drvs.meter import CountingRelay

from .common import CpuSampler, bench_process, machine, record_scene
from .service import ack_server, run_helper

BUCKET_S = 0.1
#: drvs: reports with floor outlines (the API's default); drvs_boxes: bounding boxes only, as the
#: paper's DRVS sent; raw / jpeg: both cameras stream frames, the robot detects on board.
MODES = ("drvs", "drvs_boxes", "raw", "jpeg")


async def run_mode(
    mode: str, server: str, cameras: dict[str, tuple[str, Path]], requests: int, rate: float
) -> dict[str, Any]:
    relays: list[CountingRelay] = []
    args = ["robot", "--mode", mode.split("_")[0], "--requests", str(requests), "--rate", str(rate)]
    if mode == "drvs_boxes":
        args.append("--no-outlines")
    callback_relay: CountingRelay | None = None
    if mode.startswith("drvs"):
        host, port = server.rsplit(":", 1)
        server_relay = CountingRelay(host, int(port), bucket_s=BUCKET_S)
        callback_relay = CountingRelay(bucket_s=BUCKET_S)  # target: the robot's listener, once it is up
        relays = [server_relay, callback_relay]
        for r in relays:
            await r.start()
        args += ["--server", f"127.0.0.1:{server_relay.port}", "--advertise", f"127.0.0.1:{callback_relay.port}"]
    else:
        for address, hfile in cameras.values():
            host, port = address.rsplit(":", 1)
            relay = CountingRelay(host, int(port), bucket_s=BUCKET_S)
            await relay.start()
            relays.append(relay)
            args += ["--camera", f"127.0.0.1:{relay.port}", "--homography", str(hfile)]
    robot = await bench_process(f"robot-{mode}", *args).start()
    sampler = CpuSampler(robot.pid, BUCKET_S)
    sampler.start()
    try:
        ready = await robot.wait_for_line(r"^READY (\d+)", timeout=60)
        if callback_relay is not None:
            callback_relay.set_target("127.0.0.1", int(ready.group(1)))
        done = await robot.wait_for_line(r"^DONE (.*)", timeout=requests / rate + 120)
        outcome = json.loads(done.group(1))
        assert await robot.wait(timeout=30) == 0, robot.output()
    finally:
        await sampler.stop()
        await robot.stop()
        for r in relays:
            await r.close()
    timeline: dict[int, int] = {}
    for r in relays:
        for k, v in r.timeline.items():
            timeline[k] = timeline.get(k, 0) + v
    total = sum(r.total for r in relays)
    return {
        **outcome,
        "bytes": total,
        "bytes_per_s": total / outcome["wall_s"],
        "bytes_timeline": [timeline.get(k, 0) for k in range(max(timeline, default=-1) + 1)],
        "cpu_load_timeline": [round(load, 4) for _, load in sampler.load()],
    }


async def run_paper(out: Path, requests: int, rate: float) -> dict[str, Any]:
    procs: list[ManagedProcess] = []
    with tempfile.TemporaryDirectory(prefix="drvs-bench-") as tmp:
        scene = record_scene(Path(tmp))
        try:
            # A new site: no previous run whose cameras could still be on their way back, so replies
            # carry no coverage_uncertain_s (5 bytes each for a lease after a restart).
            server, address = await start_server("--warm-up", "0")
            procs.append(server)
            cameras: dict[str, tuple[str, Path]] = {}
            for camera_id, rec in scene.items():
                cam = await start_camera(
                    camera_id, rec.video, rec.homography_file, address, "--max-range", "6", "--serve-frames"
                )
                procs.append(cam)
                listening = next(re.search(r"listening on (\S+)", line) for line in cam.lines if "listening on" in line)
                assert listening is not None
                cameras[camera_id] = (listening.group(1), rec.homography_file)
            modes = {}
            for mode in MODES:
                print(f"drvs-bench paper: {mode} ...", file=sys.stderr, flush=True)
                modes[mode] = await run_mode(mode, address, cameras, requests, rate)
            # The transport's floor for the robot's CPU: a bare grpc.aio process making one round trip
            # on a long-lived stream per request, at the same rate, to a server that answers at once:
            # no reports, no DRVS code. No robot that asks over grpc.aio can use less.
            print("drvs-bench paper: floor ...", file=sys.stderr, flush=True)
            ack, ack_address = await ack_server()
            procs.append(ack)
            floor = await run_helper(
                "rtt-floor", "rtt", "--target", ack_address, "--calls", str(requests), "--rate", str(rate)
            )
            # DRVS's whole message flow in bare grpc.aio (request, reply, a forward to each of the two
            # cameras, a report from each), and a robot that only wakes at the request rate.
            print("drvs-bench paper: bare-path and idle floors ...", file=sys.stderr, flush=True)
            bare_path = await run_bare_path(procs, len(cameras), requests, rate)
            idle = await run_helper("idle-robot", "idle-robot", "--requests", str(requests), "--rate", str(rate))
        finally:
            for proc in reversed(procs):
                await proc.stop()
    boxes, outlines = modes["drvs_boxes"], modes["drvs"]

    def cpu_rate(m: dict[str, Any]) -> float:
        return float(m["cpu_s"]) / float(m["wall_s"])

    result = {
        "benchmark": "paper",
        "requests": requests,
        "rate_hz": rate,
        "cameras": len(scene),
        "frame": "640x480 BGR, 20 fps",
        "modes": modes,
        "jpeg_mean_frame_bytes": modes["jpeg"]["bytes"] / max(1, modes["jpeg"]["frames"]),
        # Against the paper's DRVS (bounding boxes), then against reports with outlines.
        "bandwidth_ratio_raw": modes["raw"]["bytes_per_s"] / boxes["bytes_per_s"],
        "bandwidth_ratio_jpeg": modes["jpeg"]["bytes_per_s"] / boxes["bytes_per_s"],
        "robot_cpu_ratio": cpu_rate(modes["raw"]) / cpu_rate(boxes),
        "robot_cpu_ratio_jpeg": cpu_rate(modes["jpeg"]) / cpu_rate(boxes),
        "bandwidth_ratio_raw_outlines": modes["raw"]["bytes_per_s"] / outlines["bytes_per_s"],
        "bandwidth_ratio_jpeg_outlines": modes["jpeg"]["bytes_per_s"] / outlines["bytes_per_s"],
        "robot_cpu_ratio_outlines": cpu_rate(modes["raw"]) / cpu_rate(outlines),
        "robot_cpu_floor": {
            "cpu_s": floor["cpu_s"],
            "wall_s": floor["wall_s"],
            "definition": "a bare grpc.aio client: one request/reply round trip per request on one stream, "
            "same count and rate, to a server that answers at once; no reports, no DRVS code",
        },
        # The best robot_cpu_ratio any grpc.aio robot could reach: raw-frame CPU over the floor's.
        "robot_cpu_ratio_at_floor": cpu_rate(modes["raw"]) / (floor["cpu_s"] / floor["wall_s"]),
        "robot_cpu_bare_path": {
            "cpu_s": bare_path["cpu_s"],
            "wall_s": bare_path["wall_s"],
            "last_report_ms_p50": bare_path["last_report_ms_p50"],
            "definition": "DRVS's message flow in bare grpc.aio, with no DRVS code: the request on a "
            "long-lived stream, the server's reply, a forward to each camera, one report from each to the "
            "robot's listener; same count and rate",
        },
        "robot_cpu_ratio_at_bare_path": cpu_rate(modes["raw"]) / cpu_rate(bare_path),
        # The robot's CPU with DRVS over the same messages moved by bare grpc.aio: what DRVS's own code adds.
        "robot_cpu_over_bare_path": cpu_rate(boxes) / cpu_rate(bare_path),
        "robot_cpu_idle": {
            "cpu_s": idle["cpu_s"],
            "wall_s": idle["wall_s"],
            "definition": "an asyncio process that only wakes at the request rate and does nothing",
        },
        "robot_cpu_ratio_at_idle": cpu_rate(modes["raw"]) / cpu_rate(idle),
        "machine": machine(),
    }
    await asyncio.to_thread(write_outputs, result, out)
    return result


async def run_bare_path(procs: list[ManagedProcess], cameras: int, requests: int, rate: float) -> dict[str, Any]:
    async def listening(name: str, *args: str) -> str:
        proc = await bench_process(name, *args).start()
        procs.append(proc)
        return (await proc.wait_for_line(r"^LISTENING (\S+)", timeout=30)).group(1)

    camera_args: list[str] = []
    for k in range(cameras):
        camera_args += ["--camera", await listening(f"bare-camera{k}", "bare-camera", "--id", f"bare{k}")]
    server = await listening("bare-server", "bare-server", *camera_args)
    return await run_helper(
        "bare-robot", "bare-robot", "--server", server, "--cameras", str(cameras),
        "--requests", str(requests), "--rate", str(rate),
    )  # fmt: skip


def write_outputs(result: dict[str, Any], out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "paper.json").write_text(json.dumps(result, indent=1) + "\n")
    plot(result, out)


def plot(result: dict[str, Any], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = {
        "drvs": "DRVS, outlines",
        "drvs_boxes": "DRVS, boxes (as the paper)",
        "raw": "raw frame stream",
        "jpeg": "JPEG q80 frame stream",
    }
    fig, ax = plt.subplots(figsize=(9, 4.5), dpi=100)
    for mode, data in result["modes"].items():
        series = data["bytes_timeline"]
        ax.plot([i * BUCKET_S for i in range(len(series))], [max(v, 1) for v in series], label=labels[mode], lw=1)
    ax.set_yscale("log")
    ax.set_xlabel("time (s)")
    ax.set_ylabel(f"bytes to and from the robot per {BUCKET_S:g} s")
    ax.set_title(
        f"Robot network traffic (paper Fig. 10): raw/DRVS x{result['bandwidth_ratio_raw']:.0f}, "
        f"JPEG/DRVS x{result['bandwidth_ratio_jpeg']:.0f}"
    )
    ax.legend()
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "bandwidth.png")
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(9, 4.5), dpi=100)
    for mode, data in result["modes"].items():
        series = data["cpu_load_timeline"]
        windows = [series[max(0, i - 4) : i + 1] for i in range(len(series))]
        smooth = [sum(w) / len(w) for w in windows]
        ax.plot([i * BUCKET_S for i in range(len(smooth))], [100 * v for v in smooth], label=labels[mode], lw=1)
    for key, style, name in (
        ("robot_cpu_bare_path", "--", "bare grpc.aio, same messages"),
        ("robot_cpu_idle", ":", "idle asyncio loop at the same rate"),
    ):
        floor = result[key]
        ax.axhline(100 * floor["cpu_s"] / floor["wall_s"], color="black", ls=style, lw=1, label=f"floor: {name}")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("robot process CPU (% of one core, 0.5 s mean)")
    ax.set_title(f"Robot CPU load (paper Fig. 9): onboard raw / DRVS x{result['robot_cpu_ratio']:.1f}")
    ax.legend()
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "cpu.png")
    plt.close(fig)

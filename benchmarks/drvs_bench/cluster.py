"""drvs-bench cluster: several servers on one registry in a real etcd.

`--parts propagation`: how long a registration made through one server takes to be routable
through another.

A real etcd member (Debian's etcd-server, on loopback) and two `DrvsServer`s in this process, each
on its own gRPC port with `--registry etcd://…`. A camera registers through A over gRPC (a real
`Register` call, as a camera sends it). The delay runs on one clock from when the call is sent to
when B's watch has put the camera into B's routing index (B's `_apply_shared` returns): A reads the
id's holder from etcd, takes a lease, writes by compare-and-put and answers, and B hears of the
write on its watch, often before the camera hears A's answer. Registrations are spread out (one at a
time), so each delay is the path's own, not a queue's. Also published: the CPU seconds etcd spent
(its process, from /proc) against the two servers' (this process).

`--parts failover`: the gap a robot sees when the server its track goes through dies. Two
drvs-server processes on the etcd, a camera node in this process (pushed frames of a yellow disc)
and a robot that both know both servers; the robot tracks the disc at 10 Hz through A; after two
seconds A is killed (SIGKILL, at a random phase of the snapshot period); the track resumes
through B by itself, and the gap is the robot's own measure (`Track.gaps_s`: from the last
snapshot A sent to the first B sends). A new pair of servers each round.

`--parts throughput`: routing requests a second with one and with two servers, as a ratio. 1000
fake cameras (one acking endpoint) registered through A, routable through both; two load
processes (64 workers each, each on its own request stream, as drvs-bench service's routing
part) send single-shot requests for 8 s: both at A (one server), or one at A and one at B (two
servers); the sum of their requests a second. Modes interleaved, a ratio per round. On this
machine's 2 cores the two servers, the load, the fake cameras and etcd all share two cores: a
second server adds a process, not a core, so the ratio measures what a second server costs or
gains here, not what one on its own machine would.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import random
import re
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from grpc import aio

from drvs.camera import CameraNode, PushSource
from drvs.filters import HsvRange
from drvs.geometry import homography_from_pose
from drvs.launch import cpu_seconds, start_etcd, start_server
from drvs.robot import DrvsClient
from drvs.server import DrvsServer
from drvs.server.config import ServerConfig
from drvs.sim.scene import FloorPatch, render_view
from drvs.v1 import registry_pb2_grpc

from .common import YELLOW, machine, pyplot, write_result
from .fakes import register_message
from .helpers import percentile
from .stats import FULL_ROUNDS, QUICK_ROUNDS, WorkMismatch, interleaved, publish

#: The bench camera: 3 m up at the origin, looking 40° down along +y, 60° wide.
HOMOGRAPHY = homography_from_pose((0.0, 0.0, 3.0), 90.0, 40.0, 60.0, (640, 480))
FULL_REGISTRATIONS = 300
QUICK_REGISTRATIONS = 40
PARTS = ("propagation", "failover", "throughput")
THROUGHPUT_CAMERAS = 1000
FULL_FAILOVERS = 5
QUICK_FAILOVERS = 2
TRACK_RATE_HZ = 10.0


async def propagation(registrations: int) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="drvs-bench-etcd-") as data:
        members = await start_etcd(Path(data))
        try:
            registry = "etcd://" + members[0].address
            a = DrvsServer(config=ServerConfig(listen="127.0.0.1:0", registry=registry, lease_ttl_s=60))
            b = DrvsServer(config=ServerConfig(listen="127.0.0.1:0", registry=registry, lease_ttl_s=60))
            await a.start()
            await b.start()
            arrived: dict[str, float] = {}
            applied = asyncio.Event()
            original = b._apply_shared

            def timed(record: Any) -> Any:
                entry = original(record)
                arrived[record.camera_id] = time.perf_counter()
                applied.set()
                return entry

            b._apply_shared = timed  # type: ignore[method-assign]
            b.shared._apply = timed  # type: ignore[union-attr]
            assert members[0].proc is not None
            etcd_cpu0, own_cpu0 = cpu_seconds(members[0].proc.pid), time.process_time()
            delays: list[float] = []
            replies: list[float] = []
            try:
                async with aio.insecure_channel(a.address) as channel:
                    stub = registry_pb2_grpc.RegisterVisionServiceStub(channel)
                    for k in range(registrations):
                        camera_id = f"cam-{k:04d}"
                        applied.clear()
                        sent = time.perf_counter()
                        await stub.Register(register_message(camera_id, x=10.0 * k))
                        replies.append(time.perf_counter() - sent)
                        while camera_id not in arrived:
                            await asyncio.wait_for(applied.wait(), 10)
                            applied.clear()
                        delays.append(arrived[camera_id] - sent)
                etcd_cpu, own_cpu = cpu_seconds(members[0].proc.pid) - etcd_cpu0, time.process_time() - own_cpu0
            finally:
                await a.stop()
                await b.stop()
        finally:
            for m in members:
                await m.stop()
    ms = [1000 * d for d in delays]
    reply_ms = [1000 * d for d in replies]
    return {
        "registrations": registrations,
        "propagation_ms_p50": statistics.median(ms),
        "propagation_ms_p99": percentile(ms, 99),
        "propagation_ms_max": max(ms),
        # The same registrations' Register call on A, sent to answered, for comparison.
        "register_reply_ms_p50": statistics.median(reply_ms),
        "register_reply_ms_p99": percentile(reply_ms, 99),
        "etcd_cpu_s": etcd_cpu,
        "servers_cpu_s": own_cpu,
        "etcd_share_of_cpu": etcd_cpu / (etcd_cpu + own_cpu) if etcd_cpu + own_cpu > 0 else 0.0,
        "delays_ms": ms,
    }


async def one_failover(data: Path, image: Any, phase: random.Random) -> tuple[float, int, int]:
    """One round: (the gap, seconds; snapshots before the kill; snapshots after it)."""
    members = await start_etcd(data)
    procs: list[Any] = []
    try:
        registry = "etcd://" + members[0].address
        servers = [await start_server("--registry", registry, "--lease-ttl", "2") for _ in range(2)]
        procs += [p for p, _ in servers]
        (a, a_address), (_, b_address) = servers
        both = f"{a_address},{b_address}"
        source = PushSource("bench camera")
        source.push(image)
        node = CameraNode("cam1", source, HOMOGRAPHY, both, max_range_m=6.0, detectors=("hsv",))
        async with node, DrvsClient.connect(both, robot_id="bench") as drvs:
            await asyncio.wait_for(node.registered.wait(), 30)
            before = after = 0
            killed = False
            loop = asyncio.get_running_loop()
            async with drvs.track(YELLOW, (-3.0, 1.5, 3.0, 7.0), rate_hz=TRACK_RATE_HZ, duration_s=6.0) as track:
                async for _snapshot in track:
                    source.push(image)  # a camera that keeps delivering frames
                    if track.resumes == 0:
                        before += 1
                        if not killed and before >= 2 * TRACK_RATE_HZ:
                            # At a random phase of the period (right after a snapshot is the best case).
                            loop.call_later(phase.uniform(0, 1 / TRACK_RATE_HZ), a.kill)
                            killed = True
                    else:
                        after += 1
            if track.resumes != 1 or not track.gaps_s:
                raise RuntimeError(f"the track did not resume once (resumes {track.resumes}, gaps {track.gaps_s})")
            return track.gaps_s[0], before, after
    finally:
        for proc in reversed(procs):
            await proc.stop()
        for m in members:
            await m.stop()


async def failover(rounds: int) -> dict[str, Any]:
    patches = [FloorPatch.disc((0.0, 4.0), 0.3, HsvRange.parse(YELLOW).centre_bgr())]
    image = render_view(HOMOGRAPHY, (640, 480), patches)
    gaps, befores, afters = [], [], []
    phase = random.Random(19)
    for _ in range(rounds):
        with tempfile.TemporaryDirectory(prefix="drvs-bench-etcd-") as data:
            gap, before, after = await one_failover(Path(data), image, phase)
        gaps.append(1000 * gap)
        befores.append(before)
        afters.append(after)
    period_ms = 1000 / TRACK_RATE_HZ
    return {
        "rounds": rounds,
        "track_rate_hz": TRACK_RATE_HZ,
        "gap_ms_median": statistics.median(gaps),
        "gap_ms_spread": [min(gaps), max(gaps)],
        "gaps_ms": gaps,
        # Snapshots that did not come: the gap less the one period that always separates two.
        "snapshots_missed_median": statistics.median([max(0.0, g / period_ms - 1) for g in gaps]),
        "snapshots_before_kill": befores,
        "snapshots_after_kill": afters,
    }


async def throughput(quick: bool) -> dict[str, Any]:
    from .service import CAPACITY_NOT_POLICY, ack_server, run_helper

    seconds = "2" if quick else "8"
    n_rounds = QUICK_ROUNDS if quick else FULL_ROUNDS
    procs: list[Any] = []
    with tempfile.TemporaryDirectory(prefix="drvs-bench-etcd-") as data:
        members = await start_etcd(Path(data))
        try:
            registry = "etcd://" + members[0].address
            ack, ack_address = await ack_server()
            procs.append(ack)
            flags = ("--registry", registry, "--lease-ttl", "3600", *CAPACITY_NOT_POLICY)
            servers = [await start_server(*flags) for _ in range(2)]
            procs += [p for p, _ in servers]
            (_, a_address), (b, b_address) = servers

            async def register() -> None:
                seen = len(b.lines)
                await run_helper("register", "register", "--server", a_address, "--camera-address", ack_address,
                                 "--count", str(THROUGHPUT_CAMERAS))  # fmt: skip
                # B's watch applies the registrations in order: the last one's log line says all are in.
                last = re.compile(rf"camera fake{THROUGHPUT_CAMERAS - 1} registered at \S+ through")
                await b.wait_for_line(last, timeout=60, start=seen)

            async def load(targets: tuple[str, str]) -> float:
                runs = await asyncio.gather(
                    *(run_helper(f"load-{i}", "routing-load", "--target", t, "--seconds", seconds)
                      for i, t in enumerate(targets))
                )  # fmt: skip
                if any(r["errors"] for r in runs):
                    raise WorkMismatch(f"throughput: errors {[r['error_kinds'] for r in runs]}")
                return float(sum(r["rps"] for r in runs))

            await register()
            # Warm-up, not counted: each server opens its 1000 camera connections on first use; the
            # fake cameras register again after it (some first connects time out under load).
            await load((a_address, b_address))
            await register()
            modes = {"one": (a_address, a_address), "two": (a_address, b_address)}
            per_round: list[dict[str, float]] = [{} for _ in range(n_rounds)]
            for r, mode in interleaved(list(modes), n_rounds):
                per_round[r][mode] = await load(modes[mode])
        finally:
            for proc in reversed(procs):
                await proc.stop()
            for m in members:
                await m.stop()
    result: dict[str, Any] = {"cameras": THROUGHPUT_CAMERAS, "rounds": n_rounds, "seconds_per_run": float(seconds)}
    publish(result, "rps_one_server", [p["one"] for p in per_round])
    publish(result, "rps_two_servers", [p["two"] for p in per_round])
    publish(result, "two_over_one", [p["two"] / p["one"] for p in per_round])
    result["cores"] = os.cpu_count()
    return result


def run_cluster(
    quick: bool, parts: list[str], registrations: int | None = None, rounds: int | None = None
) -> dict[str, Any]:
    result: dict[str, Any] = {"machine": machine(), "parts": parts}
    if "propagation" in parts:
        count = registrations or (QUICK_REGISTRATIONS if quick else FULL_REGISTRATIONS)
        result["propagation"] = asyncio.run(propagation(count))
    if "failover" in parts:
        result["failover"] = asyncio.run(failover(rounds or (QUICK_FAILOVERS if quick else FULL_FAILOVERS)))
    if "throughput" in parts:
        result["throughput"] = asyncio.run(throughput(quick))
    return result


def plot(result: dict[str, Any], out: Path) -> None:
    if "propagation" not in result:
        return
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    ms = sorted(result["propagation"]["delays_ms"])
    ax.plot(ms, [(i + 1) / len(ms) for i in range(len(ms))], "-")
    ax.set_xlabel("Register sent to A -> routable through B, ms")
    ax.set_ylabel("fraction of registrations")
    ax.set_title("Propagation through the shared registry (etcd)")
    fig.tight_layout()
    fig.savefig(out / "cluster.png")
    plt.close(fig)


def cluster_main(args: argparse.Namespace) -> int:
    parts = [p for p in args.parts.split(",") if p]
    if not parts or any(p not in PARTS for p in parts):
        print(f"drvs-bench cluster: --parts {args.parts!r}: expected some of {', '.join(PARTS)}", file=sys.stderr)
        return 2
    if args.registrations < 0 or args.rounds < 0:
        print("drvs-bench cluster: --registrations and --rounds must be >= 0", file=sys.stderr)
        return 2
    result = run_cluster(args.quick, parts, args.registrations or None, args.rounds or None)
    shown: dict[str, Any] = {"machine": result["machine"]}
    if "propagation" in result:
        shown["propagation"] = {k: v for k, v in result["propagation"].items() if k != "delays_ms"}
    for part in ("failover", "throughput"):
        if part in result:
            shown[part] = result[part]
    print(json.dumps(shown, indent=1))
    if args.out is not None:
        write_result(result, args.out, "cluster", plot)
    return 0


def add_cluster_parser(sub: Any) -> None:
    c = sub.add_parser("cluster", help="several servers on etcd: propagation of a registration, a robot's fail-over")
    c.add_argument(
        "--quick",
        action="store_true",
        help=f"a smoke run: {QUICK_REGISTRATIONS} registrations, {QUICK_FAILOVERS} fail-overs",
    )
    c.add_argument("--parts", default=",".join(PARTS), help=f"comma-separated parts (default: {','.join(PARTS)})")
    c.add_argument("--registrations", type=int, default=0, help=f"override (full: {FULL_REGISTRATIONS})")
    c.add_argument("--rounds", type=int, default=0, help=f"fail-overs (full: {FULL_FAILOVERS})")
    c.add_argument("--out", type=Path, default=None)
    c.set_defaults(func=cluster_main)

"""drvs-bench cluster: several servers on one registry in a real etcd.

`--parts propagation`: how long a registration made through one server takes to be routable
through another.

A real etcd member (Debian's etcd-server, on loopback) and two `DrvsServer`s in this process, each
on its own gRPC port with `--registry etcd://…`. A camera registers through A over gRPC (a real
`Register` call, as a camera sends it). The delay runs on one clock from when the call is sent to
when B's watch has put the camera into B's routing index (B's `EtcdBackend.apply` returns): A reads the
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
processes (64 workers each, each on its own request stream over the process's one channel) send
single-shot requests for 8 s, their windows started together on a signal: both at A (one
server), or one at A and one at B (two servers); the sum of their routed requests a second. A
request the server's door refuses for overload (RESOURCE_EXHAUSTED, see drvs.server.admission) is
counted apart (`refused_per_s_*`) and its stream waits as the hint says, as a robot does. Modes
interleaved, a ratio per round. On a 2-core machine the two servers, the load, the fake cameras
and etcd all share two cores: a second server adds a process, not a core, so the ratio measures
what a second server costs or gains there, not what one on its own machine would.

The throughput part also measures `drvs-server --workers N` (out["workers"]): for each N in
`--workers-list` (default 1,2,4; --quick 1,2) one drvs-server with N worker processes on one port
(SO_REUSEPORT) and the registry in a real etcd, all started at once and taking turns (rounds
interleaved over N). The same 1000 fake cameras, spread over max(2, cores/4) acking processes,
are registered once and routed by every worker. max(2, cores/2) load processes each open
LOAD_CHANNELS channels (their own TCP connections: the kernel spreads connections, not requests,
over the workers) with LOAD_STREAMS request streams between them, warm up, and start their measured
window together on a signal. The figure is the sum of their routed requests a second, its ratio to
the smallest N within each round, and the CPU each process spent in the window (from /proc; the
server's workers summed and listed): the load and the fake cameras take cores too, so the cores
the machine had (os.cpu_count()) go with every figure. Where N + the harness's processes exceed
the cores, the run still happens and says so (`oversubscribed`).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import random
import re
import signal
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import grpc
from grpc import aio

from drvs.camera import CameraNode, PushSource
from drvs.core.filters import HsvRange
from drvs.core.geometry import homography_from_pose
from drvs.robot import DrvsClient
from drvs.server import DrvsServer
from drvs.server.config import ServerConfig
from drvs.sim.scene import FloorPatch, render_view
from drvs.tools.fakes import register_message
from drvs.tools.launch import SERVER_READY, ManagedProcess, cpu_seconds, running_etcd, start_etcd, start_server
from drvs.v1 import detection_pb2, detection_pb2_grpc, registry_pb2_grpc
from drvs.wire import _grpc

from .common import YELLOW, bench_process, machine, pyplot, write_result
from .etcd_writes import fleet_writes
from .helpers import grid_position, no_camera, one_camera_request, percentile, with_request_id
from .stats import FULL_ROUNDS, QUICK_ROUNDS, WorkMismatch, interleaved, publish, rounds

#: The bench camera: 3 m up at the origin, looking 40° down along +y, 60° wide.
HOMOGRAPHY = homography_from_pose((0.0, 0.0, 3.0), 90.0, 40.0, 60.0, (640, 480))
FULL_REGISTRATIONS = 300
QUICK_REGISTRATIONS = 40
PARTS = ("propagation", "failover", "throughput", "writes")
THROUGHPUT_CAMERAS = 1000
FULL_FAILOVERS = 5
QUICK_FAILOVERS = 2
TRACK_RATE_HZ = 10.0
#: drvs-server --workers N: the N measured by default, and by --quick.
WORKERS_LIST = (1, 2, 4)
QUICK_WORKERS_LIST = (1, 2)
#: Each load process: this many channels (each its own connection), this many request streams
#: spread over them (each stream one request at a time).
LOAD_CHANNELS = 8
LOAD_STREAMS = 64
#: A stream refused for overload waits at least this long (the server's hint, when it gives one).
MIN_RETRY_S = 0.01
#: A warm-up request refused for overload this many times fails the run.
WARM_TRIES = 50


async def propagation(registrations: int) -> dict[str, Any]:
    async with running_etcd() as members:
        registry = "etcd://" + members[0].address
        config = ServerConfig(listen="127.0.0.1:0", registry=registry, lease_ttl_s=60, registration_rate=1e9)
        a, b = DrvsServer(config=config), DrvsServer(config=config)
        await a.start()
        await b.start()
        arrived: dict[str, float] = {}
        applied = asyncio.Event()
        assert b.shared is not None
        original = b.shared._apply  # what b's etcd watch applies each registration with

        def timed(record: Any) -> Any:
            entry = original(record)
            arrived[record.camera_id] = time.perf_counter()
            applied.set()
            return entry

        b.shared._apply = timed
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


async def throughput(quick: bool, n_rounds: int | None = None) -> dict[str, Any]:
    from .service import CAPACITY_NOT_POLICY, ack_server, run_helper

    seconds = 2.0 if quick else 8.0
    n_rounds = n_rounds or rounds(quick)
    procs: list[Any] = []
    async with running_etcd() as members:
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

            async def load(targets: tuple[str, str]) -> dict[str, Any]:
                # One channel per load process, as before; refusals for overload are counted apart.
                return await load_window(list(targets), 1, seconds, {}, "throughput")

            await register()
            # Warm-up, not counted: each server opens its 1000 camera connections on first use; the
            # fake cameras register again after it (some first connects time out under load).
            await load((a_address, b_address))
            await register()
            modes = {"one": (a_address, a_address), "two": (a_address, b_address)}
            per_round: list[dict[str, dict[str, Any]]] = [{} for _ in range(n_rounds)]
            for r, mode in interleaved(list(modes), n_rounds):
                per_round[r][mode] = await load(modes[mode])
        finally:
            for proc in reversed(procs):
                await proc.stop()
    result: dict[str, Any] = {"cameras": THROUGHPUT_CAMERAS, "rounds": n_rounds, "seconds_per_run": seconds}
    publish(result, "rps_one_server", [p["one"]["rps"] for p in per_round])
    publish(result, "rps_two_servers", [p["two"]["rps"] for p in per_round])
    publish(result, "two_over_one", [p["two"]["rps"] / p["one"]["rps"] for p in per_round])
    publish(result, "refused_per_s_one_server", [p["one"]["refused_per_s"] for p in per_round])
    publish(result, "refused_per_s_two_servers", [p["two"]["refused_per_s"] for p in per_round])
    result["cores"] = os.cpu_count()
    return result


def harness_size(cores: int) -> tuple[int, int]:
    """(fake-camera processes, load processes) for a machine with `cores` cores."""
    return max(2, cores // 4), max(2, cores // 2)


class WorkerGroup:
    """One drvs-server --workers N: its supervisor, its address and its workers' pids."""

    def __init__(self, n: int, proc: ManagedProcess, address: str, pids: list[int]) -> None:
        self.n, self.proc, self.address, self.pids = n, proc, address, pids


async def start_group(n: int, flags: tuple[str, ...]) -> tuple[ManagedProcess, WorkerGroup]:
    proc, address = await start_server("--workers", str(n), *flags)
    try:
        ready = await proc.wait_for_lines(SERVER_READY, n, 60)
        if {m.group(1) for m in ready} != {address}:
            raise RuntimeError(f"workers listen on {sorted({m.group(1) for m in ready})}, not only {address}")
        pids = [proc.pid]  # --workers 1 is the plain server: one process, no supervisor
        if n > 1:
            started = await proc.wait_for_lines(r"worker (\d+) started \(pid (\d+)\)", n, 10)
            pids = [int(m.group(2)) for m in started]
    except BaseException:
        await proc.stop()
        raise
    return proc, WorkerGroup(n, proc, address, pids)


def camera_registration(i: int, address: str) -> Any:
    """Fake camera i (helpers.register's: on the grid, seen by one_camera_request(i)) at `address`."""
    x, y = grid_position(i)
    message = register_message(f"fake{i}", address=address)
    message.homography.m[:] = homography_from_pose((x, y, 3.0), 90.0, 40.0, 60.0, (640, 480)).to_list()
    message.forward_secret = f"drvs-bench-fake-camera-{i}"
    return message


async def register_all(groups: list[WorkerGroup], acks: list[str]) -> None:
    """THROUGHPUT_CAMERAS fake cameras, camera i at acks[i % len(acks)], registered through the first
    group; returns once every worker of every group has them all. The last one is registered after
    all the others are written, so a worker's log line for it (etcd's watch keeps the order) says
    that it has them all."""
    last = THROUGHPUT_CAMERAS - 1
    seen = {g.n: len(g.proc.lines) for g in groups}
    async with _grpc.insecure_channel(groups[0].address) as channel:
        stub = registry_pb2_grpc.RegisterVisionServiceStub(channel)
        sem = asyncio.Semaphore(32)

        async def one(i: int) -> None:
            async with sem:
                await stub.Register(camera_registration(i, acks[i % len(acks)]), timeout=60)

        await asyncio.gather(*(one(i) for i in range(last)))
        await one(last)
    pattern = rf"camera fake{last} registered at \S+ through"
    for g in groups:
        await g.proc.wait_for_lines(pattern, g.n, 120, seen[g.n])


async def load_window(
    targets: list[str], channels: int, seconds: float, watched: dict[str, list[int]], what: str
) -> dict[str, Any]:
    """One measured window: a cluster-load process at each of `targets` (LOAD_STREAMS streams over
    `channels` channels), started together on SIGUSR1 once all have warmed up. Routed requests a
    second and refusals a second (summed), the window's wall time, the loads' CPU seconds and, for
    each list in `watched`, every pid's CPU seconds over the window (from /proc)."""
    loads = [
        bench_process(f"load-{i}", "cluster-load", "--target", target, "--seconds", str(seconds),
                      "--channels", str(channels), "--concurrency", str(LOAD_STREAMS),
                      "--cameras", str(THROUGHPUT_CAMERAS))
        for i, target in enumerate(targets)
    ]  # fmt: skip
    try:
        await asyncio.gather(*(p.start() for p in loads))
        for p in loads:
            await p.wait_for_line(r"^READY$", timeout=120)
        cpu0 = {k: [cpu_seconds(pid) for pid in pids] for k, pids in watched.items()}
        t0 = time.perf_counter()
        for p in loads:
            os.kill(p.pid, signal.SIGUSR1)
        runs = [json.loads((await p.wait_for_line(r"^DONE (.*)", timeout=seconds + 120)).group(1)) for p in loads]
        wall = time.perf_counter() - t0
        cpu = {k: [cpu_seconds(pid) - c0 for pid, c0 in zip(pids, cpu0[k], strict=True)] for k, pids in watched.items()}
        for p in loads:
            await p.wait(timeout=30)
    finally:
        for p in loads:
            await p.stop()
    if any(r["errors"] for r in runs):
        raise WorkMismatch(f"{what}: errors {[r['error_kinds'] for r in runs]}")
    return {
        "rps": float(sum(r["rps"] for r in runs)),
        "refused_per_s": float(sum(r["refused_per_s"] for r in runs)),
        "wall_s": wall,
        "load_cpu_s": float(sum(r["cpu_s"] for r in runs)),
        "cpu_s": cpu,
    }


async def scaling_run(group: WorkerGroup, n_loads: int, seconds: float, others: dict[str, list[int]]) -> dict[str, Any]:
    """One window of n_loads load processes at `group`, each on LOAD_CHANNELS channels."""
    run = await load_window(
        [group.address] * n_loads, LOAD_CHANNELS, seconds, {"workers": group.pids, **others}, "workers"
    )
    cpu = run.pop("cpu_s")
    return {
        **run,
        "worker_cpu_s": cpu["workers"],
        "fake_cameras_cpu_s": sum(cpu["fake_cameras"]),
        "etcd_cpu_s": sum(cpu["etcd"]),
    }


async def workers_scaling(quick: bool, workers_list: list[int], n_rounds: int | None = None) -> dict[str, Any]:
    """drvs-server --workers N for each N in `workers_list`: routed requests a second at saturation."""
    from .service import CAPACITY_NOT_POLICY, ack_server

    cores = os.cpu_count() or 1
    n_acks, n_loads = harness_size(cores)
    seconds = 2.0 if quick else 8.0
    n_rounds = n_rounds or rounds(quick)
    procs: list[Any] = []
    async with running_etcd() as members:
        try:
            assert members[0].proc is not None
            flags = ("--registry", "etcd://" + members[0].address, "--lease-ttl", "3600", *CAPACITY_NOT_POLICY)
            acks = [await ack_server() for _ in range(n_acks)]
            procs += [p for p, _ in acks]
            groups: list[WorkerGroup] = []
            for n in workers_list:
                proc, group = await start_group(n, flags)
                procs.append(proc)
                groups.append(group)
            others = {"fake_cameras": [p.pid for p, _ in acks], "etcd": [members[0].proc.pid]}
            await register_all(groups, [a for _, a in acks])
            # Warm-up, not counted: each worker opens its connections to the cameras on first use;
            # the cameras register again after it (a first connect that timed out under load takes
            # a camera out of that worker's routing until it registers again).
            for group in groups:
                await scaling_run(group, n_loads, seconds, others)
            await register_all(groups, [a for _, a in acks])
            per_round: list[dict[int, dict[str, Any]]] = [{} for _ in range(n_rounds)]
            by_n = {g.n: g for g in groups}
            for r, n in interleaved(workers_list, n_rounds):
                per_round[r][n] = await scaling_run(by_n[n], n_loads, seconds, others)
        finally:
            for proc in reversed(procs):
                await proc.stop()
    base = workers_list[0]
    by_workers: dict[str, Any] = {}
    for n in workers_list:
        runs = [p[n] for p in per_round]
        d: dict[str, Any] = {"processes": n + n_acks + n_loads, "oversubscribed": n + n_acks + n_loads > cores}
        publish(d, "rps", [x["rps"] for x in runs])
        publish(d, "over_baseline", [p[n]["rps"] / p[base]["rps"] for p in per_round])
        publish(d, "refused_per_s", [x["refused_per_s"] for x in runs])
        # CPU as cores busy over the window (CPU seconds / wall seconds), each process kind summed.
        publish(d, "server_cores", [sum(x["worker_cpu_s"]) / x["wall_s"] for x in runs])
        publish(d, "load_cores", [x["load_cpu_s"] / x["wall_s"] for x in runs])
        publish(d, "fake_cameras_cores", [x["fake_cameras_cpu_s"] / x["wall_s"] for x in runs])
        publish(d, "etcd_cores", [x["etcd_cpu_s"] / x["wall_s"] for x in runs])
        d["worker_cpu_s_runs"] = [x["worker_cpu_s"] for x in runs]
        d["wall_s_runs"] = [x["wall_s"] for x in runs]
        by_workers[str(n)] = d
    return {
        "cores": cores,
        "workers_list": workers_list,
        "baseline_workers": base,
        "cameras": THROUGHPUT_CAMERAS,
        "fake_camera_processes": n_acks,
        "load_processes": n_loads,
        "channels_per_load": LOAD_CHANNELS,
        "streams_per_load": LOAD_STREAMS,
        "rounds": n_rounds,
        "seconds_per_run": seconds,
        "by_workers": by_workers,
    }


class StreamCaller:
    """A request stream of its own: one request at a time, the reply awaited. A refusal for overload
    (RESOURCE_EXHAUSTED from the server's admission) is returned as its retry hint, as a robot reads
    it; any other refusal, an ended stream or a reply naming no camera raises RuntimeError."""

    def __init__(self, channel: aio.Channel) -> None:
        self._call: Any = detection_pb2_grpc.DetectObjectBoundaryStub(channel).DetectStream()

    async def __call__(self, message: detection_pb2.DetectionRequest) -> float | None:
        """None when the request was routed; the seconds to wait when it was refused for overload."""
        await self._call.write(message)
        reply = await self._call.read()
        if not isinstance(reply, detection_pb2.DetectionReply):
            raise RuntimeError(f"stream ended: {reply}")
        if reply.HasField("error"):
            if reply.error.code == "RESOURCE_EXHAUSTED":
                return max(float(reply.error.retry_after_s), MIN_RETRY_S)
            raise RuntimeError(f"refused: {reply.error.code}: {reply.error.message}")
        if not reply.camera_ids:  # routed nowhere: not a request served
            raise RuntimeError(no_camera(reply))
        return None

    def close(self) -> None:
        self._call.cancel()


async def cluster_load(args: argparse.Namespace) -> None:
    """(internal) A load process of the workers measurement: `channels` channels (each its own
    connection), `concurrency` request streams over them, each one request at a time. Warms every
    stream up, prints READY, waits for SIGUSR1, then sends for `seconds` and prints DONE with its
    routed requests a second and its own CPU seconds. A request refused for overload is counted
    (`refused`), and its stream waits as the hint says, as a robot does (the server's door sheds
    what it cannot take: routed requests a second are what it serves at capacity); any other
    refusal, an error or a reply naming no camera is an error, never a request done."""
    loop = asyncio.get_running_loop()
    go = asyncio.Event()
    loop.add_signal_handler(signal.SIGUSR1, go.set)
    channels = [_grpc.insecure_channel(args.target) for _ in range(args.channels)]
    callers = [StreamCaller(channels[k % len(channels)]) for k in range(args.concurrency)]
    try:
        messages = [one_camera_request(i, args.callback) for i in range(args.cameras)]
        done = errors = refused = 0
        error_kinds: dict[str, int] = {}

        def failed(exc: Exception) -> None:
            nonlocal errors
            errors += 1
            kind = str(exc)[:200]
            error_kinds[kind] = error_kinds.get(kind, 0) + 1

        async def warm(k: int) -> None:
            for _ in range(WARM_TRIES):
                try:
                    wait = await callers[k](with_request_id(messages[k % len(messages)], f"warm{k}"))
                except (grpc.RpcError, RuntimeError) as exc:
                    failed(exc)  # a failed warm-up fails the run as any error does
                    return
                if wait is None:
                    return
                await asyncio.sleep(wait)  # refused for overload: as the hint says
            failed(RuntimeError(f"warm-up: refused for overload {WARM_TRIES} times"))

        await asyncio.gather(*(warm(k) for k in range(args.concurrency)))
        print("READY", flush=True)
        await go.wait()
        cpu0, t0 = time.process_time(), loop.time()
        end = t0 + args.seconds

        async def worker(k: int) -> None:
            nonlocal done, refused
            i = k
            while loop.time() < end:
                try:
                    wait = await callers[k](messages[i % len(messages)])
                except (grpc.RpcError, RuntimeError) as exc:
                    failed(exc)
                else:
                    if wait is None:
                        done += 1
                    else:
                        refused += 1
                        await asyncio.sleep(min(wait, max(0.0, end - loop.time())))
                i += args.concurrency

        await asyncio.gather(*(worker(k) for k in range(args.concurrency)))
        elapsed, cpu = loop.time() - t0, time.process_time() - cpu0
    finally:
        for caller in callers:
            caller.close()
        await asyncio.gather(*(c.close() for c in channels), return_exceptions=True)
    kinds = dict(sorted(error_kinds.items(), key=lambda kv: -kv[1])[:5])
    result = {
        "calls": done,
        "refused": refused,
        "errors": errors,
        "rps": done / elapsed,
        "refused_per_s": refused / elapsed,
        "cpu_s": cpu,
        "error_kinds": kinds,
    }
    print("DONE " + json.dumps(result), flush=True)


def run_cluster(
    quick: bool,
    parts: list[str],
    registrations: int | None = None,
    rounds: int | None = None,
    workers_list: list[int] | None = None,
) -> dict[str, Any]:
    result: dict[str, Any] = {"machine": machine(), "parts": parts}
    if "propagation" in parts:
        count = registrations or (QUICK_REGISTRATIONS if quick else FULL_REGISTRATIONS)
        result["propagation"] = asyncio.run(propagation(count))
    if "failover" in parts:
        result["failover"] = asyncio.run(failover(rounds or (QUICK_FAILOVERS if quick else FULL_FAILOVERS)))
    if "throughput" in parts:
        result["throughput"] = asyncio.run(throughput(quick, rounds))
        listed = workers_list or list(QUICK_WORKERS_LIST if quick else WORKERS_LIST)
        result["workers"] = asyncio.run(workers_scaling(quick, listed, rounds))
    if "writes" in parts:  # what a fleet writes to etcd (etcd_writes.py)
        result["writes"] = asyncio.run(fleet_writes(quick))
    return result


def plot(result: dict[str, Any], out: Path) -> None:
    if "workers" in result:
        plot_workers(result["workers"], out)
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


def plot_workers(workers: dict[str, Any], out: Path) -> None:
    """cluster_workers.png: routed requests a second against N (median, bars min..max), beside the
    baseline's median times N / baseline (what perfect scaling would give)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    ns = workers["workers_list"]
    data = [workers["by_workers"][str(n)] for n in ns]
    medians = [d["rps_median"] for d in data]
    low = [m - d["rps_spread"][0] for m, d in zip(medians, data, strict=True)]
    high = [d["rps_spread"][1] - m for m, d in zip(medians, data, strict=True)]
    ax.errorbar(ns, medians, yerr=[low, high], fmt="o-", capsize=4, label="measured (median, min..max)")
    base = workers["baseline_workers"]
    ax.plot(ns, [medians[0] * n / base for n in ns], ":", color="grey", label="linear in N")
    ax.axvline(workers["cores"], color="red", linestyle="--", linewidth=0.8, label=f"cores: {workers['cores']}")
    ax.set_xscale("log", base=2)
    ax.set_xticks(ns, [str(n) for n in ns])
    ax.set_xlabel("drvs-server --workers N")
    ax.set_ylabel("routed requests a second")
    ax.set_title(
        f"{workers['load_processes']} load processes, {workers['fake_camera_processes']} fake-camera processes, "
        f"{workers['cores']} cores",
        fontsize=9,
    )
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "cluster_workers.png")
    plt.close(fig)


def parse_workers_list(text: str) -> list[int] | None:
    """`1,2,4` as [1, 2, 4] (sorted, each a distinct whole number >= 1), or None if it is not one."""
    try:
        values = [int(v) for v in text.split(",")]
    except ValueError:
        return None
    if not values or min(values) < 1 or len(set(values)) != len(values) or max(values) > 256:
        return None
    return sorted(values)


def cluster_main(args: argparse.Namespace) -> int:
    parts = [p for p in args.parts.split(",") if p]
    if not parts or any(p not in PARTS for p in parts):
        print(f"drvs-bench cluster: --parts {args.parts!r}: expected some of {', '.join(PARTS)}", file=sys.stderr)
        return 2
    if args.registrations < 0 or args.rounds < 0:
        print("drvs-bench cluster: --registrations and --rounds must be >= 0", file=sys.stderr)
        return 2
    workers_list = None
    if args.workers_list is not None:
        workers_list = parse_workers_list(args.workers_list)
        if workers_list is None:
            print(
                f"drvs-bench cluster: --workers-list {args.workers_list!r}: expected distinct whole numbers "
                "from 1 to 256, comma-separated (e.g. 1,2,4,8)",
                file=sys.stderr,
            )
            return 2
    result = run_cluster(args.quick, parts, args.registrations or None, args.rounds or None, workers_list)
    shown: dict[str, Any] = {"machine": result["machine"]}
    if "propagation" in result:
        shown["propagation"] = {k: v for k, v in result["propagation"].items() if k != "delays_ms"}
    shown.update({part: result[part] for part in ("failover", "throughput", "writes") if part in result})
    if "workers" in result:
        shown["workers"] = {k: v for k, v in result["workers"].items() if k != "by_workers"}
        shown["workers"]["by_workers"] = {
            n: {k: v for k, v in d.items() if not k.endswith(("_runs", "_median"))}
            for n, d in result["workers"]["by_workers"].items()
        }
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
    rounds_help = f"fail-overs (full: {FULL_FAILOVERS}); throughput rounds (full: {FULL_ROUNDS}, quick: {QUICK_ROUNDS})"
    c.add_argument("--rounds", type=int, default=0, help=rounds_help)
    c.add_argument(
        "--workers-list",
        default=None,
        help="throughput: the drvs-server --workers N to measure, comma-separated "
        f"(default {','.join(map(str, WORKERS_LIST))}; --quick {','.join(map(str, QUICK_WORKERS_LIST))})",
    )
    c.add_argument("--out", type=Path, default=None)
    c.set_defaults(func=cluster_main)
    lo = sub.add_parser(
        "cluster-load", help="(internal) the cluster benchmark's load: several channels, a signal to go"
    )
    lo.add_argument("--target", required=True)
    lo.add_argument("--callback", default="127.0.0.1:9")
    lo.add_argument("--cameras", type=int, default=THROUGHPUT_CAMERAS)
    lo.add_argument("--channels", type=int, default=LOAD_CHANNELS)
    lo.add_argument("--concurrency", type=int, default=LOAD_STREAMS)
    lo.add_argument("--seconds", type=float, default=5.0)
    lo.set_defaults(func=lambda args: asyncio.run(cluster_load(args)) or 0)

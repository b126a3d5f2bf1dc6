"""drvs-bench cluster --parts propagation: how long a registration made through one server takes to
be routable through another, with the registry shared in a real etcd.

A real etcd member (Debian's etcd-server, on loopback) and two `DrvsServer`s in this process, each
on its own gRPC port with `--registry etcd://…`. A camera registers through A over gRPC (a real
`Register` call, as a camera sends it). The delay runs on one clock from when the call is sent to
when B's watch has put the camera into B's routing index (B's `_apply_shared` returns): A reads the
id's holder from etcd, takes a lease, writes by compare-and-put and answers, and B hears of the
write on its watch, often before the camera hears A's answer. Registrations are spread out (one at a
time), so each delay is the path's own, not a queue's. Also published: the CPU seconds etcd spent
(its process, from /proc) against the two servers' (this process).

Not measured yet (issue 19 goes on): routing throughput with one and with two servers, and the
fail-over gap a robot sees.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from grpc import aio

from drvs.launch import start_etcd
from drvs.server import DrvsServer
from drvs.server.config import ServerConfig
from drvs.v1 import registry_pb2_grpc

from .common import machine, pyplot, write_result
from .fakes import register_message
from .helpers import percentile

FULL_REGISTRATIONS = 300
QUICK_REGISTRATIONS = 40


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process, from /proc."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


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
            etcd_cpu0, own_cpu0 = _cpu_s(members[0].proc.pid), time.process_time()
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
                etcd_cpu, own_cpu = _cpu_s(members[0].proc.pid) - etcd_cpu0, time.process_time() - own_cpu0
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


def run_cluster(quick: bool, registrations: int | None = None) -> dict[str, Any]:
    result: dict[str, Any] = {"machine": machine(), "parts": ["propagation"]}
    result["propagation"] = asyncio.run(
        propagation(registrations or (QUICK_REGISTRATIONS if quick else FULL_REGISTRATIONS))
    )
    return result


def plot(result: dict[str, Any], out: Path) -> None:
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
    if args.parts != "propagation":
        print(f"drvs-bench cluster: --parts {args.parts!r}: only 'propagation' is built so far", file=sys.stderr)
        return 2
    if args.registrations < 0:
        print("drvs-bench cluster: --registrations must be >= 0", file=sys.stderr)
        return 2
    result = run_cluster(args.quick, args.registrations or None)
    shown = {k: v for k, v in result["propagation"].items() if k != "delays_ms"}
    print(json.dumps({"machine": result["machine"], "propagation": shown}, indent=1))
    if args.out is not None:
        write_result(result, args.out, "cluster", plot)
    return 0


def add_cluster_parser(sub: Any) -> None:
    c = sub.add_parser("cluster", help="several servers on etcd: how long a registration takes to propagate")
    c.add_argument("--quick", action="store_true", help=f"a smoke run: {QUICK_REGISTRATIONS} registrations")
    c.add_argument("--parts", default="propagation", help="parts to run (built so far: propagation)")
    c.add_argument("--registrations", type=int, default=0, help=f"override (full: {FULL_REGISTRATIONS})")
    c.add_argument("--out", type=Path, default=None)
    c.set_defaults(func=cluster_main)

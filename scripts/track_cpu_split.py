"""One-off breakdown of a track-following robot's CPU against its receive floor, by thread.

A bare server (drvs_bench.bare's track floor server) pushes synthetic three-object snapshots, written
as the DRVS server writes them for a DrvsClient (compact geometry, camera indices, ages), at 30 Hz.
In turn, each in a process of its own, the floor robot (one bare `async for` on the stream), the
DRVS robot (`DrvsClient.track`) and the DRVS robot with the conversion into a Snapshot replaced by a
constant one follow it for --snapshots after a warm-up; each prints its CPU a snapshot on the event
loop's thread (time.thread_time) and on the rest (gRPC's threads), and the DRVS robot the median
conversion time (thread_time_ns around snapshot_from_pb).

    PYTHONPATH=src:benchmarks .venv/bin/python scripts/track_cpu_split.py [--snapshots 300] [--rounds 3]

Not a benchmark (no target, no JSON): docs/benchmarks.md ("Where the excess goes") gives its result.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import re
import statistics
import subprocess
import sys
import time
from typing import Any

REGION = (0.0, 0.0, 5.0, 5.0)
FILTER = "hsv_014110130035225200"
RATE = 30.0


def synthetic_snapshots() -> list[Any]:
    from drvs.v1 import detection_pb2

    replies = []
    for k in range(10):
        reply = detection_pb2.DetectionReply(request_id="x")
        snapshot = reply.snapshot
        snapshot.time.GetCurrentTime()
        snapshot.camera_ids.extend(["cam0", "cam1"])
        for i in range(3):
            o = snapshot.objects.add()
            o.track_id = i + 1
            o.geometry_mm.extend([1000 * i + 500, 2000, -150, -150, 150, 150, k % 7, 0])
            o.uncertainty_m = 0.05
            o.camera_index.append(i % 2)
            o.last_seen_age_s = 0.01
            o.label = "yellow"
            o.score = 0.9
            o.area_m2 = 0.09
        replies.append(reply)
    return replies


def serve() -> None:
    from drvs_bench.bare import _TrackFloorServer
    from drvs_bench.helpers import serve_detection

    asyncio.run(serve_detection(_TrackFloorServer(synthetic_snapshots())))


async def follow_drvs(address: str, snapshots: int, convert: bool) -> tuple[int, float, float, list[int]]:
    import drvs.robot.track as track_module
    from drvs.core.model import Snapshot
    from drvs.robot import DrvsClient

    timings: list[int] = []
    real = track_module.snapshot_from_pb

    def timed(msg: Any, request_id: str, uncovered: Any) -> Snapshot:
        t = time.thread_time_ns()
        snapshot = real(msg, request_id, uncovered)
        timings.append(time.thread_time_ns() - t)
        return snapshot

    def constant(msg: Any, request_id: str, uncovered: Any) -> Snapshot:
        return Snapshot(0.0, (), {}, (), msg.sequence, msg.final, request_id)

    track_module.snapshot_from_pb = timed if convert else constant
    async with DrvsClient(address, robot_id="split") as client:
        async for _ in client.track(FILTER, REGION, rate_hz=RATE, duration_s=0.5, outlines=False):
            pass
        timings.clear()
        cpu, thread = time.process_time(), time.thread_time()
        count = 0
        duration = (snapshots - 1) / RATE
        async for _ in client.track(FILTER, REGION, rate_hz=RATE, duration_s=duration, outlines=False):
            count += 1
        return count, time.process_time() - cpu, time.thread_time() - thread, timings


async def follow_floor(address: str, snapshots: int) -> tuple[int, float, float, list[int]]:
    from drvs_bench.bare import follow_track

    from drvs.v1 import detection_pb2_grpc
    from drvs.wire import _grpc

    async with _grpc.insecure_channel(address) as channel:
        call = detection_pb2_grpc.DetectObjectBoundaryStub(channel).DetectStream()
        await follow_track(call, "warm", 15, RATE)
        cpu, thread = time.process_time(), time.thread_time()
        count = await follow_track(call, "measured", snapshots, RATE)
        return count, time.process_time() - cpu, time.thread_time() - thread, []


def robot(kind: str, address: str, snapshots: int) -> None:
    if kind == "floor":
        count, cpu, thread, timings = asyncio.run(follow_floor(address, snapshots))
    else:
        count, cpu, thread, timings = asyncio.run(follow_drvs(address, snapshots, kind == "drvs"))
    line = (
        f"{kind:<15} {count} snapshots: loop thread {1e6 * thread / count:4.0f} us a snapshot, "
        f"other threads {1e6 * (cpu - thread) / count:4.0f} us"
    )
    if timings:
        line += f", conversion median {statistics.median(timings) / 1000:.0f} us"
    print(line, flush=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--snapshots", type=int, default=300)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--serve", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--robot", help=argparse.SUPPRESS)
    parser.add_argument("--address", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.serve:
        serve()
        return 0
    if args.robot:
        robot(args.robot, args.address, args.snapshots)
        return 0
    me = [sys.executable, os.path.abspath(__file__)]
    server = subprocess.Popen([*me, "--serve"], stdout=subprocess.PIPE, text=True)
    try:
        assert server.stdout is not None
        found = re.search(r"LISTENING (\S+)", server.stdout.readline())
        assert found, "the pushing server did not start"
        for r in range(args.rounds):
            print(f"round {r + 1}, load average {os.getloadavg()[0]:.1f}", flush=True)
            for kind in ("floor", "drvs", "drvs-constant"):
                run = [*me, "--robot", kind, "--address", found.group(1), "--snapshots", str(args.snapshots)]
                subprocess.run(run, check=True, timeout=120 + args.snapshots / RATE)
    finally:
        server.terminate()
        server.wait()
    return 0


if __name__ == "__main__":
    sys.exit(main())

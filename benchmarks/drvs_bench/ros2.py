"""drvs-bench ros2: what drvs-ros2 adds between a snapshot and a ROS 2 subscriber.

The bridge's publishing half (drvs.ros2.bridge.Publisher: every topic's message built from the
snapshot, serialized and written through Cyclone DDS) runs in this process; a subscriber runs in
its own process (`python -m drvs_bench.ros2 subscriber`), plain Cyclone DDS readers of every topic
the bridge publishes with ROS 2's default QoS that take each sample (its bytes, as the DDS layer
hands them to a ROS 2 subscription) and note the monotonic clock when one of /drvs/objects is
taken. CLOCK_MONOTONIC is one clock for every process of the host, so

- latency = the subscriber's time of taking the sample - this process's time just before
  Publisher.publish(snapshot) was called: conversion, serialization, DDS on loopback and the
  subscriber's wake-up and take; p50 and p99 per round; split at the sample's source timestamp
  (the wall clock when Cyclone wrote it) into the bridge's share (objects_written: the call's
  start to the write of /drvs/objects, p50 and p99) and the delivery's (DDS and the subscriber);
- CPU per snapshot = this process's CPU time (every thread: Cyclone's own too) over the
  publishing phase divided by the snapshots; and, apart, the publishing thread's alone per call
  (p50, p99) and the publish call's wall time (p99: what the bridge itself adds to the tail,
  apart from the subscriber's wake-up on a loaded machine);
- the DDS floor: in the same round, with the same subscriber and writers, the same snapshots'
  payloads of every topic, encoded by the bridge before the clock starts (stamped FLOOR_SHIFT_S
  later so the subscriber tells them apart), written at the same rate with no bridge code between
  (drvs.ros2.dds.write_cdr alone): the CPU and latency of Cyclone and the pacing loop themselves
  (dds_floor_cpu_ms_per_snapshot, dds_floor_latency_p99_ms), the bridge's CPU over it
  (cpu_over_dds_floor) and beyond it (cpu_ms_beyond_dds_floor). The two phases run one after the
  other in each round, the bridge first in odd rounds, the floor first in even ones. What the
  benchmark made before the clock is frozen out of the garbage collector for both phases
  (gc.freeze), so that no full collection of it lands in one of them.

Each round publishes SNAPSHOTS snapshots (QUICK_SNAPSHOTS with --quick) of OBJECTS moving objects
(16-corner outlines, every topic: objects, obstacles, tracks, markers, diagnostics) at RATE_HZ,
made before the clock starts. Cyclone is confined to loopback (the tests' configuration) on a
random domain. Targets: p99 latency <= 2 ms, CPU <= 0.5 ms per snapshot; verdicts over the rounds.
A round may lose up to MAX_LOST of its /drvs/objects samples to a starved subscriber (counted as
"lost"; latency is over the samples taken); more, and the round fails.
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import os
import random
import struct
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from shapely.geometry import Point

from drvs.core.model import CameraError, Snapshot, WorldObject

from .common import machine, pyplot, write_result
from .helpers import percentile
from .stats import FULL_ROUNDS, QUICK_ROUNDS, WorkMismatch, measured, out_dir, publish, verdict

OBJECTS = 20
SNAPSHOTS = 1000
QUICK_SNAPSHOTS = 150
RATE_HZ = 50.0
TARGETS = {"latency_p99_ms": 2.0, "cpu_ms_per_snapshot": 0.5}
TOPIC = "/drvs/objects"
#: A round may lose this share of /drvs/objects samples (reported as "lost"), no more: a reliable
#: keep-last-10 writer replaces what a reader starved for 10 periods (a loaded machine) has not
#: taken, as ROS 2's default QoS does; latency is over the samples taken.
MAX_LOST = 0.01
#: The subscriber stops this long after the last /drvs/objects sample it took.
QUIET_S = 3.0
#: The DDS floor's samples are stamped this much later than the bridge's of the same snapshot.
FLOOR_SHIFT_S = 1000.0
#: The benchmark's snapshots lose camera cam3 every DIAGNOSED_EVERY-th (one second at RATE_HZ).
DIAGNOSED_EVERY = 50
CYCLONE_LOOPBACK = (
    '<CycloneDDS xmlns="https://cdds.io/config"><Domain Id="any"><General><Interfaces>'
    '<NetworkInterface name="lo"/></Interfaces><AllowMulticast>false</AllowMulticast></General>'
    "<Discovery><ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>32</MaxAutoParticipantIndex>"
    '<Peers><Peer Address="127.0.0.1"/></Peers></Discovery></Domain></CycloneDDS>'
)


def snapshots(count: int, start: float) -> list[Snapshot]:
    """`count` snapshots of OBJECTS people walking at 1 m/s, 1/RATE_HZ apart from `start`."""
    rng = random.Random(1)
    heading = [rng.uniform(0, 2 * math.pi) for _ in range(OBJECTS)]
    out = []
    for n in range(count):
        t = start + n / RATE_HZ
        objects = []
        for i in range(OBJECTS):
            vx, vy = math.cos(heading[i]), math.sin(heading[i])
            x, y = (i % 5) * 2.0 + vx * n / RATE_HZ, (i // 5) * 2.0 + vy * n / RATE_HZ
            outline = Point(x, y).buffer(0.25, quad_segs=4)  # 16 corners
            objects.append(
                WorldObject(i + 1, outline, outline.bounds, (x, y), (vx, vy), math.degrees(heading[i]), 0.05,
                            ("cam1", "cam2"), t, label="person", score=0.9, area_m2=outline.area)
            )  # fmt: skip
        missing = {"cam3": CameraError("UNAVAILABLE", "camera cam3: gone", "cam3")} if n % DIAGNOSED_EVERY == 0 else {}
        out.append(Snapshot(t, tuple(objects), missing, ("cam1", "cam2"), n, False, "bench"))
    return out


def subscriber(domain: int, count: int) -> int:
    """The subscriber process: a reader on every topic the bridge publishes (as RViz and Nav2 would
    be: the bridge's DDS side then delivers all of them), taking samples as the DDS layer under a
    ROS 2 subscription hands them over: serialized bytes (rclcpp's own deserialization is C++,
    Cyclone's Python one would time this process, not the bridge). Once it has `count` samples of
    /drvs/objects (or none came for QUIET_S seconds) it prints one JSON object: {"taken": {stamp
    ns: [monotonic ns when taken, the sample's source timestamp ns]}, "others": {topic: samples
    taken}}. Prints "ready" once its readers exist."""
    from cyclonedds._clayer import ddspy_take
    from cyclonedds.core import InstanceState, ReadCondition, SampleState, ViewState, WaitSet
    from cyclonedds.util import duration

    from drvs.ros2.convert import output_topics
    from drvs.ros2.dds import Node

    node = Node(domain)
    readers = {topic: node.reader(topic, kind) for topic, kind in output_topics("/drvs").items()}
    waitset = WaitSet(node.participant)
    ANY = SampleState.Any | ViewState.Any | InstanceState.Any
    for reader in readers.values():
        waitset.attach(ReadCondition(reader, ANY))
    objects = readers.pop(TOPIC)
    print("ready", flush=True)
    taken: dict[int, tuple[int, int]] = {}
    others = dict.fromkeys(readers, 0)
    deadline = last = time.monotonic() + 120
    while len(taken) < count and time.monotonic() < min(deadline, last + QUIET_S):
        waitset.wait(duration(seconds=1))
        for payload, info in ddspy_take(objects._ref, ANY, 64):
            now = time.monotonic_ns()
            last = now / 1e9
            if info.valid_data:  # header.stamp: the first field, after the 4-byte encapsulation
                sec, nanosec = struct.unpack_from("<iI", payload, 4)
                taken[sec * 10**9 + nanosec] = (now, info.source_timestamp)
        for topic, reader in readers.items():
            others[topic] += sum(info.valid_data for _, info in ddspy_take(reader._ref, ANY, 64))
    print(json.dumps({"taken": taken, "others": others}), flush=True)
    return 0


@dataclass
class Phase:
    """What one paced phase of a round measured: per snapshot its stamp's send times (monotonic
    and wall ns), the call's thread CPU and wall time; the process CPU over the phase."""

    sent: dict[int, tuple[int, int]] = field(default_factory=dict)
    thread_ns: list[int] = field(default_factory=list)
    call_ns: list[int] = field(default_factory=list)
    cpu_ns: int = 0


def paced(call: Callable[[int], object], count: int) -> Phase:
    """`call(n)` for n in range(count) at RATE_HZ, timed; the stamps sent are read back from the
    subscriber's samples, so `call` returns the stamp (ns) of the snapshot it wrote."""
    phase = Phase()
    cpu0 = time.process_time_ns()
    for n in range(count):
        next_at = time.monotonic() + 1 / RATE_HZ
        t0, wall0 = time.monotonic_ns(), time.time_ns()
        c0 = time.thread_time_ns()
        stamp = call(n)
        phase.thread_ns.append(time.thread_time_ns() - c0)
        phase.call_ns.append(time.monotonic_ns() - t0)
        assert isinstance(stamp, int)
        phase.sent[stamp] = (t0, wall0)
        if n + 1 < count:
            time.sleep(max(0.0, next_at - time.monotonic()))  # pacing at RATE_HZ, not synchronisation
    phase.cpu_ns = time.process_time_ns() - cpu0
    return phase


def floor_payloads(
    made: list[Snapshot], style: Any, prefix: str
) -> tuple[list[tuple[int, list[tuple[str, bytes]]]], list[int]]:
    """Per snapshot, its stamp (ns) FLOOR_SHIFT_S later and the bridge's payloads of every topic
    for it (its own MarkerState: the bridge's stays untouched), /diagnostics where the bridge
    sends it here (when the missing camera comes and goes: every DIAGNOSED_EVERY-th and the next);
    and the thread CPU (ns) each snapshot's encoding took, the snapshots encoded back to back."""
    from drvs.ros2.cdr import snapshot_payloads
    from drvs.ros2.convert import MarkerState
    from drvs.ros2.dds import cdr_padding

    markers = MarkerState()
    out = []
    encode_ns = []
    for n, snapshot in enumerate(made):
        at = snapshot.time + FLOOR_SHIFT_S
        c0 = time.thread_time_ns()
        payloads = list(
            snapshot_payloads(snapshot, style, markers, at, prefix, with_diagnostics=n % DIAGNOSED_EVERY < 2)
        )
        encode_ns.append(time.thread_time_ns() - c0)
        # Padded as write_cdr pads: it then hands these very bytes to Cyclone (+= b"" on bytes is a no-op).
        out.append((round(at * 1e9), [(topic, bytes(p) + cdr_padding(len(p))) for topic, p in payloads]))
    return out, encode_ns


def write_all(publisher: Any, pre: tuple[int, list[tuple[str, bytes]]]) -> int:
    """The floor's call: a snapshot's pre-encoded payloads written through the bridge's writers."""
    from drvs.ros2.dds import write_cdr

    stamp, payloads = pre
    for topic, payload in payloads:
        write_cdr(publisher.writers[topic], payload)
    return stamp


def one_round(domain: int, count: int, env: dict[str, str], bridge_first: bool = True) -> dict[str, Any]:
    from cyclonedds.core import DDSStatus, WaitSet
    from cyclonedds.util import duration

    from drvs.ros2.bridge import Publisher
    from drvs.ros2.convert import Style
    from drvs.ros2.dds import Node

    node = Node(domain)
    publisher = Publisher(node, Style(heights={"person": 1.8}), "/drvs")
    sub = subprocess.Popen(
        [sys.executable, "-m", "drvs_bench.ros2", "subscriber", "--domain", str(domain), "--count", str(2 * count)],
        stdout=subprocess.PIPE, text=True, env=env,
    )  # fmt: skip
    try:
        assert sub.stdout is not None
        if sub.stdout.readline().strip() != "ready":
            raise WorkMismatch("ros2: the subscriber did not start")
        waitset = WaitSet(node.participant)
        for writer in publisher.writers.values():
            writer.set_status_mask(DDSStatus.PublicationMatched)
            waitset.attach(writer)
        until = time.monotonic() + 30
        writers = list(publisher.writers.values())
        while not all(w.get_publication_matched_status().current_count for w in writers):  # type: ignore[no-untyped-call]
            if time.monotonic() > until:
                raise WorkMismatch("ros2: the subscriber never matched every writer")
            waitset.wait(duration(milliseconds=200))
        made = snapshots(count, time.time())
        # The floor's bytes: the same snapshots encoded before either clock starts, stamped FLOOR_SHIFT_S
        # later (the subscriber tells the two phases apart by the stamp).
        floor, encode_ns = floor_payloads(made, publisher.style, publisher.prefix)

        def publish(n: int) -> int:
            publisher.publish(made[n])
            return round(made[n].time * 1e9)

        phases = {"bridge": publish, "floor": lambda n: write_all(publisher, floor[n])}
        order = ("bridge", "floor") if bridge_first else ("floor", "bridge")
        # What this process made before the clock (the rounds' snapshots and the floor's payloads)
        # is set aside from the garbage collector: a full collection walking it, whose moment
        # follows from every allocation before it, would otherwise land in one phase or the other.
        gc.collect()
        gc.freeze()
        try:
            measured_phases = {phase: paced(phases[phase], count) for phase in order}
        finally:
            gc.unfreeze()
        out, _ = sub.communicate(timeout=120)
    finally:
        if sub.poll() is None:
            sub.kill()
            sub.wait()
    said = json.loads(out.strip().splitlines()[-1])
    taken = {int(k): (v[0], v[1]) for k, v in said["taken"].items()}
    bridge, floor_run = measured_phases["bridge"], measured_phases["floor"]
    sent = {**bridge.sent, **floor_run.sent}
    lost = {phase: len(set(m.sent) - set(taken)) for phase, m in measured_phases.items()}
    if set(taken) - set(sent) or max(lost.values()) > count * MAX_LOST:
        raise WorkMismatch(f"ros2: the subscriber took {len(set(taken) & set(sent))} of {len(sent)} snapshots")
    both = [s for s in bridge.sent if s in taken]
    latencies = [(taken[s][0] - bridge.sent[s][0]) / 1e6 for s in both]
    # Cyclone stamps a sample with the wall clock as it is written: the bridge's share of the latency.
    written = [(taken[s][1] - bridge.sent[s][1]) / 1e6 for s in both]
    delivered = [lat - w for lat, w in zip(latencies, written, strict=True)]
    floor_latencies = [(taken[s][0] - floor_run.sent[s][0]) / 1e6 for s in floor_run.sent if s in taken]
    cpu = bridge.cpu_ns / count / 1e6
    floor_cpu = floor_run.cpu_ns / count / 1e6
    thread_p50 = percentile([n / 1e6 for n in bridge.thread_ns], 50)
    floor_thread_p50 = percentile([n / 1e6 for n in floor_run.thread_ns], 50)
    # The encoding, paced: the publish call's thread CPU less the same writes' with nothing to encode.
    encode_paced = thread_p50 - floor_thread_p50
    encode_back_to_back = percentile([n / 1e6 for n in encode_ns], 50)
    return {
        "snapshots": count,
        "lost": lost["bridge"],
        "latency_p50_ms": percentile(latencies, 50),
        "latency_p99_ms": percentile(latencies, 99),
        "latency_max_ms": max(latencies),
        "objects_written_ms_p50": percentile(written, 50),
        "objects_written_ms_p99": percentile(written, 99),
        "delivery_ms_p99": percentile(delivered, 99),
        "cpu_ms_per_snapshot": cpu,
        "publish_thread_cpu_ms_p50": thread_p50,
        "publish_thread_cpu_ms_p99": percentile([n / 1e6 for n in bridge.thread_ns], 99),
        "publish_call_ms_p99": percentile([n / 1e6 for n in bridge.call_ns], 99),
        "dds_floor_cpu_ms_per_snapshot": floor_cpu,
        "dds_floor_thread_cpu_ms_p50": floor_thread_p50,
        "encode_back_to_back_ms_p50": encode_back_to_back,
        "encode_paced_ms_p50": encode_paced,
        "encode_paced_over_back_to_back": encode_paced / encode_back_to_back,
        "dds_floor_latency_p99_ms": percentile(floor_latencies, 99),
        "dds_floor_lost": lost["floor"],
        "cpu_over_dds_floor": cpu / floor_cpu,
        "cpu_ms_beyond_dds_floor": cpu - floor_cpu,
        "first": order[0],
        "other_topics_taken": said["others"],
    }


def run_ros2(out: Path, quick: bool, rounds: int) -> dict[str, Any]:
    count = QUICK_SNAPSHOTS if quick else SNAPSHOTS
    runs = []
    with tempfile.TemporaryDirectory(prefix="drvs-bench-ros2-") as tmp:
        config = Path(tmp) / "cyclonedds.xml"
        config.write_text(CYCLONE_LOOPBACK)
        os.environ["CYCLONEDDS_URI"] = config.as_uri()  # before this process's first participant
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join([p for p in sys.path if p])
        for r in range(rounds):  # which phase goes first alternates
            runs.append(one_round(random.randint(100, 230), count, env, bridge_first=r % 2 == 0))
            print(f"round {r + 1}/{rounds}: {runs[-1]}", file=sys.stderr, flush=True)
    result: dict[str, Any] = {
        "machine": machine(), "rounds": rounds, "objects": OBJECTS, "rate_hz": RATE_HZ, "runs": runs,
    }  # fmt: skip
    for key in (
        "latency_p50_ms",
        "latency_p99_ms",
        "latency_max_ms",
        "objects_written_ms_p50",
        "objects_written_ms_p99",
        "delivery_ms_p99",
        "cpu_ms_per_snapshot",
        "publish_thread_cpu_ms_p50",
        "publish_thread_cpu_ms_p99",
        "publish_call_ms_p99",
        "dds_floor_cpu_ms_per_snapshot",
        "dds_floor_thread_cpu_ms_p50",
        "dds_floor_latency_p99_ms",
        "cpu_over_dds_floor",
        "cpu_ms_beyond_dds_floor",
        "encode_back_to_back_ms_p50",
        "encode_paced_ms_p50",
        "encode_paced_over_back_to_back",
    ):
        publish(result, key, [r[key] for r in runs])
    result["targets"] = {
        key: {"target": target, "verdict": verdict([r[key] for r in runs], target, higher_is_better=False)}
        for key, target in TARGETS.items()
    }
    write_result(result, out, "ros2", _plot)
    return result


def _plot(result: dict[str, Any], out: Path) -> None:
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6))
    for ax, key, label in (
        (axes[0], "latency_p99_ms", "p99 latency, snapshot to subscriber (ms)"),
        (axes[1], "cpu_ms_per_snapshot", "bridge CPU per snapshot (ms)"),
    ):
        values = [r[key] for r in result["runs"]]
        ax.plot(range(1, len(values) + 1), values, "o-", label="bridge")
        floor = [r[f"dds_floor_{key}"] for r in result["runs"]]
        ax.plot(range(1, len(floor) + 1), floor, "s:", color="#777", label="DDS floor (pre-encoded bytes)")
        ax.axhline(TARGETS[key], color="#c33", linestyle="--", label="target")
        ax.set_xticks(range(1, len(values) + 1))
        ax.set_xlabel("round")
        ax.set_title(label, fontsize=9)
        ax.set_ylim(bottom=0)
        ax.legend(fontsize=7)
    fig.suptitle(f"drvs-ros2, {result['objects']} objects a snapshot at {result['rate_hz']:g} Hz")
    fig.tight_layout()
    fig.savefig(out / "ros2.png", dpi=100)
    plt.close(fig)


def ros2_main(args: argparse.Namespace) -> int:
    rounds = args.rounds or (QUICK_ROUNDS if args.quick else FULL_ROUNDS)
    if rounds < 1:
        print("drvs-bench ros2: --rounds must be > 0", file=sys.stderr)
        return 2
    out = out_dir(args.out)
    result = measured("ros2", lambda: run_ros2(out, args.quick, rounds))
    if result is None:
        return 1
    summary = {
        k: v
        for k, v in result.items()
        if k.endswith(("_ms", "_snapshot", "_spread", "_p50", "_p99", "_floor")) and not k.endswith("_median")
    }
    summary["targets"] = {k: v["verdict"] for k, v in result["targets"].items()}
    print(json.dumps(summary, indent=1))
    print(f"written: {out / 'ros2.json'}, {out / 'ros2.png'}")
    return 0


def add_ros2_parser(sub: Any) -> None:
    p = sub.add_parser("ros2", help="what drvs-ros2 adds: snapshot-to-subscriber latency and CPU per snapshot")
    p.add_argument("--quick", action="store_true", help=f"a smoke run: {QUICK_ROUNDS} rounds of {QUICK_SNAPSHOTS}")
    p.add_argument("--rounds", type=int, default=0, help=f"rounds (full: {FULL_ROUNDS} of {SNAPSHOTS} snapshots)")
    p.add_argument("--out", type=Path, default=None)
    p.set_defaults(func=ros2_main)


def main(argv: list[str] | None = None) -> int:
    """`python -m drvs_bench.ros2 subscriber --domain N --count K`: the benchmark's subscriber."""
    p = argparse.ArgumentParser(prog="drvs_bench.ros2")
    p.add_argument("role", choices=["subscriber"])
    p.add_argument("--domain", type=int, required=True)
    p.add_argument("--count", type=int, required=True)
    args = p.parse_args(argv)
    return subscriber(args.domain, args.count)


if __name__ == "__main__":
    sys.exit(main())

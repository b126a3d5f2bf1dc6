"""drvs-bench paper: the paper's Exp. C and D side by side, in interleaved rounds.

The robot, a process of its own, either asks DRVS (single-shot requests at 30 Hz) or has both
cameras stream every frame (raw, or JPEG at quality 80) and detects on board. Counting TCP relays
in front of the robot measure what its sockets carry: the TCP payload, and the frames a 1500-byte-
MTU Ethernet link would carry (drvs.tools.meter). /proc gives its CPU time and the machine's.

Every mode and floor runs once per round, in the same order (A B C … A B C …), for several rounds;
each figure, and each ratio taken within a round, is published as its median and spread. Every run
is checked for the work it was meant to do (stats.check_work): one that did less fails the
benchmark (WorkMismatch) instead of publishing a ratio.

The paper's argument for sophisticated detection ("more sophisticated detection algorithms ... are
unlikely to scale ... on mobile robots"), measured: two more cameras play real footage of people
(vtest.avi, when opencv-doc is installed), and in the same rounds the robot either asks DRVS for
`people` (drvs_people) or has both cameras stream raw frames at the request rate and runs the same
HOG people detector itself on every frame (raw_people): robot_cpu_ratio_people, beside the colour
robot_cpu_ratio. The streaming robot there gets only the frames it analyses (its best case).

A video stream is continuous: its like-for-like counterpart is a continuous fused track at the same
rate (drvs_track: one request, then one snapshot a period on the robot's own stream), not single
shots with a request, a reply and ACKs each. Its floor (track_floor, drvs_bench.bare) is the same
snapshot messages, captured from the DRVS server, pushed on one bare grpc.aio stream at the same rate
and only received: bandwidth_ratio_raw_track, bandwidth_ratio_jpeg_track and
robot_cpu_track_over_receive_floor. The single-shot modes stay: they are what a robot that looks
only now and then pays.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import secrets
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from drvs.core.geometry import FieldOfView
from drvs.sim.scenario import load_scenario
from drvs.tools.launch import ManagedProcess, start_camera, start_server
from drvs.tools.meter import CountingRelay, WireCount

from .common import (
    BOTH_REGION,
    IMAGE_SIZE,
    PEOPLE_MAX_RANGE_M,
    PEOPLE_REGION,
    SCENE,
    YELLOW,
    CpuSampler,
    bench_process,
    cpu_seconds,
    machine,
    pyplot,
    record_people,
    record_scene,
    write_result,
)
from .service import ack_server, run_helper
from .stats import FULL_ROUNDS, WorkMismatch, check_work, interleaved, publish, verdict

BUCKET_S = 0.1
#: drvs: reports with floor outlines (the API's default); drvs_boxes: bounding boxes only, as the
#: paper's DRVS sent; drvs_boxes_moving: the same, but the region slides and the filter alternates
#: every request (workload.moving_request); raw / jpeg: both cameras stream frames, the robot
#: detects on board.
MODES = ("drvs", "drvs_boxes", "drvs_boxes_moving", "raw", "jpeg")
#: The robot CPU floors, run in the same rounds: DRVS's messages in bare grpc.aio, one bare round
#: trip per request, an idle loop at the request rate.
FLOORS = ("bare_path", "rtt_floor", "idle")
#: The continuous counterpart of a video stream (issue 27): one fused track at the request rate for as
#: many snapshots as the other modes make requests, boxes only; and its floor, the same snapshot
#: messages pushed at the same rate on one bare grpc.aio stream and only received.
TRACK_MODE = "drvs_track"
TRACK_FLOOR = "track_floor"
#: Its targets: (target, higher is better), each to be met in every round.
TRACK_TARGETS: dict[str, tuple[float, bool]] = {
    "bandwidth_ratio_jpeg_track": (100.0, True),
    "robot_cpu_track_over_receive_floor": (1.1, False),
}
#: Requests per run (30 Hz): the full run takes about 15-20 minutes on the 2-core machine, --quick 2-3.
FULL_REQUESTS = 600
QUICK_REQUESTS = 90
#: The people comparison (see the module docstring), on the people cameras: DRVS `people` requests,
#: boxes only as drvs_boxes; raw frames at the request rate, the HOG detector on board.
PEOPLE_MODES = ("drvs_people", "raw_people")
#: Requests a second in the people modes: each asks every people camera for a HOG search (about
#: 0.1-0.3 s of a core here), so 30 Hz as for colour would be more than the 2-core machine has.
PEOPLE_RATE = 2.0
#: Requests (or frames per camera) per people run: 30 s at 2 Hz; --quick 8 s.
PEOPLE_FULL_REQUESTS = 60
PEOPLE_QUICK_REQUESTS = 16
#: The paper's targets (higher is better). robot_cpu_ratio_people has no number in the paper; its
#: argument is that heavier detection widens the gap, so it is held to the colour ratio's target.
TARGETS = {"bandwidth_ratio_raw": 1000.0, "bandwidth_ratio_jpeg": 100.0, "robot_cpu_ratio": 20.0}
PEOPLE_TARGETS = {"robot_cpu_ratio_people": 20.0}
#: --fused (issue 17): the DRVS boxes-only single shots again with fused delivery: the robot sends one
#: request and gets one snapshot on its own stream, no reports, no listener.
FUSED_MODES = ("drvs_boxes_fused",)
#: Its targets: (target, higher is better). robot_cpu_fused_over_floor is the fused robot's CPU over
#: the one-round-trip floor's (rtt_floor), which is robot_cpu_ratio_at_floor / robot_cpu_ratio_fused.
FUSED_TARGETS: dict[str, tuple[float, bool]] = {
    "robot_cpu_fused_over_floor": (1.1, False),
    "bandwidth_ratio_jpeg_fused": (100.0, True),
}
_TICK = os.sysconf("SC_CLK_TCK")

CPU_COVERAGE = {
    "cpu_s": "the robot process only: time.process_time() in it over its measured interval, after its warm-up (user + "
    "system, all its threads: event loop, gRPC's poller and event-engine threads, detection workers)",
    "cpu_load_timeline": "the same process from /proc/<pid>/stat (utime + stime, all threads), per 0.1 s",
    "machine_cpu_cores": "the whole machine from /proc/stat (user + nice + system + irq + softirq + steal "
    "jiffies, every core) from the robot's START (after its warm-up) to its DONE, in cores; includes the "
    "cameras, the server, the benchmark's relays and anything else running (the machine is shared)",
    "cameras_cpu_s / server_cpu_s": "the drvs-camera processes (together) and the drvs-server, /proc "
    "utime + stime over the same interval: on loopback a raw stream's send work lands in the cameras",
    "system_cpu_cores": "robot + cameras + server, as above, in cores: the whole system's work for the robot "
    "without the rest of the machine (what machine_cpu_cores shows on a quiet machine)",
    "relays_cpu_s": "the benchmark process itself (its counting relays and samplers) over the same interval",
}


def _machine_busy_jiffies() -> int:
    """Busy jiffies of the whole machine (every core) since boot, from /proc/stat."""
    fields = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:9]]
    user, nice, system, _idle, _iowait, irq, softirq, steal = fields
    return user + nice + system + irq + softirq + steal


class _Cpu:
    """CPU seconds of the machine and of named processes over an interval."""

    def __init__(self, procs: dict[str, list[int]]) -> None:
        self.procs = procs
        self._start = self._read()

    def _read(self) -> dict[str, float]:
        out = {"machine": _machine_busy_jiffies() / _TICK, "relays": cpu_seconds(os.getpid())}
        for name, pids in self.procs.items():
            out[name] = sum(cpu_seconds(pid) for pid in pids)
        return out

    def stop(self) -> dict[str, float]:
        end = self._read()
        return {k: end[k] - self._start[k] for k in end}


def _wire_sum(relays: list[CountingRelay]) -> WireCount:
    total = WireCount()
    for r in relays:
        total = total + r.wire()
    return total


def _merge(timelines: list[dict[int, int]]) -> list[int]:
    merged: dict[int, int] = {}
    for t in timelines:
        for k, v in t.items():
            merged[k] = merged.get(k, 0) + v
    return [merged.get(k, 0) for k in range(max(merged, default=-1) + 1)]


async def run_mode(
    mode: str,
    server: str,
    cameras: dict[str, tuple[str, Path]],
    requests: int,
    rate: float,
    cpu_procs: dict[str, list[int]] | None = None,
    camera_token: Path | None = None,
    extra: tuple[str, ...] = (),
) -> dict[str, Any]:
    """One run of one mode: the robot process through counting relays. Returns its outcome and figures."""
    relays: list[CountingRelay] = []
    loop = asyncio.get_running_loop()
    t_relays = loop.time()
    args = ["robot", "--mode", mode.split("_")[0], "--requests", str(requests), "--rate", str(rate)]
    if mode == TRACK_FLOOR:
        args = ["track-floor-robot", "--requests", str(requests), "--rate", str(rate)]
    if mode.startswith("drvs_boxes") or mode in ("drvs_people", TRACK_MODE):
        args.append("--no-outlines")
    args += extra
    if mode.endswith("_moving"):
        args.append("--moving")
    callback_relay: CountingRelay | None = None
    if mode.endswith("_fused") or mode in (TRACK_MODE, TRACK_FLOOR):
        # Fused delivery: everything travels on the robot's own connection to the server; it has no
        # listener. The track floor: its one connection to the bare server pushing snapshots (`server`).
        host, port = server.rsplit(":", 1)
        relays = [CountingRelay(host, int(port), bucket_s=BUCKET_S)]
        await relays[0].start()
        args += ["--server", f"127.0.0.1:{relays[0].port}"]
        if mode != TRACK_FLOOR:
            args += ["--fuse" if mode.endswith("_fused") else "--track", "--cameras", str(len(cameras))]
    elif mode.startswith("drvs"):
        host, port = server.rsplit(":", 1)
        server_relay = CountingRelay(host, int(port), bucket_s=BUCKET_S)
        # target: the robot's listener, once it is up; the socket to measure is the one to the robot
        callback_relay = CountingRelay(bucket_s=BUCKET_S, side="target")
        relays = [server_relay, callback_relay]
        for r in relays:
            await r.start()
        args += ["--server", f"127.0.0.1:{server_relay.port}", "--advertise", f"127.0.0.1:{callback_relay.port}"]
        args += ["--cameras", str(len(cameras))]
    else:
        for address, hfile in cameras.values():
            host, port = address.rsplit(":", 1)
            relay = CountingRelay(host, int(port), bucket_s=BUCKET_S)
            await relay.start()
            relays.append(relay)
            args += ["--camera", f"127.0.0.1:{relay.port}", "--homography", str(hfile)]
        if camera_token is not None:
            args += ["--camera-token-file", str(camera_token)]  # frames only for whoever holds the token
    robot = await bench_process(f"robot-{mode}", *args).start()
    t_robot = loop.time()
    sampler = CpuSampler(robot.pid, BUCKET_S)
    sampler.start()
    try:
        ready = await robot.wait_for_line(r"^READY (\d+)", timeout=60)
        if callback_relay is not None:
            callback_relay.set_target("127.0.0.1", int(ready.group(1)))
        # Measured from START, after the robot's warm-up (requests back to back, or the streams' first frames).
        await robot.wait_for_line(r"^START$", timeout=120)
        t_start = loop.time()
        cpu = _Cpu(cpu_procs or {})
        wire0 = _wire_sum(relays)
        done = await robot.wait_for_line(r"^DONE (.*)", timeout=requests / rate + 120)
        used = cpu.stop()
        t_done = loop.time()
        interval = t_done - t_start
        wire = _wire_sum(relays) - wire0
        outcome = json.loads(done.group(1))
        assert await robot.wait(timeout=30) == 0, robot.output()
    finally:
        await sampler.stop()
        await robot.stop()
        for r in relays:
            await r.close()
    payload, payload_to_robot = wire.payload, wire.payload_to_host
    wall = float(outcome["wall_s"])
    skip, end = int((t_start - t_relays) / BUCKET_S), int((t_done - t_relays) / BUCKET_S) + 1
    return {
        **outcome,
        # Wire bytes: both directions, as a 1500-byte-MTU Ethernet link carries them (drvs.tools.meter).
        "bytes": wire.total,
        "bytes_per_s": wire.total / wall,
        "wire_bytes_to_robot": wire.to_host,
        "wire_bytes_from_robot": wire.from_host,
        "segments": wire.segments,
        "segments_to_robot": wire.segments_to_host,
        "segments_from_robot": wire.segments_from_host,
        # TCP payload (what the applications wrote), both directions, from the same counters.
        "payload_bytes": payload,
        "payload_bytes_per_s": payload / wall,
        "payload_bytes_to_robot": payload_to_robot,
        "payload_bytes_from_robot": payload - payload_to_robot,
        "robot_cpu_cores": float(outcome["cpu_s"]) / wall,
        "machine_cpu_cores": used["machine"] / interval,
        "machine_cpu_s": used["machine"],
        "cameras_cpu_s": used.get("cameras", 0.0),
        "server_cpu_s": used.get("server", 0.0),
        "relays_cpu_s": used["relays"],
        "system_cpu_cores": float(outcome["cpu_s"]) / wall
        + (used.get("cameras", 0.0) + used.get("server", 0.0)) / interval,
        # Timelines from the robot's START to its DONE (start-up, warm-up and exit left out), per BUCKET_S.
        "bytes_timeline": _merge([r.wire_timeline for r in relays])[skip:end],
        "payload_bytes_timeline": _merge([r.timeline for r in relays])[skip:end],
        "cpu_load_timeline": [
            round(load, 4) for t, load in sampler.load() if t_start - t_robot <= t <= t_done - t_robot
        ],
    }


def expected_detections(
    homography_files: list[Path], filter_def: str, region: tuple[float, float, float, float]
) -> list[int] | None:
    """Objects of `filter_def`'s colour each camera sees whole, inside the region, from scene.yaml; None
    if an object lies across a field of view's or the region's edge (its count is not certain)."""
    from shapely.geometry import box

    from drvs.core.homography_file import load_homography

    scenario = load_scenario(SCENE)
    area = box(*region)
    counts = []
    for hfile in homography_files:
        fov = FieldOfView.compute(load_homography(hfile), IMAGE_SIZE, 6.0).floor
        n = 0
        for obj in scenario.objects:
            if obj.color is None or obj.color.filter_def != filter_def or not obj.shape.intersects(fov):
                continue
            if not (obj.shape.within(fov) and obj.shape.within(area)):
                return None
            n += 1
        counts.append(n)
    return counts


def check_work_saying_failures(mode: str, expected: dict[str, float], run: dict[str, Any]) -> None:
    """check_work, with the run's first failures (as the workload recorded them) in the mismatch."""
    try:
        check_work(mode, expected, run)
    except WorkMismatch as exc:
        if run.get("failures"):
            raise WorkMismatch(f"{exc}; first failures: {'; '.join(run['failures'])}") from None
        raise


def check_drvs(mode: str, run: dict[str, Any], requests: int, cameras: int, detections: int | None) -> None:
    """Every request delivered: a final report from each camera, none an error (busy included), none
    refused; with a fixed scene, the detections the scene holds in every request."""
    expected: dict[str, float] = {
        "requests": requests,
        "requests_delivered": requests,
        "reports": cameras * requests,
        "error_reports": 0,
        "busy_reports": 0,
        "refused_requests": 0,
        "missing_finals": 0,
    }
    if detections is not None:
        expected["detections"] = detections * requests
    check_work_saying_failures(mode, expected, run)


def check_fused(mode: str, run: dict[str, Any], requests: int, objects: int | None) -> None:
    """Every fused request delivered: one final snapshot merging every camera, none missing, none
    refused; with a fixed scene, the objects the scene holds in every snapshot."""
    expected: dict[str, float] = {
        "requests": requests,
        "requests_delivered": requests,
        "snapshots": requests,
        "missing_cameras": 0,
        "refused_requests": 0,
    }
    if objects is not None:
        expected["objects"] = objects * requests
    check_work_saying_failures(mode, expected, run)


def check_track(mode: str, run: dict[str, Any], requests: int, objects: int | None) -> None:
    """The track delivered a snapshot a period, `requests` in all (at least 2: a track has a first and
    a last), the last of them final, none dropped unread, and at least one merged a fresh report from
    every camera; with a fixed scene, every such snapshot held the objects the scene holds.

    Published, not checked (as the streams' `frames_expected`): `snapshots_every_camera`, and the
    snapshots naming a camera silent past its period and grace (`snapshots_missing_a_camera`), which
    a loaded machine makes. Neither flatters the ratios: a report later than half a period goes into
    the next snapshot and the tracker keeps its objects meanwhile, and a snapshot naming a missing
    camera carries more bytes, not fewer."""
    expected: dict[str, float] = {
        "snapshots": max(2, requests),
        "final_snapshots": 1,
        "dropped_snapshots": 0,
    }
    if objects is not None:
        expected["objects_every_camera"] = objects * run["snapshots_every_camera"]
    check_work_saying_failures(mode, expected, run)
    if run["snapshots_every_camera"] <= 0:
        raise WorkMismatch(f"{mode}: no snapshot merged every camera, no ratio published")


def check_track_floor(run: dict[str, Any], requests: int) -> None:
    """The floor received as many snapshot messages as the track delivers."""
    check_work(TRACK_FLOOR, {"snapshots": max(2, requests)}, run)


def check_stream(mode: str, run: dict[str, Any], per_frame: list[int] | None) -> None:
    """Every frame received was analysed, each camera sent frames, and (with a fixed scene) each frame's
    detections were the objects its camera sees."""
    for k, cam in enumerate(run["per_camera"]):
        expected: dict[str, float] = {"frames_analysed": cam["frames_received"]}
        if per_frame is not None:
            expected["detections"] = per_frame[k] * cam["frames_received"]
        check_work(f"{mode} camera {k}", expected, cam)
        if cam["frames_received"] <= 0:
            raise WorkMismatch(f"{mode} camera {k}: no frame received, no ratio published")


def people_args(mode: str) -> tuple[str, ...]:
    """The robot's arguments for a people mode (see run_paper)."""
    region = ",".join(f"{v:g}" for v in PEOPLE_REGION)
    common = ("--filter", "people", "--region", region)
    if mode == "drvs_people":
        return (*common, "--warmup", "4")
    return (*common, "--max-range", f"{PEOPLE_MAX_RANGE_M:g}", "--max-fps", f"{PEOPLE_RATE:g}", "--warmup-frames", "2")


def check_people(mode: str, run: dict[str, Any], requests: int, cameras: int) -> None:
    """Both ways did the work (every request answered, every frame received analysed) and found
    people: the same detector on the same footage, on the camera or on the robot."""
    if mode == "drvs_people":
        check_drvs(mode, run, requests, cameras, None)
    else:
        check_stream(mode, run, None)
    if run["detections"] <= 0:
        raise WorkMismatch(f"{mode}: no person found in {requests} requests' worth of vtest.avi; no ratio published")


async def run_paper(
    out: Path,
    requests: int,
    rate: float,
    rounds: int = FULL_ROUNDS,
    people_requests: int = PEOPLE_FULL_REQUESTS,
    fused: bool = False,
) -> dict[str, Any]:
    """fused: run FUSED_MODES too, in the same rounds (needs a server with fused delivery)."""
    procs: list[ManagedProcess] = []
    runs: list[dict[str, dict[str, Any]]] = [{} for _ in range(rounds)]
    with tempfile.TemporaryDirectory(prefix="drvs-bench-") as tmp:
        scene = record_scene(Path(tmp))
        footage = record_people(Path(tmp))
        if footage is None:
            print("drvs-bench paper: vtest.avi not installed (opencv-doc): no people modes", file=sys.stderr)
        try:
            # A new site: no previous run whose cameras could still be on their way back, so replies
            # carry no coverage_uncertain_s (5 bytes each for a lease after a restart).
            server, address = await start_server("--warm-up", "0")
            procs.append(server)
            cameras: dict[str, tuple[str, Path]] = {}
            camera_pids: list[int] = []
            # A camera streams whole frames only to a caller that presents its token.
            camera_token = Path(tmp) / "camera.token"
            camera_token.write_text(secrets.token_urlsafe(24))
            for camera_id, rec in scene.items():
                cam = await start_camera(
                    camera_id, rec.video, rec.homography_file, address, "--max-range", "6", "--serve-frames",
                    "--token-file", str(camera_token),
                )  # fmt: skip
                procs.append(cam)
                camera_pids.append(cam.pid)
                listening = next(re.search(r"listening on (\S+)", line) for line in cam.lines if "listening on" in line)
                assert listening is not None
                cameras[camera_id] = (listening.group(1), rec.homography_file)
            people_cameras: dict[str, tuple[str, Path]] = {}
            for camera_id, rec in (footage or {}).items():
                cam = await start_camera(
                    camera_id, rec.video, rec.homography_file, address, "--max-range", f"{PEOPLE_MAX_RANGE_M:g}",
                    "--serve-frames", "--token-file", str(camera_token),
                )  # fmt: skip
                procs.append(cam)
                listening = next(re.search(r"listening on (\S+)", line) for line in cam.lines if "listening on" in line)
                assert listening is not None
                people_cameras[camera_id] = (listening.group(1), rec.homography_file)
            people_modes = PEOPLE_MODES if people_cameras else ()
            cpu_procs = {"cameras": camera_pids, "server": [server.pid]}
            per_camera = expected_detections([h for _, h in cameras.values()], YELLOW, BOTH_REGION)
            # The floors' long-lived processes: an ack-at-once server, and DRVS's message flow in bare grpc.aio.
            ack, ack_address = await ack_server()
            procs.append(ack)
            bare_server = await start_bare_path(procs, len(cameras))
            track_floor = await start_track_floor(procs, address, rate, len(cameras))
            fused_modes = FUSED_MODES if fused else ()
            order = (*MODES, TRACK_MODE, *fused_modes, *people_modes, *FLOORS, TRACK_FLOOR)
            for r, mode in interleaved(order, rounds):
                print(f"drvs-bench paper: round {r + 1}/{rounds}: {mode} ...", file=sys.stderr, flush=True)
                if mode in PEOPLE_MODES:
                    run = await run_mode(
                        mode, address, people_cameras, people_requests, PEOPLE_RATE, cpu_procs, camera_token,
                        people_args(mode),
                    )  # fmt: skip
                    check_people(mode, run, people_requests, len(people_cameras))
                elif mode in FUSED_MODES:
                    run = await run_mode(mode, address, cameras, requests, rate, cpu_procs, camera_token)
                    # The scene's cameras do not overlap: each object is one world object.
                    check_fused(mode, run, requests, None if per_camera is None else sum(per_camera))
                elif mode == TRACK_MODE:
                    run = await run_mode(mode, address, cameras, requests, rate, cpu_procs, camera_token)
                    check_track(mode, run, requests, None if per_camera is None else sum(per_camera))
                elif mode == TRACK_FLOOR:
                    run = await run_mode(mode, track_floor, cameras, requests, rate)
                    check_track_floor(run, requests)
                elif mode in MODES:
                    run = await run_mode(mode, address, cameras, requests, rate, cpu_procs, camera_token)
                    if mode.startswith("drvs"):
                        fixed = None if mode.endswith("_moving") or per_camera is None else sum(per_camera)
                        check_drvs(mode, run, requests, len(cameras), fixed)
                    else:
                        check_stream(mode, run, per_camera)
                elif mode == "bare_path":
                    run = await run_helper(
                        "bare-robot", "bare-robot", "--server", bare_server, "--cameras", str(len(cameras)),
                        "--requests", str(requests), "--rate", str(rate),
                    )  # fmt: skip
                elif mode == "rtt_floor":
                    run = await run_helper(
                        "rtt-floor", "rtt", "--target", ack_address, "--calls", str(requests), "--rate", str(rate)
                    )
                else:
                    run = await run_helper("idle-robot", "idle-robot", "--requests", str(requests), "--rate", str(rate))
                runs[r][mode] = run
        finally:
            for proc in reversed(procs):
                await proc.stop()
    result = summarise(runs, requests, rate, len(scene), people_requests if people_modes else 0, fused)
    await asyncio.to_thread(write_outputs, result, out)
    return result


def _cpu_rate(m: dict[str, Any]) -> float:
    return float(m["cpu_s"]) / float(m["wall_s"])


def _figure(key: str) -> Callable[[dict[str, Any]], float]:
    """A mode's figure `key`, read from its measurements."""
    return lambda m: float(m[key])


#: Ratios taken within each round: name -> (numerator mode, denominator mode).
_BANDWIDTH = {
    "bandwidth_ratio_raw": ("raw", "drvs_boxes"),
    "bandwidth_ratio_jpeg": ("jpeg", "drvs_boxes"),
    "bandwidth_ratio_raw_outlines": ("raw", "drvs"),
    "bandwidth_ratio_jpeg_outlines": ("jpeg", "drvs"),
    "bandwidth_ratio_raw_moving": ("raw", "drvs_boxes_moving"),
    "bandwidth_ratio_jpeg_moving": ("jpeg", "drvs_boxes_moving"),
}
_CPU = {
    "robot_cpu_ratio": ("raw", "drvs_boxes"),
    "robot_cpu_ratio_jpeg": ("jpeg", "drvs_boxes"),
    "robot_cpu_ratio_outlines": ("raw", "drvs"),
    "robot_cpu_ratio_moving": ("raw", "drvs_boxes_moving"),
    "robot_cpu_ratio_at_floor": ("raw", "rtt_floor"),
    "robot_cpu_ratio_at_bare_path": ("raw", "bare_path"),
    "robot_cpu_over_bare_path": ("drvs_boxes", "bare_path"),
    "robot_cpu_ratio_at_idle": ("raw", "idle"),
}
#: Whole-machine ratios, for each of `machine_cpu_cores` and `system_cpu_cores`: key suffix -> modes.
_CORES = {"": ("raw", "drvs_boxes"), "_jpeg": ("jpeg", "drvs_boxes"), "_moving": ("raw", "drvs_boxes_moving")}
_FLOOR_DEFINITIONS = {
    "robot_cpu_floor": (
        "rtt_floor",
        "a bare grpc.aio client: one request/reply round trip per request on one stream, same count and rate, "
        "to a server that answers at once; no reports, no DRVS code",
    ),
    "robot_cpu_bare_path": (
        "bare_path",
        "DRVS's message flow in bare grpc.aio, with no DRVS code: the request on a long-lived stream, the "
        "server's reply, a forward to each camera, one report from each to the robot's listener; same count "
        "and rate",
    ),
    "robot_cpu_idle": ("idle", "an asyncio process that only wakes at the request rate and does nothing"),
}


def _numeric(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _mode_figures(runs: list[dict[str, dict[str, Any]]], mode: str) -> dict[str, Any]:
    data: dict[str, Any] = {}
    for key, value in runs[-1][mode].items():
        if _numeric(value):
            values = [run[mode][key] for run in runs]
            median = publish(data, key, values)["median"]
            if all(isinstance(v, int) for v in values) and float(median).is_integer():
                data[key] = data[f"{key}_median"] = int(median)  # counts stay counts
        else:
            data[key] = value  # histograms, per-camera counts, timelines: from the last round
    return data


def summarise(
    runs: list[dict[str, dict[str, Any]]],
    requests: int,
    rate: float,
    cameras: int,
    people_requests: int = 0,
    fused: bool = False,
) -> dict[str, Any]:
    """paper.json from the rounds' runs: each figure and each ratio (within a round) as median and spread.
    people_requests: the people modes' requests per run (0: they did not run, no footage); fused:
    FUSED_MODES ran too (their figures join `modes`, their ratios and targets the rest). The track mode
    and its floor join them when the runs have them (every run_paper does)."""
    track = TRACK_MODE in runs[0] and TRACK_FLOOR in runs[0]
    track_modes = (TRACK_MODE,) if track else ()
    modes = {mode: _mode_figures(runs, mode) for mode in (*MODES, *track_modes, *(FUSED_MODES if fused else ()))}
    result: dict[str, Any] = {
        "benchmark": "paper",
        "requests": requests,
        "rate_hz": rate,
        "rounds": len(runs),
        "order": [*MODES, *track_modes, *(FUSED_MODES if fused else ()), *FLOORS, *((TRACK_FLOOR,) if track else ())],
        "cameras": cameras,
        "frame": "640x480 BGR, 20 fps",
        "bytes": "bytes: wire bytes, both directions of the robot's sockets, every TCP segment (ACK-only, SYN, "
        "FIN included) as a 1500-byte-MTU Ethernet link carries it: payload + 66 B a segment (Ethernet 14, IPv4 "
        "20, TCP 32 with timestamps), from the kernel's TCP_INFO; payload_bytes: the TCP payload alone",
        "cpu": CPU_COVERAGE,
        "modes": modes,
    }
    publish(
        result,
        "jpeg_mean_frame_bytes",
        [run["jpeg"]["payload_bytes_to_robot"] / max(1, run["jpeg"]["frames"]) for run in runs],
    )

    def ratio(name: str, num: str, den: str, figure: Callable[[dict[str, Any]], float]) -> None:
        publish(result, name, [figure(run[num]) / figure(run[den]) for run in runs])

    for name, (num, den) in _BANDWIDTH.items():
        ratio(name, num, den, _figure("bytes_per_s"))
        ratio(f"{name}_payload", num, den, _figure("payload_bytes_per_s"))
    for name, (num, den) in _CPU.items():
        ratio(name, num, den, _cpu_rate)
    for kind in ("machine", "system"):
        for suffix, (num, den) in _CORES.items():
            ratio(f"{kind}_cpu_ratio{suffix}", num, den, _figure(f"{kind}_cpu_cores"))
    for key, (floor, definition) in _FLOOR_DEFINITIONS.items():
        figures: dict[str, Any] = {}
        for fig in ("cpu_s", "wall_s", "last_report_ms_p50"):
            if fig in runs[0][floor]:
                publish(figures, fig, [run[floor][fig] for run in runs])
        figures["definition"] = definition
        result[key] = figures
    result["targets"] = {
        name: {
            "target": target,
            "median": result[name],
            "spread": result[f"{name}_spread"],
            "verdict": verdict(result[f"{name}_runs"], target),
        }
        for name, target in TARGETS.items()
    }
    if people_requests:
        result["people"] = {
            "footage": "vtest.avi (Debian opencv-doc), two stretches of 200 frames scaled to 640x480, one per camera",
            "requests": people_requests,
            "rate_hz": PEOPLE_RATE,
            "drvs_people": "the robot asks DRVS for `people` (boxes only) over both people cameras, once per request",
            "raw_people": "both people cameras stream raw BGR frames at the request rate; the robot runs the same "
            "HOG people detector (drvs.detectors.people, the cameras' default settings) on every frame",
            "modes": {mode: _mode_figures(runs, mode) for mode in PEOPLE_MODES},
        }
        ratio("robot_cpu_ratio_people", "raw_people", "drvs_people", _cpu_rate)
        publish(
            result,
            "robot_cpu_cores_people_onboard",
            [_cpu_rate(run["raw_people"]) for run in runs],
        )
        for name, target in PEOPLE_TARGETS.items():
            result["targets"][name] = {
                "target": target,
                "median": result[name],
                "spread": result[f"{name}_spread"],
                "verdict": verdict(result[f"{name}_runs"], target),
            }
    if fused:
        summarise_fused(result, runs, requests, ratio)
    if track:
        summarise_track(result, runs, ratio)
    result["machine"] = machine()
    return result


def summarise_fused(
    result: dict[str, Any],
    runs: list[dict[str, dict[str, Any]]],
    requests: int,
    ratio: Callable[[str, str, str, Callable[[dict[str, Any]], float]], None],
) -> None:
    """The fused mode's ratios (within each round, as every other) and targets: the robot's CPU
    against raw frames and against the floor of one bare round trip per request, its wire bytes
    against the streams and against per-camera delivery (drvs_boxes, the same requests)."""
    fused = "drvs_boxes_fused"
    ratio("robot_cpu_ratio_fused", "raw", fused, _cpu_rate)
    ratio("robot_cpu_ratio_jpeg_fused", "jpeg", fused, _cpu_rate)
    # The robot_cpu_ratio_at_floor / robot_cpu_ratio, for per-camera and for fused delivery.
    ratio("robot_cpu_fused_over_floor", fused, "rtt_floor", _cpu_rate)
    ratio("robot_cpu_over_floor", "drvs_boxes", "rtt_floor", _cpu_rate)
    ratio("robot_cpu_fused_over_per_camera", fused, "drvs_boxes", _cpu_rate)
    for name, num in (("bandwidth_ratio_raw_fused", "raw"), ("bandwidth_ratio_jpeg_fused", "jpeg")):
        ratio(name, num, fused, _figure("bytes_per_s"))
        ratio(f"{name}_payload", num, fused, _figure("payload_bytes_per_s"))
    ratio("bytes_fused_over_per_camera", fused, "drvs_boxes", _figure("bytes"))
    ratio("payload_bytes_fused_over_per_camera", fused, "drvs_boxes", _figure("payload_bytes"))
    for mode, key in ((fused, "fused"), ("drvs_boxes", "per_camera")):
        publish(result, f"wire_bytes_per_request_{key}", [run[mode]["bytes"] / requests for run in runs])
        publish(result, f"payload_bytes_per_request_{key}", [run[mode]["payload_bytes"] / requests for run in runs])
        publish(result, f"segments_per_request_{key}", [run[mode]["segments"] / requests for run in runs])
        server_ms = [1000 * run[mode]["server_cpu_s"] / requests for run in runs]
        publish(result, f"server_cpu_ms_per_request_{key}", server_ms)
    add_targets(result, FUSED_TARGETS)


def summarise_track(
    result: dict[str, Any],
    runs: list[dict[str, dict[str, Any]]],
    ratio: Callable[[str, str, str, Callable[[dict[str, Any]], float]], None],
) -> None:
    """The track's ratios (within each round) and targets: its wire bytes against the streams', the
    robot's CPU against the floor of receiving the same snapshot messages on a bare stream, and per
    snapshot what the track and its floor carry."""
    track, floor = TRACK_MODE, TRACK_FLOOR
    for name, num in (("bandwidth_ratio_raw_track", "raw"), ("bandwidth_ratio_jpeg_track", "jpeg")):
        ratio(name, num, track, _figure("bytes_per_s"))
        ratio(f"{name}_payload", num, track, _figure("payload_bytes_per_s"))
    ratio("robot_cpu_track_over_receive_floor", track, floor, _cpu_rate)
    ratio("robot_cpu_ratio_track", "raw", track, _cpu_rate)
    ratio("robot_cpu_ratio_jpeg_track", "jpeg", track, _cpu_rate)
    ratio("robot_cpu_track_over_single_shots", track, "drvs_boxes", _cpu_rate)
    ratio("bytes_track_over_receive_floor", track, floor, _figure("bytes"))
    ratio("payload_bytes_track_over_receive_floor", track, floor, _figure("payload_bytes"))
    for mode, key in ((track, "track"), (floor, "receive_floor")):
        for fig in ("bytes", "payload_bytes", "segments"):
            name = f"{'wire_bytes' if fig == 'bytes' else fig}_per_snapshot_{key}"
            publish(result, name, [run[mode][fig] / max(1, run[mode]["snapshots"]) for run in runs])
    figures: dict[str, Any] = {}
    for fig in ("cpu_s", "wall_s", "snapshots", "bytes", "bytes_per_s", "payload_bytes", "segments"):
        publish(figures, fig, [run[floor][fig] for run in runs])
    figures["definition"] = (
        "a bare grpc.aio robot: one request on one DetectStream, then only receiving (the stub parses each "
        "message, nothing more) the snapshot replies a bare server pushes at the same rate, as many as the "
        "track's; the replies are the DRVS server's own, captured from a track over the same region, boxes "
        "only, each with its sequence and final flag set; through a counting relay like the track; no DRVS code"
    )
    result["robot_cpu_receive_floor"] = figures
    add_targets(result, TRACK_TARGETS)


def add_targets(result: dict[str, Any], targets: dict[str, tuple[float, bool]]) -> None:
    """Each target's figure (median, spread) and whether every round met it, into result["targets"]."""
    for name, (target, higher) in targets.items():
        result["targets"][name] = {
            "target": target,
            "higher_is_better": higher,
            "median": result[name],
            "spread": result[f"{name}_spread"],
            "verdict": verdict(result[f"{name}_runs"], target, higher_is_better=higher),
        }


async def start_bare_path(procs: list[ManagedProcess], cameras: int) -> str:
    """The bare path's cameras and server (drvs_bench.bare), kept for every round; returns the server's address."""

    async def listening(name: str, *args: str) -> str:
        proc = await bench_process(name, *args).start()
        procs.append(proc)
        return (await proc.wait_for_line(r"^LISTENING (\S+)", timeout=30)).group(1)

    camera_args: list[str] = []
    for k in range(cameras):
        camera_args += ["--camera", await listening(f"bare-camera{k}", "bare-camera", "--id", f"bare{k}")]
    return await listening("bare-server", "bare-server", *camera_args)


async def start_track_floor(procs: list[ManagedProcess], server: str, rate: float, cameras: int) -> str:
    """The track floor's server (drvs_bench.bare), kept for every round: it captures real snapshot
    replies from the DRVS server (a one-second track, boxes only, over the region the track mode
    asks for) and pushes them; returns its address."""
    region = ",".join(f"{v:g}" for v in BOTH_REGION)
    proc = await bench_process(
        "track-floor-server", "track-floor-server", "--drvs-server", server, "--filter", YELLOW, f"--region={region}",
        "--rate", f"{rate:g}", "--cameras", str(cameras),
    ).start()  # fmt: skip
    procs.append(proc)
    return (await proc.wait_for_line(r"^LISTENING (\S+)", timeout=60)).group(1)


def write_outputs(result: dict[str, Any], out: Path) -> None:
    write_result(result, out, "paper", plot)


def plot(result: dict[str, Any], out: Path) -> None:
    plt = pyplot()

    labels = {
        "drvs": "DRVS, outlines",
        "drvs_boxes": "DRVS, boxes (as the paper)",
        "drvs_boxes_moving": "DRVS, boxes, moving region and alternating filter",
        "raw": "raw frame stream",
        "jpeg": "JPEG q80 frame stream",
        "drvs_boxes_fused": "DRVS, boxes, fused delivery",
        "drvs_track": "DRVS, boxes, one fused track (continuous)",
    }
    fig, ax = plt.subplots(figsize=(9, 4.5), dpi=100)
    for mode, data in result["modes"].items():
        series = data["bytes_timeline"]
        ax.plot([i * BUCKET_S for i in range(len(series))], [max(v, 1) for v in series], label=labels[mode], lw=1)
    ax.set_yscale("log")
    ax.set_xlabel("time (s)")
    ax.set_ylabel(f"Ethernet bytes to and from the robot per {BUCKET_S:g} s")
    ax.set_title(
        f"Robot network traffic (paper Fig. 10), last of {result['rounds']} rounds; median ratios: "
        f"raw/DRVS x{result['bandwidth_ratio_raw']:.0f}, JPEG/DRVS x{result['bandwidth_ratio_jpeg']:.0f}",
        fontsize=10,
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
        ("robot_cpu_floor", "-.", "one bare round trip per request"),
        ("robot_cpu_idle", ":", "idle asyncio loop at the same rate"),
        ("robot_cpu_receive_floor", (0, (3, 1, 1, 1, 1, 1)), "snapshots received on one bare stream"),
    ):
        if key not in result:
            continue
        floor = result[key]
        ax.axhline(100 * floor["cpu_s"] / floor["wall_s"], color="black", ls=style, lw=1, label=f"floor: {name}")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("robot process CPU (% of one core, 0.5 s mean)")
    ax.set_title(
        f"Robot CPU load (paper Fig. 9), last of {result['rounds']} rounds; median onboard raw / DRVS "
        f"x{result['robot_cpu_ratio']:.1f}",
        fontsize=10,
    )
    ax.legend()
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "cpu.png")
    plt.close(fig)

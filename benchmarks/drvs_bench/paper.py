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
    record_people,
    record_scene,
)

# The modes, targets and figures are drvs_bench.paper_figures; the names callers import from here
# stay importable (`as` re-exports).
from .paper_figures import (
    BUCKET_S,
    FLOORS,
    FUSED_MODES,
    MODES,
    PEOPLE_MODES,
    PEOPLE_RATE,
    TRACK_FLOOR,
    TRACK_MODE,
    summarise_track_only,
    write_outputs,
)
from .paper_figures import FULL_REQUESTS as FULL_REQUESTS
from .paper_figures import FUSED_TARGETS as FUSED_TARGETS
from .paper_figures import PEOPLE_FULL_REQUESTS as PEOPLE_FULL_REQUESTS
from .paper_figures import PEOPLE_QUICK_REQUESTS as PEOPLE_QUICK_REQUESTS
from .paper_figures import QUICK_REQUESTS as QUICK_REQUESTS
from .paper_figures import plot as plot
from .paper_figures import summarise as summarise
from .service import ack_server, run_helper
from .stats import FULL_ROUNDS, WorkMismatch, check_work, interleaved

_TICK = os.sysconf("SC_CLK_TCK")


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
    track_only: bool = False,
) -> dict[str, Any]:
    """fused: run FUSED_MODES too, in the same rounds (needs a server with fused delivery);
    track_only: run only the track and its floor (drvs_track, track_floor), interleaved as ever."""
    procs: list[ManagedProcess] = []
    runs: list[dict[str, dict[str, Any]]] = [{} for _ in range(rounds)]
    with tempfile.TemporaryDirectory(prefix="drvs-bench-") as tmp:
        scene = record_scene(Path(tmp))
        footage = None if track_only else record_people(Path(tmp))
        if footage is None and not track_only:
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
            track_floor = await start_track_floor(procs, address, rate, len(cameras))
            if track_only:
                ack_address = bare_server = ""
                order: tuple[str, ...] = (TRACK_MODE, TRACK_FLOOR)
            else:
                ack, ack_address = await ack_server()
                procs.append(ack)
                bare_server = await start_bare_path(procs, len(cameras))
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
    if track_only:
        result = summarise_track_only(runs, requests, rate, len(scene))
    else:
        result = summarise(runs, requests, rate, len(scene), people_requests if people_modes else 0, fused)
    await asyncio.to_thread(write_outputs, result, out)
    return result


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

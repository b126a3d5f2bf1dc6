"""drvs-bench paper's modes, targets and figures: what each mode is, the targets the comparisons are
held to, each run's summary (medians, spreads, ratios taken within a round) and the plot
(drvs_bench.paper runs the modes)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from .common import (
    machine,
    pyplot,
    write_result,
)
from .stats import publish, verdict

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


Ratio = Callable[[str, str, str, Callable[[dict[str, Any]], float]], None]


def ratios(result: dict[str, Any], runs: list[dict[str, dict[str, Any]]]) -> Ratio:
    """`ratio(name, num, den, figure)`: publishes in `result` under `name` the ratio of mode
    `num`'s `figure` to mode `den`'s, within each round of `runs`."""

    def ratio(name: str, num: str, den: str, figure: Callable[[dict[str, Any]], float]) -> None:
        publish(result, name, [figure(run[num]) / figure(run[den]) for run in runs])

    return ratio


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

    ratio = ratios(result, runs)
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
    ratio: Ratio,
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
    ratio: Ratio,
    track_only: bool = False,
) -> None:
    """The track's ratios (within each round) and targets: its wire bytes against the streams', the
    robot's CPU against the floor of receiving the same snapshot messages on a bare stream, and per
    snapshot what the track and its floor carry. track_only: only the track and its floor ran (no
    stream or single-shot ratios)."""
    track, floor = TRACK_MODE, TRACK_FLOOR
    if not track_only:
        for name, num in (("bandwidth_ratio_raw_track", "raw"), ("bandwidth_ratio_jpeg_track", "jpeg")):
            ratio(name, num, track, _figure("bytes_per_s"))
            ratio(f"{name}_payload", num, track, _figure("payload_bytes_per_s"))
        ratio("robot_cpu_ratio_track", "raw", track, _cpu_rate)
        ratio("robot_cpu_ratio_jpeg_track", "jpeg", track, _cpu_rate)
        ratio("robot_cpu_track_over_single_shots", track, "drvs_boxes", _cpu_rate)
    ratio("robot_cpu_track_over_receive_floor", track, floor, _cpu_rate)
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
    targets = TRACK_TARGETS
    if track_only:
        targets = {k: v for k, v in TRACK_TARGETS.items() if k == "robot_cpu_track_over_receive_floor"}
    add_targets(result, targets)


def summarise_track_only(
    runs: list[dict[str, dict[str, Any]]], requests: int, rate: float, cameras: int
) -> dict[str, Any]:
    """paper.json from rounds of the track and its floor alone (`drvs-bench paper --track-only`):
    the track's figures, its ratios to its floor and the robot CPU target."""
    result: dict[str, Any] = {
        "benchmark": "paper",
        "track_only": True,
        "requests": requests,
        "rate_hz": rate,
        "rounds": len(runs),
        "order": [TRACK_MODE, TRACK_FLOOR],
        "cameras": cameras,
        "cpu": CPU_COVERAGE,
        "modes": {TRACK_MODE: _mode_figures(runs, TRACK_MODE)},
        "targets": {},
    }

    summarise_track(result, runs, ratios(result, runs), track_only=True)
    result["machine"] = machine()
    return result


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


def write_outputs(result: dict[str, Any], out: Path) -> None:
    write_result(result, out, "paper", (lambda _result, _out: None) if result.get("track_only") else plot)


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

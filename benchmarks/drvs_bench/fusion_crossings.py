"""drvs-bench fusion, the crossings part: identities kept where objects pass within a body width.

Four simulated cameras (the simulator's renderer and camera geometry: textured floor, lighting,
sensor noise), one on each side of a 10 m room, 3.2 m up, each calibrated a little wrong (its
homography from a pose off the true one by CROSSINGS_CALIBRATION_ERROR: its position by 2 cm, its
yaw and pitch by 0.3 degree each, in directions drawn each round; the pixels from the true pose).
Six yellow discs 0.44 m across (a body's width) move in three pairs whose paths cross again and
again: two circling one centre in opposite directions on circles 0.3 m apart, two going back and
forth on lines that cross at 60 degrees, two going back and forth head on along lines 0.3 m apart.
Where a pair passes, its two discs overlap on the floor and every camera sees one blob for a few
frames.

Each frame (5 Hz, the rate the issue's outside measurement used) goes through what the server does
for a continuous fused request: each camera's real HSV detector on its rendered frame, the report
through the wire format, `drvs.server.fusion.fuse`, then `drvs.server.tracking.Tracker`: the
tracker as it is (`merges=True`: a merged blob holds the tracks it can hold, they coast through it
and are re-associated by their motion) and, fed the same fused objects in the same run, with the
merge handling switched off (`merges=False`: one track per object, nearest in the Mahalanobis sense,
as before). Both are scored with motmetrics (CLEAR MOT and IDF1) at a 1 m gate, WILDTRACK's.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from drvs.core.model import WorldObject
from drvs.sim.scenario import Scenario, parse_scenario

from .fusion_scene import Cameras, Disc
from .stats import WorkMismatch, publish, verdict

CROSSINGS_SCENE_TEXT = """
name: bench-fusion-crossings
floor_plan: {bounds: [-1, -1, 11, 11], walls: []}
colors:
  yellow: {filter_def: hsv_014110130035225200, bgr: [57, 143, 165]}
  blue:   {filter_def: hsv_100120080130255255, bgr: [167, 100, 42]}
cameras:
  - {id: cam-n, position: [5.0, 10.5, 3.2], yaw_deg: -90, pitch_deg: 36, hfov_deg: 70, resolution: [640, 480],
     fps: 20, max_range_m: 7.0}
  - {id: cam-e, position: [10.5, 5.2, 3.2], yaw_deg: 180, pitch_deg: 36, hfov_deg: 70, resolution: [640, 480],
     fps: 20, max_range_m: 7.0}
  - {id: cam-s, position: [4.8, -0.5, 3.2], yaw_deg: 90, pitch_deg: 36, hfov_deg: 70, resolution: [640, 480],
     fps: 20, max_range_m: 7.0}
  - {id: cam-w, position: [-0.5, 5.0, 3.2], yaw_deg: 0, pitch_deg: 36, hfov_deg: 70, resolution: [640, 480],
     fps: 20, max_range_m: 7.0}
objects: []
robot: {start: [10.5, 10.5], goal: [10.4, 10.4], radius: 0.1, color: blue}
mission: navigate
render: {noise_sigma: 3, lighting: 0.08, floor_texture: 10}
"""
#: The request's region: the whole room.
REGION = (-1.0, -1.0, 11.0, 11.0)
#: Each camera's calibration error: yaw and pitch each off by this many degrees (up or down, drawn
#: each round), its position by this many metres (in a direction drawn each round).
CROSSINGS_CALIBRATION_ERROR = (0.3, 0.02)
#: Frames a second, and each round's length (s): every pair passes at least twice in a quick round.
RATE_HZ = 5.0
FULL_S, QUICK_S = 40.0, 16.0
#: The discs' radius (m): 0.44 m across, a person's shoulders.
DISC_RADIUS = 0.22
#: How far apart (centre to centre, m) the two discs of a pair pass.
PASS_GAP_M = 0.3
#: motmetrics' gate (m): a track further than this from a disc is not its track.
GATE_M = 1.0
#: The targets, every round, at the tracker's default (merges=True).
TARGETS = {"idf1": 0.95, "mota": 0.95}
#: The tracker's modes compared in each round.
MODES = {"merges": True, "nearest": False}
#: The motmetrics figures published.
METRICS = ["idf1", "mota", "motp", "num_switches", "num_fragmentations", "num_false_positives", "num_misses",
           "num_objects", "num_unique_objects", "mostly_tracked"]  # fmt: skip


def crossings_scenario() -> Scenario:
    return parse_scenario(CROSSINGS_SCENE_TEXT, "drvs_bench.fusion_crossings.CROSSINGS_SCENE_TEXT")


def _swing(phase: float) -> float:
    """Back and forth, 0 -> 1 -> 0 over one unit of phase, slowing to a stop at each end (a cosine:
    someone walking to a shelf and back, not a ball bouncing off a wall)."""
    return (1.0 - math.cos(2.0 * math.pi * phase)) / 2.0


@dataclasses.dataclass(frozen=True)
class Walker:
    """A disc on a path: where it is at time t (s)."""

    name: str
    path: Callable[[float], tuple[float, float]]

    def at(self, t: float) -> Disc:
        return Disc(self.path(t), DISC_RADIUS)


def _segment(
    a: tuple[float, float], b: tuple[float, float], period: float, phase: float
) -> Callable[[float], tuple[float, float]]:
    def path(t: float) -> tuple[float, float]:
        s = _swing(t / period + phase)
        return (a[0] + (b[0] - a[0]) * s, a[1] + (b[1] - a[1]) * s)

    return path


def _circle(
    centre: tuple[float, float], radius: float, omega: float, phase: float
) -> Callable[[float], tuple[float, float]]:
    def path(t: float) -> tuple[float, float]:
        angle = phase + omega * t
        return (centre[0] + radius * math.cos(angle), centre[1] + radius * math.sin(angle))

    return path


def walkers(rng: np.random.Generator) -> list[Walker]:
    """Three pairs whose discs pass PASS_GAP_M apart, centre to centre (their edges overlap by
    0.14 m): circling (they meet every 7 s or so), crossing at 60 degrees (every half period), head on
    (every half period); the pairs' paths keep apart from each other's. Speeds up to 0.5-1 m/s; the
    timing varies from round to round."""
    out = []
    # Circling (3.2, 6.4): radii 1.0 and 1.3 m, opposite directions.
    omega = float(rng.uniform(0.45, 0.55))
    start = float(rng.uniform(0, 2 * math.pi))
    out.append(Walker("circle-in", _circle((3.2, 6.4), 1.0, omega, start)))
    out.append(Walker("circle-out", _circle((3.2, 6.4), 1.0 + PASS_GAP_M, -omega, start + 0.9)))
    # Crossing at 60 degrees around (6.6, 3.2): 4 m segments through it, crossed at full speed
    # (pi * 4 m / period); the second disc reaches the crossing point PASS_GAP_M / sin(60) / speed
    # later, so they pass about PASS_GAP_M apart.
    period = float(rng.uniform(13.0, 15.0))
    speed = math.pi * 4.0 / period
    lag = PASS_GAP_M / math.sin(math.radians(60)) / speed / period
    phase = float(rng.uniform(0, 1))
    c = (6.6, 3.2)
    d1 = (2.0, 0.0)
    d2 = (2.0 * math.cos(math.radians(60)), 2.0 * math.sin(math.radians(60)))
    out.append(Walker("x-a", _segment((c[0] - d1[0], c[1] - d1[1]), (c[0] + d1[0], c[1] + d1[1]), period, phase)))
    out.append(Walker("x-b", _segment((c[0] - d2[0], c[1] - d2[1]), (c[0] + d2[0], c[1] + d2[1]), period, phase - lag)))
    # Head on around (6.85, 7.2): 3.3 m segments, PASS_GAP_M apart, opposite directions.
    period = float(rng.uniform(10.0, 12.0))
    phase = float(rng.uniform(0, 1))
    y0, y1 = 7.2 - PASS_GAP_M / 2, 7.2 + PASS_GAP_M / 2
    out.append(Walker("head-a", _segment((5.2, y0), (8.5, y0), period, phase)))
    out.append(Walker("head-b", _segment((8.5, y1), (5.2, y1), period, phase)))
    return out


def run_crossings(seconds: float, seed: int) -> dict[str, Any]:
    """One round: the same fused objects frame by frame into a Tracker per mode, each scored by motmetrics."""
    import motmetrics as mm

    from drvs.server.fusion import fuse
    from drvs.server.tracking import Tracker

    cams = Cameras(
        seed,
        miscalibrated=True,
        scenario=crossings_scenario(),
        calibration_error=CROSSINGS_CALIBRATION_ERROR,
        region=REGION,
        exact_error=True,
    )
    people = walkers(np.random.default_rng([seed, 31]))
    trackers = {mode: Tracker(merges=merges) for mode, merges in MODES.items()}
    accumulators = {mode: mm.MOTAccumulator(auto_id=True) for mode in MODES}
    frames = round(seconds * RATE_HZ)
    t0 = time.time()
    closest = [math.inf] * (len(people) // 2)
    merged_frames = [0] * (len(people) // 2)  # frames in which a pair was one fused object
    unseen = 0
    for f in range(frames):
        t = f / RATE_HZ
        discs = [w.at(t) for w in people]
        if any(not cams.seen_by(d) for d in discs):
            unseen += 1
        fused = fuse(cams.reports(discs, t0 + t), cams.homography_of)
        for k in range(len(closest)):
            a, b = discs[2 * k], discs[2 * k + 1]
            closest[k] = min(closest[k], math.dist(a.xy, b.xy))
            if any(o.outline.contains(_point(a.xy)) and o.outline.contains(_point(b.xy)) for o in fused):
                merged_frames[k] += 1
        truth = np.array([d.xy for d in discs])
        for mode, tracker in trackers.items():
            tracks: list[WorldObject] = tracker.update(fused, t0 + t)
            hyp = np.array([tr.centroid_xy for tr in tracks]).reshape(-1, 2)
            dist = np.sqrt(mm.distances.norm2squared_matrix(truth, hyp, max_d2=GATE_M**2))
            accumulators[mode].update(list(range(len(discs))), [tr.track_id for tr in tracks], dist)
    host = mm.metrics.create()
    out: dict[str, Any] = {
        "frames": frames,
        "rate_hz": RATE_HZ,
        "discs": len(people),
        "pairs_closest_m": [round(v, 3) for v in closest],
        "pairs_merged_frames": merged_frames,
        "frames_a_disc_unseen": unseen,
    }
    for mode, acc in accumulators.items():
        summary = host.compute(acc, metrics=METRICS, name=mode)
        for key in METRICS:
            value = float(summary[key].iloc[0])
            out[f"{mode}_{key}"] = int(value) if key.startswith(("num_", "mostly")) else value
    return out


def _point(xy: tuple[float, float]) -> Any:
    from shapely.geometry import Point

    return Point(xy)


def check_crossings(run: dict[str, Any]) -> None:
    """The scene did what it is for: every pair merged into one fused object in some frames and
    passed within a body width, and every disc was in some camera's view throughout."""
    if (
        min(run["pairs_merged_frames"]) < 2
        or max(run["pairs_closest_m"]) >= 2 * DISC_RADIUS
        or run["frames_a_disc_unseen"]
    ):
        raise WorkMismatch(
            f"fusion crossings: merged frames per pair {run['pairs_merged_frames']} (each at least 2), closest "
            f"{run['pairs_closest_m']} m (each under {2 * DISC_RADIUS:g}), {run['frames_a_disc_unseen']} frames with a "
            "disc out of every view (none): not the scene the figures describe"
        )


def run_part(result: dict[str, Any], rounds: int, quick: bool) -> dict[str, Any]:
    """The crossings part for drvs_bench.fusion: `rounds` rounds, the figures published into `result`
    as crossings_<mode>_<metric> (median, spread, runs); returns the part's description."""
    seconds = QUICK_S if quick else FULL_S
    runs = []
    for r in range(rounds):
        print(f"drvs-bench fusion: round {r + 1}/{rounds}: crossings ...", file=sys.stderr, flush=True)
        run = run_crossings(seconds, 3000 + r)
        check_crossings(run)
        runs.append(run)
    for key, value in runs[0].items():
        if isinstance(value, int | float) and not isinstance(value, bool):
            publish(result, f"crossings_{key}", [float(r[key]) for r in runs])
    return {
        "seconds": seconds,
        "rate_hz": RATE_HZ,
        "cameras": [c.id for c in crossings_scenario().cameras],
        "calibration_error_sd": {
            "yaw_pitch_deg": CROSSINGS_CALIBRATION_ERROR[0],
            "position_m": CROSSINGS_CALIBRATION_ERROR[1],
        },
        "disc_radius_m": DISC_RADIUS,
        "pass_gap_m": PASS_GAP_M,
        "gate_m": GATE_M,
        "modes": {
            "merges": "the tracker as it is (merges=True)",
            "nearest": "the same tracker with merge handling off (merges=False): one track per object",
        },
        "definition": "motmetrics (CLEAR MOT and IDF1; its MOTAccumulator fed frame by frame, distances the discs' "
        "true centres to the tracks' centroids, gated at gate_m): idf1, mota, motp (m), num_switches, ... per mode; "
        "both modes fed the same fused objects in the same run",
        "targets": {f"crossings_merges_{k}": f">= {v:g}" for k, v in TARGETS.items()},
        "runs": runs,
    }


def crossings_targets(result: dict[str, Any]) -> dict[str, Any]:
    """The targets' verdicts (every round must meet them)."""
    found = {}
    for key, target in TARGETS.items():
        name = f"crossings_merges_{key}"
        if f"{name}_runs" in result:
            found[name] = {
                "target": f">= {target:g}",
                "median": result[name],
                "spread": result[f"{name}_spread"],
                "verdict": verdict(result[f"{name}_runs"], target),
            }
    return found


def plot_crossings(result: dict[str, Any], out: Path) -> None:
    """fusion_crossings.png: IDF1 and MOTA per mode (median, min-max whiskers), and one round's paths."""
    from .common import pyplot

    if "crossings" not in result:
        return
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.4), dpi=100)
    ax = axes[0]
    for k, mode in enumerate(MODES):
        for j, metric in enumerate(("idf1", "mota")):
            key = f"crossings_{mode}_{metric}"
            med = result[key]
            lo, hi = result[f"{key}_spread"]
            ax.bar(j + (k - 0.5) * 0.35, med, 0.35, yerr=[[med - lo], [hi - med]], capsize=3,
                   color=f"C{k}", label=mode if j == 0 else None)  # fmt: skip
    ax.axhline(TARGETS["idf1"], color="k", lw=0.8, ls="--", label="target")
    ax.set_xticks([0, 1], ["IDF1", "MOTA"])
    ax.set_ylim(0.5, 1.01)
    ax.set_title("Crossings: identity through merges (5 Hz, 1 m gate)")
    ax.legend(fontsize=8)
    ax = axes[1]
    rng = np.random.default_rng([3000, 31])
    for w in walkers(rng):
        ts = np.arange(0.0, result["crossings"]["seconds"], 1 / RATE_HZ)
        xy = np.array([w.path(float(t)) for t in ts])
        ax.plot(xy[:, 0], xy[:, 1], lw=1, label=w.name)
    for cam in crossings_scenario().cameras:
        ax.plot(*cam.position[:2], "k^")
    ax.set_aspect("equal")
    ax.set_title("The six discs' paths (round 1), cameras ^")
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    fig.savefig(out / "fusion_crossings.png")
    plt.close(fig)


__all__ = ["check_crossings", "crossings_targets", "plot_crossings", "run_crossings", "run_part", "walkers"]

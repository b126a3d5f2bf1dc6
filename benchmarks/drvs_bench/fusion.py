"""drvs-bench fusion: how well the server's fusion and tracking (drvs.server.fusion, drvs.server.tracking) work on
real pixels, and what fused delivery costs the server.

Two overlapping cameras of the simulator (its renderer and camera geometry: textured floor,
lighting, sensor noise) look at yellow discs lying on the floor; the cameras' real HSV detector
finds them in the rendered pixels. Each frame goes through the pipeline the server runs: per
camera a DetectionReport as a camera node makes it (found, narrowed, selected by the request's
region, and through the wire format and back, as the server receives it), then
`drvs.server.fusion.fuse` over both cameras' reports, then (tracking) `drvs.server.tracking.Tracker`.

- accuracy: discs at known random places in the overlap, a few per placement; each camera's
  position error against the truth, and the fused one, in cm (p50/p95), and what the fusion
  leaves over: duplicates (two fused objects for one disc), missed discs, spurious objects.
- tracking: three discs moving on straight lines at constant speed, crossing in the overlap one
  after the other, handed over from one camera to the other; id switches and fragmentations
  (CLEAR MOT's definitions), and the velocity error (m/s) once a track is 1 s old.
- crossings (drvs_bench.fusion_crossings): four miscalibrated cameras, three pairs of discs passing
  within a body width again and again (one blob for a few frames each time), 5 Hz; the tracker with
  and without its merge handling on the same fused objects, scored with motmetrics (IDF1, MOTA) at 1 m.
- cost (networked, needs the server's fused delivery): a drvs-server and two drvs-camera
  processes on videos of the overlap; a robot process asks single shots at 30 Hz, per-camera
  delivery and fused delivery interleaved run by run; the server's CPU per request and the
  robot's latency (p50, p99) of each, and the ratios taken within each round.

Every part runs for several rounds (a different seed each: the noise, the placements, the
motions' timing) and publishes each figure as its median and spread (stats.publish).
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import itertools
import json
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from shapely.geometry import Polygon

from drvs.core.model import WorldObject

from .common import YELLOW, machine, pyplot, write_result
from .fusion_cost import run_cost
from .fusion_crossings import crossings_targets, plot_crossings, run_part
from .fusion_scene import CALIBRATION_ERROR, REGION, Cameras, Disc, fusion_scenario
from .stats import FULL_ROUNDS, QUICK_ROUNDS, WorkMismatch, measured, out_dir, publish, verdict

#: Accuracy: placements per round, and discs per placement wholly inside both views (each
#: placement has one more disc, across one view's edge: place_edge_disc).
FULL_PLACEMENTS = 40
QUICK_PLACEMENTS = 8
INSIDE_DISCS = 2
#: Disc radii (m), and the least gap between two discs' edges (m): close, but apart.
RADIUS_RANGE = (0.15, 0.3)
MIN_GAP_M = 0.3
#: A fused object or a detection counts for the nearest disc within this distance (m).
MATCH_GATE_M = 0.5
#: Tracking: frames a second (the rate a robot would ask for), and the run's length in seconds (all
#: three discs are handed over from one camera to the other in it).
TRACK_RATE_HZ = 10.0
TRACK_S = 16.0
#: The moving discs pass the crossing point this far apart in time (s).
CROSSING_SPACING_S = 2.5
#: The moving discs' edges never come closer than this (m): each stays a blob of its own.
MIN_TRACK_GAP_M = 0.15
#: cam-b's frames are taken this long after cam-a's: the cameras are not synchronised (a frame
#: period of a 20 fps camera is 50 ms; a camera answers with its newest frame).
CAMERA_B_LAG_S = 0.025
#: A track's velocity is scored once it has followed its disc for this long (the filter converging).
VELOCITY_SETTLE_S = 1.0
#: The benchmark's parts, in the order they run.
PARTS = ("accuracy", "tracking", "crossings", "cost")
#: The targets: (key, target, higher is better). Each is met only when every round meets it.
TARGETS: dict[str, tuple[float, bool]] = {
    "accuracy_duplicates": (0.0, False),
    "accuracy_missed": (0.0, False),
    "accuracy_miscalibrated_duplicates": (0.0, False),
    "accuracy_miscalibrated_missed": (0.0, False),
    "accuracy_edge_duplicates": (0.0, False),
    "accuracy_miscalibrated_edge_duplicates": (0.0, False),
    "tracking_id_switches": (0.0, False),
    "tracking_fragmentations": (0.0, False),
    # The fused error is never worse than the worse camera's, disc by disc (a fraction of discs).
    "accuracy_fused_not_worse_than_worse_camera": (1.0, True),
    "accuracy_miscalibrated_fused_not_worse_than_worse_camera": (1.0, True),
}


def _match(
    truths: Sequence[tuple[float, float]], found: Sequence[tuple[float, float]], gate: float = MATCH_GATE_M
) -> list[tuple[int, int, float]]:
    """Optimal one-to-one pairs (truth index, found index, distance m) within the gate (scipy's
    linear_sum_assignment on the distance matrix)."""
    from scipy.optimize import linear_sum_assignment

    if not truths or not found:
        return []
    t = np.asarray(truths, dtype=float)
    f = np.asarray(found, dtype=float)
    dist = np.linalg.norm(t[:, None, :] - f[None, :, :], axis=2)
    cost = np.where(dist <= gate, dist, 1e6)
    rows, cols = linear_sum_assignment(cost)
    return [(int(r), int(c), float(dist[r, c])) for r, c in zip(rows, cols, strict=True) if dist[r, c] <= gate]


def _near(truths: Sequence[tuple[float, float]], point: tuple[float, float]) -> tuple[int, float]:
    """The nearest truth to a point and its distance."""
    dists = [math.dist(t, point) for t in truths]
    k = int(np.argmin(dists))
    return k, dists[k]


def place_discs(rng: np.random.Generator, area: Polygon, count: int, others: Sequence[Disc] = ()) -> list[Disc]:
    """`count` discs of random radius wholly inside `area` (0.2 m in from its edge: a miscalibrated
    view's edges move), at least MIN_GAP_M apart (edge to edge) from each other and from `others`."""
    discs: list[Disc] = []
    for _ in range(10_000):
        if len(discs) == count:
            return discs
        disc = _random_disc(rng, area.bounds)
        if disc.shape.buffer(0.2).within(area) and _apart(disc, [*others, *discs]):
            discs.append(disc)
    raise RuntimeError(f"could not place {count} discs in {area.area:.1f} m²")


def place_edge_disc(rng: np.random.Generator, fovs: Sequence[Polygon], others: Sequence[Disc]) -> Disc:
    """A disc wholly in one camera's view (0.2 m in from its edge) and across the other's edge, a
    quarter to three quarters of it inside: the second camera sees only part of it (its blob is cut
    at the image's edge or the view's range), as when an object is handed over between cameras."""
    x0, y0, x1, y1 = fovs[0].union(fovs[1]).bounds
    for _ in range(20_000):
        disc = _random_disc(rng, (x0, y0, x1, y1))
        shape = disc.shape
        for whole, part in ((fovs[0], fovs[1]), (fovs[1], fovs[0])):
            across = 0.25 <= shape.intersection(part).area / shape.area <= 0.75
            if across and shape.buffer(0.2).within(whole) and _apart(disc, others):
                return disc
    raise RuntimeError("could not place a disc across a view's edge")


def _random_disc(rng: np.random.Generator, bounds: tuple[float, float, float, float]) -> Disc:
    x0, y0, x1, y1 = bounds
    radius = float(rng.uniform(*RADIUS_RANGE))
    return Disc((float(rng.uniform(x0, x1)), float(rng.uniform(y0, y1))), radius)


def _apart(disc: Disc, others: Sequence[Disc]) -> bool:
    return all(math.dist(disc.xy, d.xy) >= disc.radius + d.radius + MIN_GAP_M for d in others)


def _pct(values: Sequence[float], q: float) -> float:
    return float(np.percentile(np.asarray(values, dtype=float), q)) if values else math.nan


def run_accuracy(placements: int, seed: int, miscalibrated: bool = False) -> dict[str, Any]:
    """One round of the accuracy part: `placements` placements of INSIDE_DISCS discs wholly in both
    views and one across a view's edge (place_edge_disc); with miscalibrated, the cameras'
    homographies are off as a real calibration's are (Cameras)."""
    from drvs.server.fusion import fuse

    cams = Cameras(seed, miscalibrated)
    rng = np.random.default_rng([seed, 17])
    overlap = cams.overlap
    fovs = list(cams.fovs.values())
    single: dict[str, list[float]] = {c.id: [] for c in cams.cameras}
    single_missed = dict.fromkeys(single, 0)
    fused_err: list[float] = []
    edge_err: list[float] = []
    edge_whole_err: list[float] = []  # the error of the camera that sees the edge disc whole
    sigma: list[float] = []
    within_2_sigma = duplicates = missed = spurious = merged = discs_total = 0
    edge_duplicates = edge_missed = 0
    not_worse = better_than_best = 0
    per_disc_best: list[float] = []
    t0 = time.time()
    for p in range(placements):
        discs = place_discs(rng, overlap, INSIDE_DISCS)
        discs.append(place_edge_disc(rng, fovs, discs))
        inside = [True] * INSIDE_DISCS + [False]
        discs_total += INSIDE_DISCS
        truths = [d.xy for d in discs]
        reports = cams.reports(discs, t0 + p)
        errors_by_disc: list[dict[str, float]] = [{} for _ in discs]
        for report in reports:
            pairs = _match(truths, [det.centroid_xy for det in report.detections])
            for ti, _fi, dist in pairs:
                errors_by_disc[ti][report.camera_id] = dist * 100
                if inside[ti]:
                    single[report.camera_id].append(dist * 100)
            found = {ti for ti, _fi, _dist in pairs}
            single_missed[report.camera_id] += sum(1 for ti in range(INSIDE_DISCS) if ti not in found)
        objects = fuse(reports, cams.homography_of)
        counts = [0] * len(discs)
        for obj in objects:
            k, dist = _near(truths, obj.centroid_xy)
            if dist > MATCH_GATE_M:
                spurious += 1
                continue
            counts[k] += 1
        duplicates += sum(max(0, c - 1) for c, ok in zip(counts, inside, strict=True) if ok)
        missed += sum(1 for c, ok in zip(counts, inside, strict=True) if ok and c == 0)
        edge_duplicates += max(0, counts[-1] - 1)
        edge_missed += counts[-1] == 0
        whole = [cid for cid in cams.seen_by(discs[-1]) if cid in errors_by_disc[-1]]
        edge_whole_err.extend(errors_by_disc[-1][cid] for cid in whole)
        for ti, fi, dist in _match(truths, [o.centroid_xy for o in objects]):
            obj = objects[fi]
            err = dist * 100
            if not inside[ti]:
                edge_err.append(err)
                continue
            fused_err.append(err)
            sigma.append(obj.uncertainty_m * 100)
            within_2_sigma += dist <= 2 * obj.uncertainty_m
            merged += len(obj.camera_ids) >= 2
            singles = errors_by_disc[ti]
            if len(singles) == len(cams.cameras):
                # 0.05 cm: the wire's float32 coordinates and the weighting's rounding, not a worse answer.
                not_worse += err <= max(singles.values()) + 0.05
                better_than_best += err <= min(singles.values()) + 0.05
                per_disc_best.append(min(singles.values()))
    compared = len(per_disc_best)
    out: dict[str, Any] = {
        "placements": placements,
        "discs": discs_total,
        "fused_objects_matched": len(fused_err),
        "duplicates": duplicates,
        "missed": missed,
        "spurious": spurious,
        "merged_from_both_cameras": merged,
        "fused_error_cm_p50": _pct(fused_err, 50),
        "fused_error_cm_p95": _pct(fused_err, 95),
        "fused_uncertainty_cm_p50": _pct(sigma, 50),
        "fused_within_2_sigma": within_2_sigma / max(1, len(fused_err)),
        "discs_seen_by_both": compared,
        "fused_not_worse_than_worse_camera": not_worse / max(1, compared),
        "fused_not_worse_than_better_camera": better_than_best / max(1, compared),
        "better_camera_error_cm_p50": _pct(per_disc_best, 50),
        "better_camera_error_cm_p95": _pct(per_disc_best, 95),
        "edge_discs": placements,
        "edge_duplicates": edge_duplicates,
        "edge_missed": edge_missed,
        "edge_fused_error_cm_p50": _pct(edge_err, 50),
        "edge_fused_error_cm_p95": _pct(edge_err, 95),
        "edge_whole_camera_error_cm_p50": _pct(edge_whole_err, 50),
        "edge_whole_camera_error_cm_p95": _pct(edge_whole_err, 95),
    }
    for cid, errs in single.items():
        key = cid.replace("-", "_")
        out[f"{key}_error_cm_p50"] = _pct(errs, 50)
        out[f"{key}_error_cm_p95"] = _pct(errs, 95)
        out[f"{key}_missed"] = single_missed[cid]
    return out


@dataclasses.dataclass(frozen=True)
class Mover:
    """A disc moving on a straight line at constant velocity: at `cross_at` s it is at `through`."""

    through: tuple[float, float]
    velocity: tuple[float, float]
    cross_at: float
    radius: float = 0.2

    def at(self, t: float) -> Disc:
        dt = t - self.cross_at
        return Disc((self.through[0] + self.velocity[0] * dt, self.through[1] + self.velocity[1] * dt), self.radius)


def movers(rng: np.random.Generator, seconds: float) -> list[Mover]:
    """Three discs of 0.2 m crossing one point of the overlap 2.5 s apart (two driving from cam-b's
    side of the room to cam-a's, on lines 45 degrees apart, then one across the room): their edges
    pass 0.2 m apart or more, close enough to test the tracker's assignment, and each is handed over
    from one camera to the other through the overlap. The speeds vary a little from round to round."""
    crossing = (0.4, 4.0)
    middle = seconds / 2

    def velocity(direction: tuple[float, float], speed: float) -> tuple[float, float]:
        n = math.hypot(*direction)
        return (direction[0] / n * speed, direction[1] / n * speed)

    return [
        Mover(crossing, velocity((0.25, 1.0), float(rng.uniform(0.57, 0.63))), middle - CROSSING_SPACING_S),
        Mover(crossing, velocity((-0.6, 1.0), float(rng.uniform(0.52, 0.58))), middle),
        Mover(crossing, velocity((1.0, 0.03), float(rng.uniform(0.47, 0.53))), middle + CROSSING_SPACING_S),
    ]


def run_tracking(seconds: float, seed: int, drop_after_s: float = 1.0) -> dict[str, Any]:
    """One round of the tracking part: reports -> fuse -> Tracker at TRACK_RATE_HZ, scored against the truth."""
    from drvs.server.fusion import fuse
    from drvs.server.tracking import Tracker

    cams = Cameras(seed, miscalibrated=True)
    rng = np.random.default_rng([seed, 29])
    motion = movers(rng, seconds)
    tracker = Tracker(drop_after_s=drop_after_s)
    frames = round(seconds * TRACK_RATE_HZ)
    t0 = time.time()
    last_id: list[int | None] = [None] * len(motion)  # the track each disc was last matched to
    matched_before = [False] * len(motion)  # matched in the previous frame it was visible in
    first_matched: dict[tuple[int, int], float] = {}  # (disc, track) -> when that pairing began
    id_switches = fragmentations = misses = visible_frames = 0
    velocity_err: list[float] = []
    position_err: list[float] = []
    cameras_seen: list[list[tuple[str, ...]]] = [[] for _ in motion]  # the views that hold each disc, in turn
    track_ids: set[int] = set()
    matched_ids: set[int] = set()
    closest = math.inf
    paths: dict[int, list[list[float]]] = {}  # each track's centroid, frame by frame (for the plot)
    for f in range(frames):
        t = f / TRACK_RATE_HZ
        discs = [m.at(t) for m in motion]
        for one, other in itertools.combinations(discs, 2):
            closest = min(closest, math.dist(one.xy, other.xy) - one.radius - other.radius)
        seen = [tuple(cams.seen_by(d)) for d in discs]
        visible = [bool(c) for c in seen]
        for i, c in enumerate(seen):
            if c and (not cameras_seen[i] or cameras_seen[i][-1] != c):
                cameras_seen[i].append(c)
        reports = cams.reports(discs, t0 + t, lag_s=(0.0, CAMERA_B_LAG_S))
        tracks: list[WorldObject] = tracker.update(fuse(reports, cams.homography_of), t0 + t)
        track_ids.update(tr.track_id for tr in tracks)
        for tr in tracks:
            paths.setdefault(tr.track_id, []).append([round(tr.centroid_xy[0], 3), round(tr.centroid_xy[1], 3)])
        truths = [d.xy for d in discs]
        # CLEAR MOT: a disc keeps last frame's track while that track is still within the gate;
        # the rest are paired optimally.
        pairs: dict[int, int] = {}
        taken: set[int] = set()
        for i, tid in enumerate(last_id):
            if not visible[i] or tid is None:
                continue
            for j, tr in enumerate(tracks):
                if tr.track_id == tid and j not in taken and math.dist(tr.centroid_xy, truths[i]) <= MATCH_GATE_M:
                    pairs[i] = j
                    taken.add(j)
        rest_t = [i for i in range(len(discs)) if visible[i] and i not in pairs]
        rest_f = [j for j in range(len(tracks)) if j not in taken]
        for ti, fi, _ in _match([truths[i] for i in rest_t], [tracks[j].centroid_xy for j in rest_f]):
            pairs[rest_t[ti]] = rest_f[fi]
        for i, disc in enumerate(discs):
            if not visible[i]:
                continue
            visible_frames += 1
            if i not in pairs:
                misses += 1
                matched_before[i] = False
                continue
            tr = tracks[pairs[i]]
            matched_ids.add(tr.track_id)
            if last_id[i] is not None and last_id[i] != tr.track_id:
                id_switches += 1
            elif last_id[i] is not None and not matched_before[i]:
                fragmentations += 1  # the same track again after a gap: the trajectory was interrupted
            last_id[i] = tr.track_id
            matched_before[i] = True
            since = first_matched.setdefault((i, tr.track_id), t)
            position_err.append(math.dist(tr.centroid_xy, disc.xy) * 100)
            if t - since >= VELOCITY_SETTLE_S:
                velocity_err.append(math.dist(tr.velocity_xy, motion[i].velocity))
    # A hand-over: a disc in one camera's view alone, later in the other's alone (through the overlap).
    handovers = 0
    for seen in cameras_seen:
        alone = [c[0] for c in seen if len(c) == 1]
        handovers += sum(1 for x, y in itertools.pairwise(alone) if x != y)
    return {
        "frames": frames,
        "rate_hz": TRACK_RATE_HZ,
        "discs": len(motion),
        "speeds_mps": [round(math.hypot(*m.velocity), 3) for m in motion],
        "closest_gap_m": closest,
        "visible_disc_frames": visible_frames,
        "misses": misses,
        "id_switches": id_switches,
        "fragmentations": fragmentations,
        "tracks_matched": len(matched_ids),
        "tracks_unmatched": len(track_ids - matched_ids),
        "cameras_sequence": [[list(c) for c in seen] for seen in cameras_seen],
        "handovers": handovers,
        "position_error_cm_p50": _pct(position_err, 50),
        "position_error_cm_p95": _pct(position_err, 95),
        "velocity_error_mps_p50": _pct(velocity_err, 50),
        "velocity_error_mps_p95": _pct(velocity_err, 95),
        "velocity_samples": len(velocity_err),
        "track_paths": {str(k): v for k, v in paths.items()},
        "disc_paths": [[list(m.at(0.0).xy), list(m.at(seconds).xy)] for m in motion],
    }


def _publish_rounds(out: dict[str, Any], prefix: str, runs: Sequence[dict[str, Any]]) -> None:
    """Every numeric figure of the rounds' runs as `prefix_key` (median), `_median`, `_spread`, `_runs`."""
    for key, value in runs[0].items():
        if isinstance(value, int | float) and not isinstance(value, bool):
            values = [float(r[key]) for r in runs]
            if all(math.isfinite(v) for v in values):
                median = publish(out, f"{prefix}_{key}", values)["median"]
                if all(isinstance(r[key], int) for r in runs) and float(median).is_integer():
                    out[f"{prefix}_{key}"] = out[f"{prefix}_{key}_median"] = int(median)  # counts stay counts


def check_accuracy(run: dict[str, Any]) -> None:
    """The accuracy part did its work: every disc found by both cameras (the placements keep them
    wholly in both views), and the fusion matched something."""
    cams = [k for k in run if k.endswith("_missed") and k != "missed"]
    wrong = [f"{k}: {run[k]}" for k in cams if run[k]]
    if wrong or run["discs_seen_by_both"] != run["discs"]:
        raise WorkMismatch(
            f"fusion accuracy: a camera missed discs it sees wholly ({', '.join(wrong) or 'none'}; "
            f"{run['discs_seen_by_both']} of {run['discs']} seen by both): the detector, not the fusion, "
            "would be measured"
        )


def check_tracking(run: dict[str, Any]) -> None:
    """The tracking scenario did what it is for: the discs never touched (each stays one blob) and
    every one of them was handed over from one camera to the other."""
    if run["closest_gap_m"] < MIN_TRACK_GAP_M or run["handovers"] < run["discs"]:
        raise WorkMismatch(
            f"fusion tracking: closest gap {run['closest_gap_m']:.2f} m (at least {MIN_TRACK_GAP_M:g}), "
            f"{run['handovers']} hand-overs (expected {run['discs']}): not the scenario the figures describe"
        )


def targets(out: dict[str, Any]) -> dict[str, Any]:
    found = {}
    for key, (target, higher) in TARGETS.items():
        if f"{key}_runs" in out:
            found[key] = {
                "target": f"{'>=' if higher else '<='} {target:g}",
                "median": out[key],
                "spread": out[f"{key}_spread"],
                "verdict": verdict(out[f"{key}_runs"], target, higher_is_better=higher),
            }
    return found


async def run_fusion(
    out: Path,
    quick: bool,
    parts: Sequence[str] = PARTS,
    rounds: int = 0,
    cost_requests: int = 0,
) -> dict[str, Any]:
    rounds = rounds or (QUICK_ROUNDS if quick else FULL_ROUNDS)
    result: dict[str, Any] = {
        "benchmark": "fusion",
        "rounds": rounds,
        "quick": quick,
        "parts": list(parts),
        "scene": {
            "cameras": [dataclasses.asdict(c) for c in fusion_scenario().cameras],
            "overlap_m2": round(Cameras(0).overlap.area, 2),
            "detector": f"hsv ({YELLOW}) on rendered 640x480 frames (textured floor, lighting, noise sigma 3)",
            "pipeline": "per camera: find, narrow, select by region, report through the wire format and back; "
            "then drvs.server.fusion.fuse over both cameras' reports; tracking: drvs.server.tracking.Tracker per frame",
        },
    }
    if "accuracy" in parts:
        placements = QUICK_PLACEMENTS if quick else FULL_PLACEMENTS
        runs: dict[str, list[dict[str, Any]]] = {"accuracy": [], "accuracy_miscalibrated": []}
        for r in range(rounds):
            for name, run_runs in runs.items():
                print(f"drvs-bench fusion: round {r + 1}/{rounds}: {name} ...", file=sys.stderr, flush=True)
                run = await asyncio.to_thread(run_accuracy, placements, 1000 + r, name.endswith("_miscalibrated"))
                check_accuracy(run)
                run_runs.append(run)
        for name, run_runs in runs.items():
            _publish_rounds(result, name, run_runs)
        result["accuracy"] = {
            "placements_per_round": placements,
            "discs_per_placement": {"inside_both_views": INSIDE_DISCS, "across_a_view_edge": 1},
            "radius_m": list(RADIUS_RANGE),
            "min_gap_m": MIN_GAP_M,
            "match_gate_m": MATCH_GATE_M,
            "calibration_error_sd": {"yaw_pitch_deg": CALIBRATION_ERROR[0], "position_m": CALIBRATION_ERROR[1]},
            "definition": "error: distance from a disc's true centre to the detection's (one camera) or the fused "
            "object's centroid; duplicates: fused objects beyond one per disc; missed: discs with no fused object "
            "within the gate; spurious: fused objects with no disc within it (every figure without edge_ over the "
            "discs wholly in both views); edge_*: the disc of each placement that lies wholly in one view and "
            "across the other's edge (that camera sees part of it), edge_whole_camera_error: the first camera's "
            "error on it. accuracy_*: the cameras' homographies "
            "exact (the detector's own error); accuracy_miscalibrated_*: each camera's homography from a pose off "
            "by calibration_error_sd (a new draw each round), the pixels from the true pose",
            "runs": runs["accuracy"],
            "runs_miscalibrated": runs["accuracy_miscalibrated"],
        }
    if "tracking" in parts:
        seconds = TRACK_S
        tracking_runs = []
        for r in range(rounds):
            print(f"drvs-bench fusion: round {r + 1}/{rounds}: tracking ...", file=sys.stderr, flush=True)
            run = await asyncio.to_thread(run_tracking, seconds, 2000 + r)
            check_tracking(run)
            tracking_runs.append(run)
        _publish_rounds(result, "tracking", tracking_runs)
        result["tracking"] = {
            "seconds": seconds,
            "rate_hz": TRACK_RATE_HZ,
            "camera_b_lag_s": CAMERA_B_LAG_S,
            "cameras_miscalibrated": "as accuracy_miscalibrated: each camera's homography off by calibration_error_sd",
            "velocity_settle_s": VELOCITY_SETTLE_S,
            "definition": "CLEAR MOT: a disc keeps its track while that track stays within the gate, the rest are "
            "paired optimally (linear_sum_assignment); an id switch: a disc matched to another track than before; "
            "a fragmentation: a disc matched to the same track again after frames in which no track matched it; "
            "only frames in which some camera sees the whole disc count",
            "runs": tracking_runs,
        }
    if "crossings" in parts:
        result["crossings"] = await asyncio.to_thread(run_part, result, rounds, quick)
    if "cost" in parts:
        result["cost"] = await run_cost(result, rounds, quick, cost_requests)
    result["targets"] = {**targets(result), **crossings_targets(result)}
    result["machine"] = machine()
    await asyncio.to_thread(write_outputs, result, out)
    return result


def write_outputs(result: dict[str, Any], out: Path) -> None:
    write_result(result, out, "fusion", plot)
    plot_crossings(result, out)


def plot(result: dict[str, Any], out: Path) -> None:
    plt = pyplot()

    panels = [p for p in ("accuracy", "tracking", "cost") if p in result]
    widths = [7.0 if p == "accuracy" else 5.0 for p in panels] or [5.0]
    fig, axes = plt.subplots(
        1, len(widths), figsize=(sum(widths), 4.6), dpi=100, squeeze=False, gridspec_kw={"width_ratios": widths}
    )
    for ax, panel in zip(axes[0], panels, strict=False):
        if panel == "accuracy":
            names = ["cam_a", "cam_b", "better_camera", "fused", "edge_whole_camera", "edge_fused"]
            labels = ["cam-a\nalone", "cam-b\nalone", "better\ncamera", "fused"]
            labels += ["edge disc:\nwhole cam.", "edge disc:\nfused"]
            bars = (
                ("accuracy", 50, "exact calibration, p50"),
                ("accuracy", 95, "exact calibration, p95"),
                ("accuracy_miscalibrated", 50, "calibration error, p50"),
                ("accuracy_miscalibrated", 95, "calibration error, p95"),
            )
            for b, (prefix, q, label) in enumerate(bars):
                keys = [f"{prefix}_{n}_error_cm_p{q}" for n in names]
                med = [result.get(k, math.nan) for k in keys]
                lo = [m - result.get(f"{k}_spread", [m, m])[0] for k, m in zip(keys, med, strict=True)]
                hi = [result.get(f"{k}_spread", [m, m])[1] - m for k, m in zip(keys, med, strict=True)]
                xs = [i + (b - 1.5) * 0.2 for i in range(len(names))]
                ax.bar(xs, med, 0.2, yerr=[lo, hi], label=label, capsize=2)
            ax.set_xticks(range(len(names)), labels, fontsize=8)
            ax.set_ylabel("position error (cm)")
            ax.set_title(
                f"Fusion accuracy, {result['rounds']} rounds (median, [min, max]); duplicates "
                f"{result.get('accuracy_duplicates', 0):g} / {result.get('accuracy_miscalibrated_duplicates', 0):g}, "
                f"missed {result.get('accuracy_missed', 0):g} / {result.get('accuracy_miscalibrated_missed', 0):g}",
                fontsize=9,
            )
            ax.legend(fontsize=7)
        elif panel == "tracking":
            last = result["tracking"]["runs"][-1]
            for cid, fov in Cameras(0).fovs.items():
                xs, ys = fov.exterior.xy
                ax.plot(xs, ys, lw=0.8, color="grey", ls=":")
                ax.annotate(f"{cid}'s view", (fov.centroid.x, fov.centroid.y), fontsize=7, color="grey")
            for k, (start, end) in enumerate(last["disc_paths"]):
                ax.plot([start[0], end[0]], [start[1], end[1]], color="black", lw=0.6, ls="--",
                        label="the discs' paths" if k == 0 else None)  # fmt: skip
            for tid, points in last["track_paths"].items():
                ax.plot([p[0] for p in points], [p[1] for p in points], lw=1.5, label=f"track {tid}")
            x0, y0, x1, y1 = REGION
            ax.set_xlim(x0, x1)
            ax.set_ylim(y0, y1)
            ax.set_aspect("equal")
            ax.set_xlabel("x (m)")
            ax.set_ylabel("y (m)")
            ax.set_title(
                f"Tracking, last of {result['rounds']} rounds: id switches {last['id_switches']}, fragmentations "
                f"{last['fragmentations']},\nhand-overs {last['handovers']}; velocity error p50 "
                f"{last['velocity_error_mps_p50']:.3f} m/s, p95 {last['velocity_error_mps_p95']:.3f} m/s",
                fontsize=9,
            )
            ax.legend(fontsize=7, loc="lower right")
        else:
            cost = result["cost"]
            modes = ["per_camera", "fused"]
            for k, (fig_key, label) in enumerate((("latency_ms_p50", "p50"), ("latency_ms_p99", "p99"))):
                vals = [cost.get(f"{m}_{fig_key}", math.nan) for m in modes]
                ax.bar([i + (k - 0.5) * 0.4 for i in range(2)], vals, 0.4, label=f"latency {label}")
            ax.set_xticks([0, 1], ["per-camera delivery", "fused delivery"], fontsize=8)
            ax.set_ylabel("robot's latency (ms)")
            ax.set_title(
                f"Server CPU per request: per-camera {cost.get('per_camera_server_cpu_ms_per_request', math.nan):.2f}"
                f" ms, fused {cost.get('fused_server_cpu_ms_per_request', math.nan):.2f} ms,\nbare-proxy floor "
                f"{cost.get('bare_server_cpu_ms_per_request', math.nan):.2f} ms (medians of {result['rounds']} rounds)",
                fontsize=9,
            )
            ax.legend(fontsize=8)
        ax.grid(True, axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "fusion.png")
    plt.close(fig)


def fusion_main(args: argparse.Namespace) -> int:
    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    unknown = [p for p in parts if p not in PARTS]
    if unknown or not parts:
        print(f"drvs-bench fusion: --parts: {', '.join(unknown) or 'none'}: name some of {', '.join(PARTS)}",
              file=sys.stderr)  # fmt: skip
        return 2
    if args.rounds < 0 or args.requests < 0:
        print("drvs-bench fusion: --rounds and --requests must be >= 0 (0: the default)", file=sys.stderr)
        return 2
    out = out_dir(args.out)
    result = measured("fusion", lambda: asyncio.run(run_fusion(out, args.quick, parts, args.rounds, args.requests)))
    if result is None:
        return 1
    summary: dict[str, Any] = {
        k: (round(v, 4) if isinstance(v, float) else v)
        for k, v in result.items()
        if k.startswith(("accuracy_", "tracking_", "crossings_")) and not k.endswith(("_median", "_spread", "_runs"))
    }
    if "cost" in result:
        summary["cost"] = {
            k: (round(v, 4) if isinstance(v, float) else v)
            for k, v in result["cost"].items()
            if isinstance(v, int | float) and not k.endswith(("_median", "_runs"))
        }
    summary["targets"] = {k: v["verdict"] for k, v in result["targets"].items()}
    print(json.dumps(summary, indent=1))
    print(f"written: {out / 'fusion.json'}, {out / 'fusion.png'}")
    return 0


def add_fusion_parser(sub: Any) -> None:
    f = sub.add_parser("fusion", help="fusion accuracy and tracking on rendered pixels; the server's cost of fusing")
    f.add_argument("--quick", action="store_true", help="a smoke run: 3 rounds of short runs (full: 5)")
    f.add_argument("--parts", default=",".join(PARTS), help=f"comma-separated parts (default: {','.join(PARTS)})")
    f.add_argument("--rounds", type=int, default=0, help="override the number of rounds")
    f.add_argument("--requests", type=int, default=0, help="override the cost part's requests per run")
    f.add_argument("--out", type=Path, default=None)
    f.set_defaults(func=fusion_main)


__all__ = ["add_fusion_parser", "run_accuracy", "run_fusion", "run_tracking"]

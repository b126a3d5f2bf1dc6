"""drvs-bench mobile --parts accuracy: where a moving camera puts a still object, as its robot's
poses come late or noisy by known amounts.

A scout of the simulator (a camera 0.8 m up, 30° down, 70° wide, 640x480) drives a gentle curve
past a yellow disc at 0.5 and at 1.0 m/s. Its frames are rendered from its true pose at 10 frames
a second (real OpenCV warps, lighting and sensor noise), the disc is found by the real HSV
detector in the mount's base frame, and moved to the map by the pose a camera node would use:
`PoseBuffer.at(capture time)` over the robot's poses as they would have reached the node, 20 a
second, each stamped with when it held, and

- late: at a frame's capture the node holds only the poses stamped `delay` or more before it (a
  localisation stack's latency); it uses the newest (it does not extrapolate), or
- noisy: each pose off by Gaussian noise of `noise_m` (per axis) or `noise_deg` (heading).

The error is the distance from the detection's centroid to the disc's centre. The setting with the
true pose on time is the floor (rendering, detection and mapping alone); every other setting is
published beside it, measured on the same frames. The frames are processed at their capture (the
worst case: a node answering a request later may already hold the poses around the capture).
"""

from __future__ import annotations

import itertools
import math
import random
import statistics
import time
from typing import Any

from drvs.core.filters import object_type
from drvs.core.geometry import FieldOfView
from drvs.core.mobile import PoseBuffer, move_detection
from drvs.core.model import Pose2
from drvs.detectors.base import REGISTRY, CameraView, Frame, FrameAnalysis
from drvs.sim.render import CameraRenderer
from drvs.sim.scenario import Scenario, parse_scenario

from .helpers import percentile

YELLOW = "hsv_014110130035225200"
TARGET = (4.5, 2.6)
#: The scout's way: a gentle curve to the left, passing the disc on its left (about 0.9 rad in 4 m).
PATH = [(0.5, 1.0), (1.5, 1.1), (2.5, 1.4), (3.3, 1.9), (3.9, 2.5)]
SCENE = f"""
name: mobile-accuracy
floor_plan: {{bounds: [0, 0, 8, 5], walls: []}}
colors:
  yellow: {{filter_def: {YELLOW}, bgr: [57, 143, 165]}}
  blue:   {{filter_def: hsv_100120080130255255, bgr: [167, 100, 42]}}
cameras:
  - {{id: ceiling, position: [4.0, -3.0, 6.0], yaw_deg: 90, pitch_deg: 60, hfov_deg: 90}}
objects:
  - {{kind: obstacle, color: yellow, center: [{TARGET[0]}, {TARGET[1]}], radius: 0.15}}
scouts:
  - {{id: scout, camera: {{height: 0.8, pitch_deg: 30, hfov_deg: 70, resolution: [640, 480], fps: 10}},
     path: {[list(p) for p in PATH]}, speed_mps: SPEED}}
robot: {{start: [7.5, 4.5], goal: [7.5, 0.5], radius: 0.2, color: blue}}
mission: navigate
"""
SPEEDS_MPS = (0.5, 1.0)
FRAME_RATE_HZ = 10.0
POSE_RATE_HZ = 20.0
#: (name, delay s, position noise m, heading noise degrees): the floor, then one error at a time.
SETTINGS: tuple[tuple[str, float, float, float], ...] = (
    ("true pose", 0.0, 0.0, 0.0),
    ("late 50 ms", 0.05, 0.0, 0.0),
    ("late 100 ms", 0.10, 0.0, 0.0),
    ("late 200 ms", 0.20, 0.0, 0.0),
    ("position noise 2 cm", 0.0, 0.02, 0.0),
    ("position noise 5 cm", 0.0, 0.05, 0.0),
    ("heading noise 1°", 0.0, 0.0, 1.0),
    ("heading noise 2°", 0.0, 0.0, 2.0),
)
MAX_POSE_GAP_S = 0.25


def scenario(speed_mps: float) -> Scenario:
    return parse_scenario(SCENE.replace("SPEED", f"{speed_mps:g}"), "mobile-accuracy")


def frames(scene: Scenario) -> list[tuple[float, list[Any]]]:
    """(world time, the detector's disc-sized blobs in the base frame) for each frame along the way."""
    (scout,) = scene.scouts
    base = scout.mount.base_homography(scout.resolution)
    view = CameraView(base, FieldOfView.compute(base, scout.resolution, 8.0), scout.resolution, camera_id="scout")
    detector = REGISTRY["hsv"](view, None)
    renderer = CameraRenderer(scene, scout, seed=5)
    duration = sum(math.dist(a, b) for a, b in itertools.pairwise(PATH)) / scout.speed_mps
    out = []
    for k in range(int(duration * FRAME_RATE_HZ)):
        t = k / FRAME_RATE_HZ
        image = renderer.render(None, k, 0.0, t)
        found = detector.find(FrameAnalysis(Frame(image, t, k)), object_type(YELLOW))
        out.append((t, [d for d in found if 0.03 < d.outline.area < 0.15]))  # the disc is 0.07 m²
    return out


def errors(scene: Scenario, looks: list[tuple[float, list[Any]]], setting: tuple[str, float, float, float],
           seed: int) -> list[float]:  # fmt: skip
    """The disc's position error in each frame that shows it, with poses as `setting` has them."""
    _, delay, noise_m, noise_deg = setting
    (scout,) = scene.scouts
    rng = random.Random(seed)
    stamps = [i / POSE_RATE_HZ for i in range(int((looks[-1][0] + 1) * POSE_RATE_HZ))]
    noisy = []
    for s in stamps:
        p = scout.pose_at(s)
        dx, dy, dyaw = rng.gauss(0, noise_m), rng.gauss(0, noise_m), math.radians(rng.gauss(0, noise_deg))
        noisy.append((s, Pose2(p.x + dx, p.y + dy, p.yaw + dyaw)))
    out = []
    for t, blobs in looks:
        if not blobs:
            continue
        buffer = PoseBuffer(MAX_POSE_GAP_S)
        for s, held in noisy:
            if s <= t - delay + 1e-9:  # what had reached the node by the frame's capture
                buffer.push(s, held)
        used = buffer.at(t)
        if used is None:
            continue
        placed = [move_detection(d, used) for d in blobs]
        out.append(min(math.dist(d.centroid_xy, TARGET) for d in placed))
    return out


def run_accuracy(quick: bool) -> dict[str, Any]:
    """Per speed and setting: the position error's median and p95 (cm) over the frames, for each
    noise seed (rounds), and its ratio to the floor's."""
    seeds = range(2 if quick else 5)
    started = time.perf_counter()
    result: dict[str, Any] = {
        "frame_rate_hz": FRAME_RATE_HZ,
        "pose_rate_hz": POSE_RATE_HZ,
        "max_pose_gap_s": MAX_POSE_GAP_S,
        "target_xy": list(TARGET),
        "rounds": len(seeds),
        "speeds": {},
    }
    for speed in SPEEDS_MPS:
        scene = scenario(speed)
        looks = frames(scene)
        per_setting: dict[str, Any] = {}
        floor: list[float] = []
        for setting in SETTINGS:
            name, delay, noise_m, noise_deg = setting
            rounds = [errors(scene, looks, setting, seed) for seed in seeds]
            medians = [100 * statistics.median(r) for r in rounds]
            p95s = [100 * percentile(r, 95) for r in rounds]
            entry: dict[str, Any] = {
                "delay_s": delay,
                "noise_m": noise_m,
                "noise_deg": noise_deg,
                "frames": len(rounds[0]),
                "error_cm_median": statistics.median(medians),
                "error_cm_median_spread": [min(medians), max(medians)],
                "error_cm_p95": statistics.median(p95s),
                "error_cm_p95_spread": [min(p95s), max(p95s)],
            }
            if name == "true pose":
                floor = medians
            else:
                ratios = [m / f for m, f in zip(medians, floor, strict=True)]
                entry["median_over_floor"] = statistics.median(ratios)
                entry["median_over_floor_spread"] = [min(ratios), max(ratios)]
            per_setting[name] = entry
        result["speeds"][f"{speed:g}"] = {
            "frames_with_the_disc": sum(1 for _, b in looks if b),
            "settings": per_setting,
        }
    result["seconds"] = round(time.perf_counter() - started, 1)
    return result


def plot_accuracy(result: dict[str, Any], out: Any) -> None:
    from .common import pyplot

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8, 4), dpi=100)
    names = [s[0] for s in SETTINGS]
    width = 0.8 / max(1, len(result["speeds"]))
    for i, (speed, data) in enumerate(result["speeds"].items()):
        xs = [k + i * width for k in range(len(names))]
        med = [data["settings"][n]["error_cm_median"] for n in names]
        p95 = [data["settings"][n]["error_cm_p95"] for n in names]
        ax.bar(xs, med, width, label=f"{speed} m/s: median")
        ax.scatter(xs, p95, marker="_", s=200, color="black", label="p95" if i == 0 else None, zorder=3)
    ax.set_xticks([k + width * (len(result["speeds"]) - 1) / 2 for k in range(len(names))])
    ax.set_xticklabels(names, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel("position error, cm")
    ax.set_title("A still object seen from a moving camera, by pose error")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "mobile_accuracy.png")
    plt.close(fig)

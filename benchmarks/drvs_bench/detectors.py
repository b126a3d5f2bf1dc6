"""drvs-bench detectors: what each detector plug-in costs and how well it finds what it should.

For every detector in `drvs.detectors.REGISTRY` that this module has inputs for (`INPUTS`), in
interleaved rounds (stats.FULL_ROUNDS, QUICK_ROUNDS with --quick, or --rounds):

- **find ms per 640x480 frame**: the detector's `find` on real frames (rendered office frames for
  hsv, aruco and foreground, real footage for people, the office frames for a model), in this
  process, one new `FrameAnalysis` per frame (so the frame's grey or HSV conversion is counted);
  a detector that `observes` every frame has its `observe` timed apart;
- **camera CPU at 10 requests a second** against the same camera idle: one real `drvs-camera`
  process per detector (serving only that detector, on a looping 20 fps video of its frames),
  served by a real `drvs-server`; this process, as the robot, sends single-shot requests of that
  type at 10 a second; the camera process's CPU from /proc, both modes in the same round;
- **peak RSS** of a camera process with every detector loaded (a model too) against one with only
  `hsv`, both started side by side and given requests of every type they serve;
- **accuracy** where there is ground truth: markers rendered at known floor poses in the office's
  camera views (position error in cm, heading error in degrees), obstacles of colours no `hsv`
  filter matches in the office against an empty-floor background image (found, missed, false),
  people against hand-marked feet (precision, recall, feet error; drvs_bench.detectors_people).

A detector this branch does not have is reported under `missing`, one without inputs here under
`no_inputs`: neither is a crash. Every run's work is checked (stats.check_work): a request that was
not answered in full by its camera, or a timed `find` that found less than its inputs hold, fails
the benchmark (WorkMismatch) instead of publishing a figure.
"""

from __future__ import annotations

import asyncio
import json
import math
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from shapely.geometry import box

from drvs.core.geometry import FieldOfView, Homography
from drvs.core.homography_file import save_homography
from drvs.detectors import REGISTRY, CameraView, Detector, Frame, FrameAnalysis, parse_object_type
from drvs.sim.render import CameraRenderer
from drvs.sim.scenario import CameraDef, ColorDef, ObjectDef, Scenario, load_scenario
from drvs.sim.scene import write_video

from .common import IMAGE_SIZE, VTEST, machine, pyplot
from .detectors_cameras import RATE_HZ, measure_cameras, measure_memory
from .detectors_foreground import floor_lines, floor_scene
from .detectors_markers import draw_markers, marker_poses
from .detectors_people import accuracy_people, people_inputs, people_lines
from .stats import FULL_ROUNDS, QUICK_ROUNDS, WorkMismatch, check_work, interleaved, publish

#: Frames of each detector's video (it loops at 20 fps) and frames `find` is timed on per round.
FULL_FRAMES, QUICK_FRAMES = 40, 8
FULL_TIMED, QUICK_TIMED = 12, 3
#: Seconds of each camera CPU run.
FULL_SECONDS, QUICK_SECONDS = 10.0, 1.0
#: The office camera whose view the timing, the camera CPU and the memory runs use.
TIMING_CAMERA = "cam-west"
#: Colours no hsv filter of the office matches (BGR), for obstacles only `foreground` can find.
UNMATCHED = {
    "red": (50, 45, 160),
    "white": (215, 218, 222),
    "dark": (48, 50, 52),
    "purple": (120, 50, 110),
}
#: Obstacles added to the office so every camera sees some (the office's own two are at the
#: hallway entrance, in cam-hall's view): (colour, x0, y0, x1, y1), metres.
EXTRA_OBSTACLES = (
    ("red", 3.6, 4.6, 4.3, 5.2),
    ("white", 5.6, 7.6, 6.4, 8.2),
    ("dark", 1.0, 6.0, 1.5, 6.8),
    ("purple", 8.6, 3.4, 9.3, 4.0),
    ("white", 6.5, 1.0, 7.2, 1.8),
)


@dataclass
class DetectorInputs:
    """What one detector is benchmarked on."""

    prefix: str
    #: The filter_def the timed runs and the camera's requests use.
    filter_def: str
    #: 640x480 BGR frames `find` is timed on (and, looping, the camera's video).
    frames: list[NDArray[np.uint8]]
    homography: Homography
    max_range_m: float
    #: The detector's options in this process (drvs.detectors: `REGISTRY[prefix](view, options)`).
    options: dict[str, Any] | None
    #: What the camera's --config file says to give the detector the same options.
    camera_config: dict[str, Any]
    #: What the frames are, for the JSON.
    frames_are: str
    #: The timed `find` must find at least this many detections a frame, on average over a round.
    min_found: int = 1
    #: What else the JSON should say about the inputs (the model used ...).
    about: dict[str, Any] = field(default_factory=dict)
    #: Frames an observing detector sees before it is timed (a background model's warm-up).
    warm_frames: list[NDArray[np.uint8]] = field(default_factory=list)
    #: Filled in by `materialise`: the camera process's video and homography file.
    video: Path | None = None
    homography_file: Path | None = None

    def region(self) -> tuple[float, float, float, float]:
        """A request region over everything this camera sees."""
        fov = FieldOfView.compute(self.homography, IMAGE_SIZE, self.max_range_m)
        x0, y0, x1, y1 = fov.floor.bounds
        return (x0 - 0.5, y0 - 0.5, x1 + 0.5, y1 + 0.5)

    def view(self, camera_id: str = "bench") -> CameraView:
        fov = FieldOfView.compute(self.homography, IMAGE_SIZE, self.max_range_m)
        return CameraView(self.homography, fov, IMAGE_SIZE, camera_id=camera_id)


# --- the office and what is put in it ----------------------------------------------------------


def bench_office(obstacles: bool = True) -> Scenario:
    """The paper's office with its obstacles in colours no hsv filter matches, and more of them
    so that every camera sees some (obstacles=False: the empty floor, for background images).
    Its moving obstacle (the trolley) and its scout are left out: the benchmark's frames are of a
    still world."""
    office = load_scenario()
    colours = {name: ColorDef(name, "", bgr) for name, bgr in UNMATCHED.items()}
    recoloured = ["red", "purple"]
    objects: list[ObjectDef] = []
    seen = [c.field_of_view.floor for c in office.cameras]
    for obj in office.objects:
        if obj.kind == "obstacle":
            # (Not the one only the office's scout sees: the benchmark's cameras are the fixed ones.)
            if obstacles and not obj.moving and any(f.intersects(obj.shape) for f in seen):
                objects.append(replace(obj, color=colours[recoloured.pop(0)]))
        else:
            objects.append(obj)
    if obstacles:
        for name, x0, y0, x1, y1 in EXTRA_OBSTACLES:
            objects.append(ObjectDef("obstacle", box(x0, y0, x1, y1), colours[name]))
    return replace(office, objects=tuple(objects), scouts=())


def office_frames(
    scenario: Scenario, camera: CameraDef, versions: Sequence[int], seed: int = 0
) -> list[NDArray[np.uint8]]:
    renderer = CameraRenderer(scenario, camera, seed=seed)
    return [renderer.render(None, v) for v in versions]


# --- per-detector inputs ------------------------------------------------------------------------


@dataclass
class Work:
    """Shared state of one run: the scratch directory and what is rendered once."""

    tmp: Path
    quick: bool
    cache: dict[str, Any] = field(default_factory=dict)

    @property
    def frames(self) -> int:
        return QUICK_FRAMES if self.quick else FULL_FRAMES

    def office(self) -> tuple[Scenario, CameraDef, list[NDArray[np.uint8]]]:
        """The bench office, its timing camera, and that camera's frames (with markers)."""
        if "office" not in self.cache:
            scenario = bench_office()
            camera = scenario.camera(TIMING_CAMERA)
            frames = office_frames(scenario, camera, range(self.frames))
            markers = marker_poses(camera, scenario, 0.3, 1.3, limit=6)
            rng = np.random.default_rng(1)
            frames = [draw_markers(f, camera.homography, markers, rng=rng) for f in frames]
            self.cache["office"] = (scenario, camera, frames)
        result: tuple[Scenario, CameraDef, list[NDArray[np.uint8]]] = self.cache["office"]
        return result

    def office_inputs(self, prefix: str, filter_def: str, **kw: Any) -> DetectorInputs:
        _scenario, camera, frames = self.office()
        return DetectorInputs(
            prefix=prefix,
            filter_def=filter_def,
            frames=frames,
            homography=camera.homography,
            max_range_m=camera.max_range_m,
            frames_are=f"the office (drvs.sim, {TIMING_CAMERA}) rendered: textured floor, lighting drift, noise, "
            "coloured discs, obstacles of unmatched colours and 0.3 m ArUco markers",
            **{"options": None, "camera_config": {}, **kw},
        )


class NoInputs(Exception):
    """A detector's inputs cannot be made on this machine (the message says why)."""


def hsv_inputs(work: Work) -> DetectorInputs:
    # The office's yellow discs (markers and distractors) in cam-west's view.
    return work.office_inputs("hsv", "hsv_014110130035225200", min_found=1)


def aruco_inputs(work: Work) -> DetectorInputs:
    # Six 0.3 m markers of DICT_4X4_50 drawn on the floor of every frame.
    return work.office_inputs("aruco", "aruco_4x4_50", min_found=4)


def empty_floor(work: Work, camera: CameraDef) -> Path:
    """A picture of the camera's empty floor (the office without obstacles), as `drvs-camera
    snapshot` would take it: the foreground detector's `background`."""
    path = work.tmp / f"empty-{camera.id}.png"
    if not path.exists():
        image = CameraRenderer(bench_office(obstacles=False), camera, seed=0).render(None, 0)
        cv2.imwrite(str(path), image)
    return path


def foreground_inputs(work: Work) -> DetectorInputs:
    _scenario, camera, frames = work.office()
    background = str(empty_floor(work, camera))
    # Its obstacles (and the markers drawn on the floor, which the empty-floor picture lacks).
    return work.office_inputs(
        "foreground", "foreground", options={"background": background}, camera_config={"background": background},
        min_found=4, warm_frames=frames[-6:],
    )  # fmt: skip


def model_inputs(work: Work) -> DetectorInputs:
    # The model detector's own benchmark network (drvs_bench.onnx_models, by its author): random
    # weights in a small YOLO's shape, about a YOLOv8n's arithmetic at 640; a smoke run uses 320.
    from .onnx_models import yolo_sized_model

    size = 320 if work.quick else 640
    path, macs = yolo_sized_model(work.tmp / "bench-model.onnx", classes=80, size=size)
    spec = {"path": str(path), "classes": [f"class{i}" for i in range(80)]}
    inputs = work.office_inputs(
        "model", "model_bench", options={"models": {"bench": spec}}, camera_config={"models": {"bench": spec}},
        min_found=0,
    )  # fmt: skip
    inputs.about["model"] = {
        "built_by": "drvs_bench.onnx_models.yolo_sized_model: random weights in the shape of a small YOLO "
        "(stride-2 conv backbone, heads at strides 8, 16, 32, 80 classes); it detects nothing",
        "input": [1, 3, size, size],
        "gflops": round(2 * macs / 1e9, 2),
        "for_comparison": "YOLOv8n at 640: 8.7 GFLOPs",
    }
    return inputs


#: Inputs by detector prefix. A detector registered without an entry here is listed as `no_inputs`.
INPUTS: dict[str, Callable[[Work], DetectorInputs]] = {
    "hsv": hsv_inputs,
    "aruco": aruco_inputs,
    "foreground": foreground_inputs,
    "people": people_inputs,
    "model": model_inputs,
}


def materialise(inputs: DetectorInputs, directory: Path) -> None:
    """Write the detector's video (its frames, looping at 20 fps) and homography file."""
    directory.mkdir(parents=True, exist_ok=True)
    inputs.video = write_video(directory / f"{inputs.prefix}.avi", inputs.frames, 20.0)
    inputs.homography_file = directory / f"{inputs.prefix}.homography.yaml"
    save_homography(inputs.homography_file, inputs.homography)


def build(prefix: str, inputs: DetectorInputs) -> Detector:
    return REGISTRY[prefix](inputs.view(), inputs.options)


# --- find ms per frame --------------------------------------------------------------------------


def measure_find(all_inputs: Mapping[str, DetectorInputs], rounds: int, timed: int, out: dict[str, Any]) -> None:
    """`find` (and `observe`) on the same frames, detectors interleaved round by round."""
    detectors = {p: build(p, i) for p, i in all_inputs.items()}
    types = {p: parse_object_type(i.filter_def) for p, i in all_inputs.items()}
    for p, det in detectors.items():
        det.check(types[p])
        for seq, image in enumerate(all_inputs[p].warm_frames):
            det.observe(Frame(image, 0.0, seq))
    per_round: list[dict[str, dict[str, Any]]] = [{} for _ in range(rounds)]
    sequence = 1_000_000
    try:
        for r, prefix in interleaved(list(all_inputs), rounds):
            inputs, det = all_inputs[prefix], detectors[prefix]
            find_ms, observe_ms, found = [], [], 0
            for i in range(timed):
                image = inputs.frames[(r * timed + i) % len(inputs.frames)]
                sequence += 1
                frame = Frame(image, time.time(), sequence)
                if det.observes:
                    t0 = time.perf_counter()
                    det.observe(frame)
                    observe_ms.append((time.perf_counter() - t0) * 1000)
                t0 = time.perf_counter()
                result = det.find(FrameAnalysis(frame), types[prefix])
                find_ms.append((time.perf_counter() - t0) * 1000)
                found += len(det.narrow(result, types[prefix]))
            check_work(
                f"find {prefix}, round {r + 1}",
                {"enough_found": 1},
                {"enough_found": 1 if found >= inputs.min_found * timed else 0, "found": found},
            )
            per_round[r][prefix] = {
                "find_ms": statistics.median(find_ms),
                "observe_ms": statistics.median(observe_ms) if observe_ms else None,
                "found_per_frame": found / timed,
            }
    finally:
        for det in detectors.values():
            det.close()
    for prefix in all_inputs:
        entry = out.setdefault(prefix, {})
        publish(entry, "find_ms", [f[prefix]["find_ms"] for f in per_round])
        if detectors[prefix].observes:
            publish(entry, "observe_ms", [f[prefix]["observe_ms"] for f in per_round])
        entry["found_per_frame"] = per_round[0][prefix]["found_per_frame"]
        entry["heavy"] = detectors[prefix].heavy
        entry["observes"] = detectors[prefix].observes
        if "hsv" in all_inputs and prefix != "hsv":
            # Side by side: this detector's find over hsv's in the same round (the machine drifts less
            # within a round than between runs).
            publish(entry, "find_ms_over_hsv", [f[prefix]["find_ms"] / f["hsv"]["find_ms"] for f in per_round])


# --- accuracy -----------------------------------------------------------------------------------


def spread(values: Sequence[float]) -> dict[str, float | None]:
    """Median, 95th percentile and max of errors (None when there are none)."""
    if not values:
        return {"median": None, "p95": None, "max": None}
    v = np.asarray(values, dtype=np.float64)
    return {"median": float(np.median(v)), "p95": float(np.percentile(v, 95)), "max": float(v.max())}


def office_view(camera: CameraDef) -> CameraView:
    fov = FieldOfView.compute(camera.homography, camera.resolution, camera.max_range_m)
    return CameraView(camera.homography, fov, camera.resolution, camera_id=camera.id)


def accuracy_aruco(work: Work) -> dict[str, Any]:
    """0.3 m markers of DICT_4X4_50 on a grid over each office camera's floor, each at another
    heading, drawn into rendered frames: position (the detection's centroid against the marker's
    centre) and heading errors of every marker found, and how many were found."""
    scenario = bench_office()
    wanted = parse_object_type("aruco_4x4_50")
    versions = (3,) if work.quick else (3, 11, 19)
    position_cm: list[float] = []
    heading_deg: list[float] = []
    rendered = found = false = 0
    per_camera: dict[str, Any] = {}
    for camera in scenario.cameras:
        poses = marker_poses(camera, scenario, 0.3, 1.6 if work.quick else 1.0)
        truth = {m.marker_id: m for m in poses}
        det = REGISTRY["aruco"](office_view(camera), None)
        cam_found = 0
        cam_distances: list[float] = []
        for v in versions:
            image = draw_markers(office_frames(scenario, camera, [v])[0], camera.homography, poses,
                                 rng=np.random.default_rng(v))  # fmt: skip
            detections = det.narrow(det.find(FrameAnalysis(Frame(image, 0.0, v)), wanted), wanted)
            rendered += len(poses)
            seen: set[int] = set()
            for d in detections:
                m = truth.get(d.marker_id) if d.marker_id is not None else None
                if m is None or m.marker_id in seen:
                    false += 1
                    continue
                seen.add(m.marker_id)
                position_cm.append(100 * math.dist(d.centroid_xy, (m.x, m.y)))
                if d.heading_deg is not None:
                    heading_deg.append(abs((d.heading_deg - m.heading_deg + 180.0) % 360.0 - 180.0))
                cam_distances.append(math.dist((m.x, m.y), camera.position[:2]))
            cam_found += len(seen)
        found += cam_found
        per_camera[camera.id] = {
            "markers": len(poses),
            "found": cam_found,
            "rendered": len(poses) * len(versions),
            "farthest_found_m": round(max(cam_distances), 2) if cam_distances else None,
        }
        det.close()
    return {
        "what": "0.3 m DICT_4X4_50 markers (black square; one-module white margin) lying on the floor at known "
        "poses, a grid 1 m apart over each office camera's view, headings varied; drawn into rendered office "
        "frames (textured floor, lighting, noise)",
        "rendered": rendered,
        "found": found,
        "false": false,
        "found_fraction": found / rendered if rendered else None,
        "position_error_cm": spread(position_cm),
        "heading_error_deg": spread(heading_deg),
        "per_camera": per_camera,
    }


def accuracy_foreground(work: Work) -> dict[str, Any]:
    """The office with obstacles of colours no hsv filter matches (the office's two, recoloured,
    and five more), each camera's foreground detector given a picture of its empty floor: obstacles
    found, missed and false in each camera's view."""
    scenario = bench_office()
    wanted = parse_object_type("foreground")
    frames = 8 if work.quick else 24
    found = missed = false = 0
    per_camera: dict[str, Any] = {}
    for camera in scenario.cameras:
        view = office_view(camera)
        det = REGISTRY["foreground"](view, {"background": str(empty_floor(work, camera))})
        images = office_frames(scenario, camera, range(1, frames + 1), seed=3)
        for seq, image in enumerate(images):
            det.observe(Frame(image, float(seq), seq))
        last = Frame(images[-1], float(frames), frames)
        detections = det.narrow(det.find(FrameAnalysis(last), wanted), wanted)
        visible = [
            o for o in scenario.obstacles if o.shape.intersection(view.field_of_view.floor).area >= 0.5 * o.shape.area
        ]
        partly = [o for o in scenario.obstacles if o.shape.intersects(view.field_of_view.floor)]
        matched = [o for o in visible if any(d.outline.intersects(o.shape) for d in detections)]
        near = [o.shape.buffer(0.15) for o in partly]
        wrong = [d for d in detections if not any(d.outline.intersects(n) for n in near)]
        found += len(matched)
        missed += len(visible) - len(matched)
        false += len(wrong)
        per_camera[camera.id] = {
            "obstacles_in_view": len(visible),
            "found": len(matched),
            "missed": len(visible) - len(matched),
            "false": len(wrong),
            "false_areas_m2": [round(d.area_m2, 3) for d in wrong],
            "missed_obstacles": [
                {
                    "colour": o.color.name if o.color else "",
                    "centre": [round(o.shape.centroid.x, 2), round(o.shape.centroid.y, 2)],
                }
                for o in visible
                if o not in matched
            ],
        }
        det.close()
    return {
        "what": "the office (drvs.sim) with 7 obstacles in colours no hsv filter of the office matches (red, purple, "
        "white, near-black), after the detector saw the camera's frames (lighting drift, noise) from the start; "
        "each camera's background: a picture of its empty floor; an obstacle counts when half of it is in view, "
        "a detection is false when it touches no obstacle (within 0.15 m)",
        "frames_observed": frames,
        "found": found,
        "missed": missed,
        "false": false,
        "per_camera": per_camera,
    }


#: Accuracy by detector prefix, against ground truth.
ACCURACY: dict[str, Callable[[Work], dict[str, Any] | None]] = {
    "aruco": accuracy_aruco,
    "foreground": accuracy_foreground,
    "people": accuracy_people,
}


# --- the run ------------------------------------------------------------------------------------


def gather_inputs(work: Work, only: Sequence[str] | None = None) -> tuple[dict[str, DetectorInputs], dict[str, str]]:
    """Inputs for every registered detector this module knows, and why any other is left out."""
    found: dict[str, DetectorInputs] = {}
    left_out: dict[str, str] = {}
    for prefix in INPUTS:
        if only is not None and prefix not in only:
            continue
        if prefix not in REGISTRY:
            left_out[prefix] = "missing: no such detector in drvs.detectors.REGISTRY on this branch"
    for prefix in REGISTRY:
        if only is not None and prefix not in only:
            continue
        make = INPUTS.get(prefix)
        if make is None:
            left_out[prefix] = "no_inputs: registered, but drvs_bench.detectors has no inputs for it"
            continue
        try:
            found[prefix] = make(work)
        except NoInputs as exc:
            left_out[prefix] = f"no_inputs: {exc}"
    return found, left_out


async def run_detectors(
    out_dir: Path, quick: bool, only: Sequence[str] | None = None, n_rounds: int = 0
) -> dict[str, Any]:
    """The benchmark; `only`: these detector prefixes (default: every registered one); `n_rounds`:
    the interleaved rounds (0: QUICK_ROUNDS with `quick`, else FULL_ROUNDS)."""
    rounds = n_rounds or (QUICK_ROUNDS if quick else FULL_ROUNDS)
    result: dict[str, Any] = {"benchmark": "detectors", "quick": quick, "rounds": rounds, "rate_hz": RATE_HZ}
    # The machine is shared: how loaded it was (1-minute load average, 2 cores) when the run began and ended.
    result["load_average_at_start"] = os.getloadavg()[0]
    t0 = time.perf_counter()

    def say(what: str) -> None:
        print(f"drvs-bench detectors: {what} ... ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)

    with tempfile.TemporaryDirectory(prefix="drvs-bench-det-") as tmp:
        work = Work(Path(tmp), quick)
        say("rendering inputs")
        all_inputs, left_out = await asyncio.to_thread(gather_inputs, work, only)
        for inputs in all_inputs.values():
            await asyncio.to_thread(materialise, inputs, work.tmp / "videos")
        per: dict[str, Any] = {
            p: {"filter_def": i.filter_def, "frames": i.frames_are, **i.about} for p, i in all_inputs.items()
        }
        say("find ms per frame")
        timed = QUICK_TIMED if quick else FULL_TIMED
        await asyncio.to_thread(measure_find, all_inputs, rounds, timed, per)
        say("camera CPU at 10 requests/s against idle")
        await measure_cameras(all_inputs, rounds, QUICK_SECONDS if quick else FULL_SECONDS, work.tmp, per)
        say("peak RSS: every detector against hsv only")
        if "hsv" in all_inputs:
            await measure_memory(all_inputs, 1 if quick else 3, work.tmp, result)
        say("accuracy")
        for prefix in all_inputs:
            check = ACCURACY.get(prefix)
            if check is not None:
                accuracy = await asyncio.to_thread(check, work)
                if accuracy is not None:
                    per[prefix]["accuracy"] = accuracy
        if "foreground" in all_inputs:
            say("foreground on a tiled floor with markers and tape")
            per["foreground"]["floor_scene"] = await asyncio.to_thread(floor_scene, work.tmp, quick)
        result["detectors"] = per
        result["left_out"] = left_out
        say("done")
    result["load_average_at_end"] = os.getloadavg()[0]
    result["seconds"] = round(time.perf_counter() - t0, 1)
    result["definition"] = DEFINITION
    result["machine"] = machine()
    await asyncio.to_thread(write_outputs, result, out_dir)
    return result


DEFINITION = {
    "find_ms": "median ms of the detector's find() per 640x480 frame in this process (a new FrameAnalysis per "
    "frame, so a grey or HSV conversion is counted), per round; observe_ms likewise for observe()",
    "camera_cpu_idle_cores / camera_cpu_10hz_cores": "CPU of a drvs-camera process serving only this detector "
    "(all threads, /proc utime + stime) over the run's wall time, idle (no requests) and while one robot sends "
    "single-shot requests of this type at 10 a second (timed until the last is answered); both modes in every round",
    "camera_marginal_cpu_ms_per_request": "(CPU at 10/s - the idle CPU rate x the same wall time) / requests",
    "memory": "VmHWM of a drvs-camera running every detector here against one running only hsv, both on the "
    "office video, started side by side, after requests of every type they serve",
    "holds_for": "this machine at the time of the run: 2 cores shared with other work, so absolute figures are "
    "noisy; ratios are taken within a round",
}


def accuracy_lines(per: Mapping[str, Any]) -> list[str]:
    """The accuracy figures as short lines of text (the plot's fourth panel)."""
    lines: list[str] = []

    def fmt(v: float | None, digits: int = 1) -> str:
        return "-" if v is None else f"{v:.{digits}f}"

    aruco = per.get("aruco", {}).get("accuracy")
    if aruco:
        p, h = aruco["position_error_cm"], aruco["heading_error_deg"]
        lines += [
            f"aruco: {aruco['found']}/{aruco['rendered']} markers found, {aruco['false']} false",
            f"  position error cm: median {fmt(p['median'], 2)}, p95 {fmt(p['p95'], 2)}, max {fmt(p['max'], 2)}",
            f"  heading error deg: median {fmt(h['median'], 2)}, p95 {fmt(h['p95'], 2)}, max {fmt(h['max'], 2)}",
            "",
        ]
    fg = per.get("foreground", {}).get("accuracy")
    if fg:
        lines += [f"foreground (office): {fg['found']} found, {fg['missed']} missed, {fg['false']} false", ""]
    lines += floor_lines(per.get("foreground", {}).get("floor_scene"))
    people = per.get("people", {}).get("accuracy")
    if people:
        lines += people_lines(people)
    return lines


def write_outputs(result: dict[str, Any], out: Path) -> None:
    plt = pyplot()

    out.mkdir(parents=True, exist_ok=True)
    per: dict[str, Any] = result.get("detectors", {})
    names = list(per)
    fig, axes = plt.subplots(1, 4, figsize=(18, 4.4), dpi=100, gridspec_kw={"width_ratios": [3, 3, 2, 4]})
    x = np.arange(len(names))

    def bars(ax: Any, offset: float, width: float, key: str, scale: float, label: str | None) -> None:
        med = [per[n].get(key, math.nan) * scale for n in names]
        lo = [m - per[n].get(f"{key}_spread", [math.nan, math.nan])[0] * scale for n, m in zip(names, med, strict=True)]
        hi = [per[n].get(f"{key}_spread", [math.nan, math.nan])[1] * scale - m for n, m in zip(names, med, strict=True)]
        ax.bar(x + offset, med, width, yerr=[lo, hi], capsize=3, label=label)

    ax = axes[0]
    bars(ax, 0.0, 0.6, "find_ms", 1.0, None)
    ax.set_yscale("log")
    ax.set_ylabel("ms per 640x480 frame (find)")
    ax.set_title("Detector time per frame")
    ax = axes[1]
    bars(ax, -0.2, 0.4, "camera_cpu_idle_cores", 100.0, "idle")
    bars(ax, 0.2, 0.4, "camera_cpu_10hz_cores", 100.0, f"{result.get('rate_hz', RATE_HZ):g} requests/s")
    ax.set_ylabel("camera process CPU (% of a core)")
    ax.set_title("Camera CPU: idle against 10 requests/s")
    ax.legend(fontsize=8)
    for ax in axes[:2]:
        ax.set_xticks(x, names)
        ax.grid(True, axis="y", alpha=0.3)
    ax = axes[2]
    memory = result.get("memory", {})
    if memory:
        values = [memory["camera_peak_rss_bytes_hsv"] / 1e6, memory["camera_peak_rss_bytes_all"] / 1e6]
        ax.bar([0, 1], values, 0.6)
        ax.set_xticks([0, 1], ["hsv only", "every detector"])
        ax.set_ylabel("camera peak RSS (MB)")
        ax.set_title("Camera memory")
        ax.grid(True, axis="y", alpha=0.3)
    ax = axes[3]
    ax.axis("off")
    ax.set_title("Accuracy")
    ax.text(0.0, 1.0, "\n".join(accuracy_lines(per)) or "no accuracy measured", va="top", ha="left", fontsize=8,
            family="monospace", transform=ax.transAxes)  # fmt: skip
    fig.suptitle(f"drvs-bench detectors ({result.get('rounds')} interleaved rounds; bars: median, whiskers: min-max)")
    fig.tight_layout()
    fig.savefig(out / "detectors.png")
    plt.close(fig)
    (out / "detectors.json").write_text(json.dumps(result, indent=1) + "\n")


__all__ = ["VTEST", "WorkMismatch", "run_detectors"]

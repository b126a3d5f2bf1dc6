"""drvs-bench detectors, the people part: real footage of people walking, hand-marked feet.

OpenCV's sample footage (vtest.avi, Debian's opencv-doc, 768x576) with feet marked by hand on ten
frames (tests/data/vtest_feet.json, 57 people). The people detector is scored there at the camera's
defaults and at the older settings side by side, at 640x480 (frames and marks scaled) and as
recorded: precision, recall, how far its feet are from the marked ones (pixels, and metres on the
floor through the footage's homography), and its milliseconds per frame in interleaved rounds, the
search by geometry against the whole-frame scan in the same round.
"""

from __future__ import annotations

import json
import math
import statistics
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
from numpy.typing import NDArray

from drvs.core.geometry import FieldOfView, Homography, homography_from_pose
from drvs.detectors import REGISTRY, CameraView, Detector, Frame, FrameAnalysis, parse_object_type

from .common import IMAGE_SIZE, VTEST
from .stats import FULL_ROUNDS, QUICK_ROUNDS, interleaved, publish, verdict

if TYPE_CHECKING:
    from .detectors import DetectorInputs, Work

#: Feet marked by hand on frames of VTEST (tests/data, by the people detector's author).
VTEST_FEET = Path(__file__).resolve().parents[2] / "tests" / "data" / "vtest_feet.json"
#: The footage's pose, fitted to its people (tests/detectors/test_people.py's POSE): 5.6 m up, 26 degrees
#: down, a 60 degree lens; the same pose at 640x480 gives the same view, scaled.
VTEST_POSE = ((0.0, 0.0, 5.6), 90.0, 26.0, 60.0)
VTEST_RANGE_M = 40.0
NATIVE_SIZE = (768, 576)
#: The whole-frame scan as the camera ran it by default before the search by geometry (HOG's
#: window, no resampling), and the people tests' tuned setting (85 px at 768x576, scaled).
OLD_DEFAULT = {"min_height_px": 128}
PEOPLE_NATIVE = {"min_height_px": 85}
PEOPLE_TUNED = {"min_height_px": round(85 * 480 / 576)}
#: The people tests' rule: a detection matches a marked person when its feet are within this
#: fraction of its box height of the marked feet (greedy, strongest first, each person once).
MATCH_FRACTION = 0.12
#: Runs of `find` per frame in the timed rounds, of which the fastest counts.
FIND_REPEATS = 3
#: Targets at the camera's defaults, at both sizes.
TARGETS = {"recall": 0.85, "precision": 0.9, "feet_error_m_max": 0.5, "ms_over_old_default": 0.6}


def vtest_frames(indices: Sequence[int], resize: bool = True) -> dict[int, NDArray[np.uint8]]:
    """Frames of vtest.avi by index, resized to 640x480 (resize=False: as recorded, 768x576)."""
    from .detectors import NoInputs

    if not VTEST.is_file():
        raise NoInputs(f"{VTEST} is absent (apt-get install opencv-doc)")
    wanted = set(indices)
    out: dict[int, NDArray[np.uint8]] = {}
    cap = cv2.VideoCapture(str(VTEST))
    try:
        index = 0
        while len(out) < len(wanted):
            ok, image = cap.read()
            if not ok:
                raise NoInputs(f"{VTEST} ended at frame {index}; wanted up to {max(wanted)}")
            if index in wanted:
                if resize:
                    image = cv2.resize(image, IMAGE_SIZE, interpolation=cv2.INTER_AREA)
                out[index] = np.asarray(image, dtype=np.uint8)
            index += 1
    finally:
        cap.release()
    return out


def vtest_homography(size: tuple[int, int] = IMAGE_SIZE) -> Homography:
    position, yaw, pitch, hfov = VTEST_POSE
    return homography_from_pose(position, yaw, pitch, hfov, size)


def people_inputs(work: Work) -> DetectorInputs:
    from .detectors import DetectorInputs

    indices = [5 * i for i in range(work.frames)]
    frames = vtest_frames(indices)
    return DetectorInputs(
        prefix="people",
        filter_def="people",
        frames=[frames[i] for i in indices],
        homography=vtest_homography(),
        max_range_m=VTEST_RANGE_M,
        # As a camera runs it by default: the search by geometry.
        options=None,
        camera_config={},
        frames_are=f"real footage: {VTEST} (Debian opencv-doc), every 5th frame from 0, resized to 640x480",
        min_found=0,
    )


def _detector(size: tuple[int, int], options: dict[str, Any] | None) -> Detector:
    homography = vtest_homography(size)
    view = CameraView(homography, FieldOfView.compute(homography, size, VTEST_RANGE_M), size, camera_id="vtest")
    return REGISTRY["people"](view, options)


def _score(det: Detector, size: tuple[int, int], images: dict[int, Any], marks: dict[int, list[Any]]) -> dict[str, Any]:
    from .detectors import spread

    wanted = parse_object_type("people")
    homography = vtest_homography(size)
    to_image = homography.inverse()
    true = false = missed = 0
    errors_px: list[float] = []
    errors_m: list[float] = []
    for index, feet in marks.items():
        found = det.narrow(det.find(FrameAnalysis(Frame(images[index], 0.0, index)), wanted), wanted)
        free = list(range(len(feet)))
        for d in sorted(found, key=lambda d: -d.score):
            u, v = to_image.apply([list(d.ground_contact_xy)])[0]
            near = [(math.dist((u, v), feet[j]), j) for j in free]
            near = [(e, j) for e, j in near if e <= MATCH_FRACTION * d.pixel_box.height]
            if not near:
                false += 1
                continue
            error, j = min(near)
            free.remove(j)
            true += 1
            errors_px.append(error)
            errors_m.append(math.dist(d.ground_contact_xy, homography.apply([list(feet[j])])[0]))
        missed += len(free)
    return {
        "true": true,
        "false": false,
        "missed": missed,
        "precision": true / max(1, true + false),
        "recall": true / max(1, true + missed),
        "feet_error_px": spread(errors_px),
        "feet_error_m": spread(errors_m),
    }


def _timed_find(det: Detector, image: Any, index: int) -> tuple[float, float]:
    """One `find` (a new FrameAnalysis): ms of wall clock and of this process's CPU (all its threads)."""
    wanted = parse_object_type("people")
    w0, c0 = time.perf_counter(), time.process_time()
    det.find(FrameAnalysis(Frame(image, 0.0, index)), wanted)
    return (time.perf_counter() - w0) * 1000, (time.process_time() - c0) * 1000


def _paired_ms(new: Detector, old: Detector, images: dict[int, Any]) -> dict[str, float]:
    """The two detectors side by side on each frame: FIND_REPEATS runs of each, alternating which goes
    first, each one's fastest counted (the machine is shared: the fastest run is the least
    disturbed). Medians over the frames of each one's ms (wall and CPU) and of the per-frame ratios
    new / old: a frame's two searches run milliseconds apart, under the same load."""
    per: dict[str, list[float]] = {k: [] for k in ("new_wall", "old_wall", "new_cpu", "old_cpu")}
    for index, image in images.items():
        best = dict.fromkeys(per, math.inf)
        for rep in range(FIND_REPEATS):
            for name, det in (("new", new), ("old", old)) if rep % 2 == 0 else (("old", old), ("new", new)):
                wall, cpu = _timed_find(det, image, index)
                best[f"{name}_wall"] = min(best[f"{name}_wall"], wall)
                best[f"{name}_cpu"] = min(best[f"{name}_cpu"], cpu)
        for key, value in best.items():
            per[key].append(value)
    out = {key: statistics.median(values) for key, values in per.items()}
    out["wall_ratio"] = statistics.median(n / o for n, o in zip(per["new_wall"], per["old_wall"], strict=True))
    out["cpu_ratio"] = statistics.median(n / o for n, o in zip(per["new_cpu"], per["old_cpu"], strict=True))
    return out


def accuracy_people(work: Work) -> dict[str, Any]:
    """Precision, recall and feet error on the hand-marked frames, at each size: the camera's
    default (the search by geometry), the old default (the whole-frame scan at 128 px) and the people
    tests' tuned setting; then ms per frame of the default against the old default in interleaved
    rounds, and the targets' verdicts."""
    truth = json.loads(VTEST_FEET.read_text())
    if work.quick:  # a smoke run: four of the marked frames
        truth["frames"] = truth["frames"][:4]
    native = (int(truth["image_size"][0]), int(truth["image_size"][1]))
    sizes = {"640x480": IMAGE_SIZE, "768x576": native}
    # Settings by name (kept from before the search by geometry: camera_default, tuned, native_768x576).
    runs: dict[str, tuple[dict[str, Any] | None, tuple[int, int]]] = {
        "camera_default": (None, IMAGE_SIZE),
        "old_default": (OLD_DEFAULT, IMAGE_SIZE),
        "tuned": (PEOPLE_TUNED, IMAGE_SIZE),
        "camera_default_768x576": (None, native),
        "old_default_768x576": (OLD_DEFAULT, native),
        "native_768x576": (PEOPLE_NATIVE, native),
    }
    data: dict[str, tuple[dict[int, Any], dict[int, list[Any]]]] = {}
    for label, size in sizes.items():
        sx, sy = size[0] / native[0], size[1] / native[1]
        marks = {f["index"]: [(p["feet"][0] * sx, p["feet"][1] * sy) for p in f["people"]] for f in truth["frames"]}
        data[label] = (vtest_frames(list(marks), resize=size != native), marks)
    out: dict[str, Any] = {}
    detectors = {name: _detector(size, options) for name, (options, size) in runs.items()}
    try:
        for name, (options, size) in runs.items():
            images, marks = data["640x480" if size == IMAGE_SIZE else "768x576"]
            out[name] = {
                "image_size": list(size),
                "options": options or {},
                **_score(detectors[name], size, images, marks),
            }
            if options is None:
                out[name]["passes"] = len(getattr(detectors[name], "passes", None) or ())
        rounds = QUICK_ROUNDS if work.quick else FULL_ROUNDS
        pairs = {"": ("camera_default", "old_default"), "_768x576": ("camera_default_768x576", "old_default_768x576")}
        timed: dict[str, list[dict[str, float]]] = {suffix: [] for suffix in pairs}
        for _r, suffix in interleaved(list(pairs), rounds):
            new, old = pairs[suffix]
            images = data["640x480" if runs[new][1] == IMAGE_SIZE else "768x576"][0]
            timed[suffix].append(_paired_ms(detectors[new], detectors[old], images))
    finally:
        for det in detectors.values():
            det.close()
    targets: dict[str, Any] = {}
    for suffix, label in (("", "640x480"), ("_768x576", "768x576")):
        new, old = out[f"camera_default{suffix}"], out[f"old_default{suffix}"]
        got = timed[suffix]
        for entry, who in ((new, "new"), (old, "old")):
            publish(entry, "find_ms", [g[f"{who}_wall"] for g in got])
            publish(entry, "find_cpu_ms", [g[f"{who}_cpu"] for g in got])
        ratio = [g["wall_ratio"] for g in got]
        publish(new, "find_ms_over_old_default", ratio)
        publish(new, "find_cpu_ms_over_old_default", [g["cpu_ratio"] for g in got])
        targets[label] = {
            "recall": {"value": new["recall"], "target": TARGETS["recall"],
                       "verdict": verdict([new["recall"]], TARGETS["recall"])},
            "precision": {"value": new["precision"], "target": TARGETS["precision"],
                          "verdict": verdict([new["precision"]], TARGETS["precision"])},
            "feet_error_m_max": {"value": new["feet_error_m"]["max"], "target": TARGETS["feet_error_m_max"],
                                 "verdict": verdict([new["feet_error_m"]["max"] or math.inf],
                                                    TARGETS["feet_error_m_max"], higher_is_better=False)},
            "ms_over_old_default": {"value": new["find_ms_over_old_default"],
                                    "spread": new["find_ms_over_old_default_spread"],
                                    "target": TARGETS["ms_over_old_default"],
                                    "verdict": verdict(ratio, TARGETS["ms_over_old_default"], higher_is_better=False)},
            "cpu_ms_over_old_default": {"value": new["find_cpu_ms_over_old_default"],
                                        "spread": new["find_cpu_ms_over_old_default_spread"]},
            "old_default_recall": old["recall"],
        }  # fmt: skip
    people = sum(len(f["people"]) for f in truth["frames"])
    return {
        "what": f"{len(truth['frames'])} frames of {VTEST} with {people} people whose feet were marked by hand "
        f"({VTEST_FEET.name}), at 640x480 (frames and marks scaled) and as recorded (768x576); the footage's pose "
        f"fitted to its people {VTEST_POSE}; a detection is true when its feet (ground contact mapped back to the "
        f"image) are within {MATCH_FRACTION} of its box height of a marked person's, greedy, strongest first. "
        "camera_default: the camera's defaults (the search by the homography's geometry); old_default: the "
        "whole-frame scan at min_height_px 128 (the camera's default before the geometry); tuned / native_768x576: "
        "the people tests' min_height_px 85 at 768x576 (scaled at 640x480). find_ms: ms of find per marked frame, the "
        f"geometry and the old default side by side on each frame ({FIND_REPEATS} runs each, alternating which goes "
        "first, each one's fastest counted), the median over the frames, per round; find_cpu_ms: the same in this "
        "process's CPU time (all threads: both searches use OpenCV's threads); *_over_old_default: the median over "
        "the frames of each frame's ratio, per round",
        "rounds": rounds,
        **out,
        "targets": targets,
    }


def people_lines(accuracy: dict[str, Any]) -> list[str]:
    """The people figures as short lines of text (the plot's accuracy panel)."""
    lines = ["people (vtest.avi, hand-marked feet):"]
    for name, entry in accuracy.items():
        if isinstance(entry, dict) and "precision" in entry:
            size = "x".join(str(v) for v in entry["image_size"])
            ms = f", {entry['find_ms']:.0f} ms" if "find_ms" in entry else ""
            lines.append(f"  {name} ({size}): precision {entry['precision']:.2f}, recall {entry['recall']:.2f}{ms}")
    return lines

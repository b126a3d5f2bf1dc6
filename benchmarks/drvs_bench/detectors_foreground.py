"""A real floor for `foreground`: tiles, tape lines and printed ArUco markers in the background
picture, a plain cardboard box of the floor's colour family placed later, and frames as an MJPEG
camera sends them (optics blur, sensor noise, sub-pixel jitter between frames, JPEG compression).

The floor is drawn top-down with OpenCV at 5 mm a pixel (tiles 0.5 m with 8 mm grout, two 5 cm
tape lines, two markers of cv2.aruco's DICT_4X4_50 with their white margins), then seen through
the camera's homography: warped at twice the camera's resolution and shrunk by pixel area (so thin
grout is not aliased), blurred by the lens (sigma 0.7 px), shifted by this frame's jitter (normal,
sigma `jitter_px` in each axis), noised (sigma `noise_sigma`) and put through JPEG at quality 80.
The background picture is one such frame of the empty floor (what `drvs-camera snapshot` takes),
or the median of several (`snapshot --frames N`).

`run_scene` is what `drvs-bench detectors` publishes: over `requests` requests (each on a new
frame the detector has observed, as a camera serves them), how often the box is found and how many
other objects are reported (false detections per 100 requests), for the texture-aware model and,
side by side on the same frames, for the model without it (`texture_noise=False`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from shapely.geometry import Polygon, box

from drvs.core.geometry import FieldOfView, Homography, homography_from_pose
from drvs.detectors import CameraView, Frame, FrameAnalysis, parse_object_type
from drvs.detectors.foreground import ForegroundDetector

SIZE = (640, 480)
#: The floor drawing: metres per pixel, and the part of the floor drawn (x0, y0, x1, y1).
FLOOR_M_PER_PX = 0.005
FLOOR_BOUNDS = (-6.0, 1.0, 6.0, 11.0)
TILE_M = 0.5
GROUT_M = 0.008
#: Beige tiles (BGR), each tile a little off (per-tile offsets up to TILE_SPREAD), with grain.
TILE_BGR = (150, 172, 192)
TILE_SPREAD = 6
GROUT_BGR = (105, 115, 125)
#: A cardboard box: brown, the floor's hue family (B < G < R), darker and more saturated.
BOX_BGR = (88, 128, 168)
BOX = box(0.70, 4.80, 1.15, 5.15)
#: Printed markers: (dictionary id, centre, side in metres), each with a white margin of a cell.
MARKERS = ((7, (-0.40, 3.20), 0.30), (23, (1.60, 6.40), 0.20))
#: Tape: (polygon, BGR): yellow safety tape along y, white tape across.
TAPES = (
    (box(-1.40, 2.0, -1.35, 9.5), (40, 200, 230)),
    (box(-3.0, 7.00, 3.0, 7.05), (235, 235, 235)),
)
JPEG_QUALITY = 80
NOISE_SIGMA = 2.5
JITTER_PX = 0.2
LENS_BLUR_PX = 0.7


def camera() -> Homography:
    """3 m up, looking along +y, 40 degrees down, 60 degree lens (as tests/detectors/test_foreground.py's)."""
    return homography_from_pose((0.0, 0.0, 3.0), 90.0, 40.0, 60.0, SIZE)


def view() -> CameraView:
    h = camera()
    return CameraView(h, FieldOfView.compute(h, SIZE, 15.0), SIZE, camera_id="floor")


def _floor_px(points: Any) -> NDArray[np.int32]:
    x0, y0 = FLOOR_BOUNDS[0], FLOOR_BOUNDS[1]
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    return np.round((pts - (x0, y0)) / FLOOR_M_PER_PX).astype(np.int32)


def draw_floor(with_box: bool, seed: int = 0) -> NDArray[np.uint8]:
    """The floor seen from above (row 0 at y0: y grows with the row), BGR."""
    rng = np.random.default_rng(seed)
    x0, y0, x1, y1 = FLOOR_BOUNDS
    width, height = round((x1 - x0) / FLOOR_M_PER_PX), round((y1 - y0) / FLOOR_M_PER_PX)
    tile_px = round(TILE_M / FLOOR_M_PER_PX)
    grout_px = max(1, round(GROUT_M / FLOOR_M_PER_PX))
    tiles_x, tiles_y = math.ceil(width / tile_px), math.ceil(height / tile_px)
    offsets = rng.integers(-TILE_SPREAD, TILE_SPREAD + 1, (tiles_y, tiles_x, 1))
    per_tile = np.clip(np.asarray(TILE_BGR) + offsets, 0, 255)
    floor = np.repeat(np.repeat(per_tile, tile_px, axis=0), tile_px, axis=1)[:height, :width].astype(np.float32)
    grain = cv2.GaussianBlur(rng.normal(0.0, 1.0, (height, width)).astype(np.float32), (0, 0), 1.5)
    floor *= (1.0 + 0.04 * grain / float(grain.std()))[:, :, None]
    image = np.clip(floor, 0, 255).astype(np.uint8)
    for i in range(0, width + 1, tile_px):
        cv2.rectangle(image, (i - grout_px // 2, 0), (i + grout_px // 2, height), GROUT_BGR, cv2.FILLED)
    for j in range(0, height + 1, tile_px):
        cv2.rectangle(image, (0, j - grout_px // 2), (width, j + grout_px // 2), GROUT_BGR, cv2.FILLED)
    for shape, bgr in TAPES:
        cv2.fillPoly(image, [_floor_px(shape.exterior.coords[:-1])], bgr, lineType=cv2.LINE_AA)
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    for marker_id, (cx, cy), side in MARKERS:
        cells = 6  # 4x4 bits and the black border
        side_px = round(side / FLOOR_M_PER_PX)
        marker = cv2.aruco.generateImageMarker(dictionary, marker_id, side_px)
        margin = round(side_px / cells)
        sheet = cv2.copyMakeBorder(marker, margin, margin, margin, margin, cv2.BORDER_CONSTANT, value=255)
        # The printed sheet is white paper, a little warmer than pure white.
        sheet_bgr = cv2.cvtColor(sheet, cv2.COLOR_GRAY2BGR).astype(np.float32) * np.float32(0.92)
        left, top = _floor_px([(cx, cy)])[0] - sheet.shape[0] // 2
        # Flipped vertically: the drawing's rows grow with y, a printed sheet's top is at +y.
        image[top : top + sheet.shape[0], left : left + sheet.shape[1]] = np.flipud(sheet_bgr).astype(np.uint8)
    if with_box:
        cv2.fillPoly(image, [_floor_px(BOX.exterior.coords[:-1])], BOX_BGR, lineType=cv2.LINE_AA)
    return image


@dataclass
class FloorCamera:
    """Frames of the drawn floor as an MJPEG camera sends them; each call a new frame."""

    floor: NDArray[np.uint8]
    seed: int = 1
    noise_sigma: float = NOISE_SIGMA
    jitter_px: float = JITTER_PX

    def __post_init__(self) -> None:
        self.rng = np.random.default_rng(self.seed)
        x0, y0 = FLOOR_BOUNDS[0], FLOOR_BOUNDS[1]
        to_floor = np.array([[FLOOR_M_PER_PX, 0, x0], [0, FLOOR_M_PER_PX, y0], [0, 0, 1]])
        double = np.diag([2.0, 2.0, 1.0])
        # Floor drawing pixels -> the camera's pixels at twice its resolution.
        self._warp = double @ np.linalg.inv(camera().matrix) @ to_floor
        self.sequence = 0

    def image(self, gain: float = 1.0, shadow: Polygon | None = None, darken: float = 0.45) -> NDArray[np.uint8]:
        """A frame; `gain` scales the whole image (the building's light), `shadow` darkens a floor
        region by `darken` with a soft edge of a few pixels, every channel alike."""
        dx, dy = self.rng.normal(0.0, self.jitter_px, 2) * 2  # at twice the resolution
        shift = np.array([[1, 0, dx], [0, 1, dy], [0, 0, 1]])
        width, height = SIZE
        big = cv2.warpPerspective(
            self.floor, shift @ self._warp, (2 * width, 2 * height), flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT, borderValue=(190, 185, 180),
        )  # fmt: skip
        small = cv2.resize(big, SIZE, interpolation=cv2.INTER_AREA).astype(np.float32)
        image = np.asarray(cv2.GaussianBlur(small, (0, 0), LENS_BLUR_PX), dtype=np.float32) * np.float32(gain)
        if shadow is not None:
            hard = np.zeros((height, width), dtype=np.float32)
            ring = camera().inverse().apply(np.asarray(shadow.exterior.coords)[:-1])
            cv2.fillPoly(hard, [np.round(ring).astype(np.int32)], 1.0)
            soft = np.asarray(cv2.GaussianBlur(hard, (0, 0), 3.0), dtype=np.float32)
            image *= (1.0 - darken * soft)[:, :, None]
        image += self.rng.normal(0.0, self.noise_sigma, image.shape).astype(np.float32)
        pixels = np.clip(np.round(image), 0, 255).astype(np.uint8)
        ok, jpeg = cv2.imencode(".jpg", pixels, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        assert ok
        return np.asarray(cv2.imdecode(jpeg, cv2.IMREAD_COLOR), dtype=np.uint8)

    def frame(self) -> Frame:
        self.sequence += 1
        return Frame(self.image(), 1_700_000_000.0 + self.sequence / 15.0, self.sequence)

    def frames(self, count: int) -> Iterator[Frame]:
        for _ in range(count):
            yield self.frame()


def background_picture(path: Path, frames: int = 1, seed: int = 100) -> Path:
    """The empty floor's picture as `drvs-camera snapshot --frames N` takes it: the per-pixel median
    of N frames (one frame for N = 1)."""
    cam = FloorCamera(draw_floor(with_box=False), seed=seed)
    images = [cam.image() for _ in range(frames)]
    picture = images[0] if frames == 1 else np.median(np.stack(images), axis=0).round().astype(np.uint8)
    cv2.imwrite(str(path), picture)
    return path


def score(detections: Sequence[Any]) -> tuple[bool, list[Polygon]]:
    """(the box found: a detection whose outline covers its centre, within 0.1 m; the others)."""
    near = BOX.buffer(0.1)
    found = any(d.outline.buffer(0.1).contains(BOX.centroid) for d in detections)
    others = [d.outline for d in detections if not d.outline.intersects(near)]
    return found, others


def run_scene(directory: Path, requests: int = 100, snapshot_frames: int = 1, seed: int = 1) -> dict[str, Any]:
    """Both models on the same frames: the box's detection rate and the false detections per 100
    requests, with where the false ones were."""
    wanted = parse_object_type("foreground")
    background = str(background_picture(directory / f"floor-empty-{snapshot_frames}.png", snapshot_frames))
    detectors = {
        name: ForegroundDetector(view(), {"background": background}, texture_noise=texture_noise)
        for name, texture_noise in (("texture_noise", True), ("plain", False))
    }
    cam = FloorCamera(draw_floor(with_box=True), seed=seed)
    tallies: dict[str, dict[str, Any]] = {
        name: {"found": 0, "false": 0, "false_at": [], "ms": []} for name in detectors
    }
    try:
        for frame in cam.frames(requests):
            for name, det in detectors.items():
                started = time.perf_counter()
                det.observe(frame)
                found, others = score(det.find(FrameAnalysis(frame), wanted))
                tally = tallies[name]
                tally["ms"].append((time.perf_counter() - started) * 1000.0)
                tally["found"] += int(found)
                tally["false"] += len(others)
                tally["false_at"] += [
                    [round(o.centroid.x, 2), round(o.centroid.y, 2), round(o.area, 3)] for o in others
                ]
    finally:
        for det in detectors.values():
            det.close()
    out: dict[str, Any] = {
        "requests": requests,
        "background_frames": snapshot_frames,
        "noise_sigma": NOISE_SIGMA,
        "jitter_px": JITTER_PX,
        "jpeg_quality": JPEG_QUALITY,
    }
    for name, tally in tallies.items():
        out[name] = {
            "box_found_fraction": tally["found"] / requests,
            "false_per_100_requests": 100.0 * tally["false"] / requests,
            "false_at_xy_area": tally["false_at"][:20],
            "observe_and_find_ms_median": float(np.median(tally["ms"])),
        }
    return out


#: Rounds (FloorCamera seeds) and requests a round: full, and --quick.
FULL_ROUNDS, FULL_REQUESTS = 5, 100
QUICK_ROUNDS, QUICK_REQUESTS = 2, 25


def floor_scene(directory: Path, quick: bool) -> dict[str, Any]:
    """`run_scene` over several rounds (each its own frames: noise and jitter), with the background
    picture of one frame and (not --quick) the median of five: per model, the box's detection rate
    and the false detections per 100 requests, median and [min, max] over the rounds, and the
    verdicts against the targets (the box in every request; no false detection)."""
    rounds, requests = (QUICK_ROUNDS, QUICK_REQUESTS) if quick else (FULL_ROUNDS, FULL_REQUESTS)
    out: dict[str, Any] = {
        "what": "a 640x480 camera 3 m up over a tiled floor (0.5 m beige tiles, 8 mm grout), two tape lines and "
        "two printed ArUco markers in the background picture, a 0.45 x 0.35 m brown box placed later; frames with "
        f"lens blur, noise sigma {NOISE_SIGMA}, jitter sigma {JITTER_PX} px, JPEG quality {JPEG_QUALITY}; "
        "each request on a new frame the detector observed; false: a detection that does not touch the box "
        "(within 0.1 m)",
        "rounds": rounds,
        "requests_per_round": requests,
        "targets": {"box_found_fraction": "1.0 in every round", "false_per_100_requests": "0 in every round"},
    }
    for background_frames in (1,) if quick else (1, 5):
        runs = [run_scene(directory, requests, background_frames, seed=seed) for seed in range(1, rounds + 1)]
        entry: dict[str, Any] = {}
        for model in ("texture_noise", "plain"):
            found = [r[model]["box_found_fraction"] for r in runs]
            false = [r[model]["false_per_100_requests"] for r in runs]
            entry[model] = {
                "box_found_fraction": float(np.median(found)),
                "box_found_fraction_spread": [min(found), max(found)],
                "false_per_100_requests": float(np.median(false)),
                "false_per_100_requests_spread": [min(false), max(false)],
                "false_at_xy_area": [xy for r in runs for xy in r[model]["false_at_xy_area"]][:10],
                "observe_and_find_ms_median": float(np.median([r[model]["observe_and_find_ms_median"] for r in runs])),
                "verdict": "met" if min(found) == 1.0 and max(false) == 0.0 else "missed",
            }
        out[f"background_{background_frames}_frames"] = entry
    return out


def floor_lines(scene: dict[str, Any] | None) -> list[str]:
    """The scene's figures as short lines of text (the plot's accuracy panel)."""
    if not scene:
        return []
    lines = [f"foreground (tiled floor, markers, tape; {scene['requests_per_round']} requests x {scene['rounds']}):"]
    for key, entry in scene.items():
        if key.startswith("background_"):
            for model in ("texture_noise", "plain"):
                e = entry[model]
                lines.append(
                    f"  {model} ({key.split('_')[1]}-frame picture): box {e['box_found_fraction']:.2f}, "
                    f"false/100 {e['false_per_100_requests']:.1f} {e['false_per_100_requests_spread']} ({e['verdict']})"
                )
    return [*lines, ""]

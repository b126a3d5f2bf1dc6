"""`foreground` on a real floor's picture: tiles, tape lines and printed ArUco markers (drawn with
OpenCV, cv2.aruco's own marker images) in the empty floor's picture, frames as an MJPEG camera sends
them (lens blur, sensor noise, sub-pixel jitter between frames, JPEG), and a plain cardboard box of
the floor's colour family. The scene is drvs-bench's (drvs_bench.detectors_foreground); the bench
publishes the same figures. And `drvs-camera snapshot --frames N`, the picture's median of N frames."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from drvs_bench.detectors_foreground import (
    BOX,
    FloorCamera,
    background_picture,
    draw_floor,
    score,
    view,
)
from shapely.geometry import Polygon

from drvs.camera.cli import snapshot_main
from drvs.detectors import Frame, FrameAnalysis, parse_object_type
from drvs.detectors.foreground import NOISE_FRAMES, ForegroundDetector
from drvs.sim.scene import write_video

FOREGROUND = parse_object_type("foreground")


@pytest.mark.parametrize("snapshot_frames", [1, 5])
def test_on_a_tiled_floor_with_markers_and_tape_only_the_box_is_found_over_100_requests(
    tmp_path: Path, snapshot_frames: int
) -> None:
    background = str(background_picture(tmp_path / "empty.png", snapshot_frames))
    texture = ForegroundDetector(view(), {"background": background})
    plain = ForegroundDetector(view(), {"background": background}, texture_noise=False)
    cam = FloorCamera(draw_floor(with_box=True), seed=snapshot_frames)
    found = {"texture": 0, "plain": 0}
    false: dict[str, list[tuple[int, float, float]]] = {"texture": [], "plain": []}
    for frame in cam.frames(100):
        for name, det in (("texture", texture), ("plain", plain)):
            det.observe(frame)
            detections = det.find(FrameAnalysis(frame), FOREGROUND)
            box_found, others = score(detections)
            found[name] += box_found
            false[name] += [(frame.sequence, round(o.centroid.x, 2), round(o.centroid.y, 2)) for o in others]
            if name == "texture" and box_found:
                (box,) = [d for d in detections if d.outline.intersects(BOX)]
                assert abs(box.area_m2 - BOX.area) < 0.1 * BOX.area, (frame.sequence, box.area_m2)
        assert texture.noise_learnt == (frame.sequence >= NOISE_FRAMES)
    assert found["texture"] == 100 and false["texture"] == [], (found, false["texture"])
    # The same frames without the texture-aware model: the larger marker is an object in most of them.
    assert found["plain"] == 100 and len(false["plain"]) >= 50, len(false["plain"])
    assert any(abs(x + 0.40) < 0.2 and abs(y - 3.20) < 0.2 for _, x, y in false["plain"]), false["plain"][:5]


def test_on_the_tiled_floor_light_and_shadows_are_not_objects(tmp_path: Path) -> None:
    """The building's light rising 30 % (the yellow tape then clips in the red channel) and falling
    to 70 %, and a cast shadow over the marker and the tape (40-50 % darker, also under changed
    light): nothing is found. Without the edge model the marker alone is an object in most frames."""
    background = str(background_picture(tmp_path / "empty.png"))
    detectors = {
        "texture": ForegroundDetector(view(), {"background": background}),
        "plain": ForegroundDetector(view(), {"background": background}, texture_noise=False),
    }
    cam = FloorCamera(draw_floor(with_box=False), seed=9)
    shadow = Polygon([(-1.5, 2.0), (1.0, 2.0), (1.5, 5.0), (-1.0, 5.0)])
    looks = [{"gain": float(g)} for g in (*np.linspace(1.0, 1.3, 20), *np.linspace(1.3, 0.7, 30))]
    looks += [
        {"gain": g, "shadow": shadow, "darken": d} for d, g in ((0.4, 0.7), (0.5, 0.7), (0.45, 1.0), (0.5, 1.2))
    ] * 3
    found: dict[str, list[tuple[int, float, float]]] = {"texture": [], "plain": []}
    for sequence, look in enumerate(looks, 1):
        frame = Frame(cam.image(**look), 1_700_000_000.0 + sequence / 15, sequence)
        for name, det in detectors.items():
            det.observe(frame)
            found[name] += [
                (sequence, round(d.centroid_xy[0], 2), round(d.centroid_xy[1], 2))
                for d in det.find(FrameAnalysis(frame), FOREGROUND)
            ]
    assert found["texture"] == [], found["texture"]
    assert len({s for s, _, _ in found["plain"]}) >= len(looks) // 2, found["plain"][:5]


def test_snapshot_frames_saves_the_median_of_n_frames(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    empty = FloorCamera(draw_floor(with_box=False), seed=3)
    clean = FloorCamera(draw_floor(with_box=False), seed=3, noise_sigma=0.0, jitter_px=0.0).image().astype(np.float32)
    video = write_video(tmp_path / "empty.avi", [empty.image() for _ in range(7)])
    one, seven = tmp_path / "one.png", tmp_path / "seven.png"
    assert snapshot_main(["--source", str(video), "--out", str(one)]) == 0
    assert snapshot_main(["--source", str(video), "--out", str(seven), "--frames", "7"]) == 0
    assert f"seven.png: 640x480 from {video} (the median of 7 frames)" in capsys.readouterr().out

    def noise(path: Path) -> float:
        image = cv2.imread(str(path))
        assert image is not None and image.shape == (480, 640, 3)
        return float(np.std(image.astype(np.float32) - clean))

    assert noise(seven) < 0.8 * noise(one), (noise(seven), noise(one))
    # More frames than a file that is not looped holds; and a count out of range.
    assert (
        snapshot_main(["--source", str(video), "--out", str(tmp_path / "x.png"), "--frames", "8", "--timeout", "2"])
        == 1
    )
    assert "--frames 8: the source gave 7 and then no new one in 2 s" in capsys.readouterr().err
    for bad in ("0", "101"):
        assert snapshot_main(["--source", str(video), "--out", str(tmp_path / "x.png"), "--frames", bad]) == 2
        assert f"drvs-camera snapshot: --frames: {bad} must be 1-100" in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists()

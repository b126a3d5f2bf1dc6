"""The operator's own ONNX detection models (`model_<name>`, `model_<name>_<class>`).

No trained network ships with DRVS and nothing may be downloaded, so these tests build small ONNX
models with the `onnx` package (drvs_bench.onnx_models) whose graphs compute a YOLO-shaped output
*from the pixels*: for
each class (red, green, blue) the graph thresholds the image's colour channels, finds the bounding
box of the pixels of that colour with reductions, and writes it as one candidate (cx, cy, w, h in
input pixels, then class scores) in the layout under test ([1, 4+nc, N], [1, N, 4+nc] or YOLOv5's
[1, N, 5+nc] with objectness). Such a "network" is exact, so a patch painted at a known place on the
floor of a rendered camera view must come back at that place.

What this proves: the runtime path (onnxruntime loads and runs the file the config names), the
preprocessing (letterbox, BGR->RGB: a red patch is labelled red, not blue; /255: the thresholds are
in 0-1), the decoding of each layout, undoing the letterbox, per-class NMS, mapping the box to the
floor (ground contact and footprint), the field-of-view filter, the class filter, and every
start-time refusal, end to end through real processes.

What it does not prove: that any real trained network (a YOLOv8 or YOLO11 export) detects real
objects well, or how fast such a network runs here: that is a property of the network, measured
with the operator's own model (`drvs-bench detectors`).
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from drvs_bench.onnx_models import (
    COLOUR_CLASSES,
    classifier_model,
    colour_box_model,
    odd_model,
    vector_model,
    yolo_sized_model,
)

from drvs.camera.config import load_config
from drvs.core.errors import FailedPrecondition, InvalidArgument
from drvs.core.filters import object_type
from drvs.core.geometry import FieldOfView, homography_from_pose
from drvs.detectors import CameraView, DetectorUnavailable, Frame, FrameAnalysis
from drvs.detectors.model import ModelDetector, ModelSpec, letterbox, parse_models
from drvs.robot import DrvsClient
from drvs.sim.scene import FloorPatch, record_camera, render_view
from drvs.tools.launch import ManagedProcess, camera_ready, start_server

IMAGE_SIZE = (640, 480)
HOMOGRAPHY = homography_from_pose((0.0, 0.0, 3.0), 90.0, 40.0, 60.0, IMAGE_SIZE)
CLASSES = list(COLOUR_CLASSES)
RED_BGR = (30, 30, 220)
BLUE_BGR = (250, 40, 30)
#: A red and a blue rectangle on the floor (x0, y0, x1, y1), axis-aligned. This camera looks along +y
#: with no roll, so each rectangle's near edge (y0) is one image row, the bottom of its pixel box.
RED = (0.4, 3.0, 1.0, 3.5)
BLUE = (-1.2, 4.0, -0.6, 4.4)


def box_bottom(rect: tuple[float, float, float, float]) -> tuple[tuple[float, float], float, float]:
    """Where the bottom edge of the pixel box around a floor rectangle's image lies on the floor: its
    centre (the ground contact) and its two ends' x. Off the camera's axis the box is wider than the
    near edge (the far corner on the side of the axis sticks out), so this is worked out from the
    rectangle's corners projected into the image, not read off the rectangle."""
    x0, y0, x1, y1 = rect
    corners = np.array([[x0, y0, 1], [x1, y0, 1], [x1, y1, 1], [x0, y1, 1]]) @ np.linalg.inv(HOMOGRAPHY.matrix).T
    pixels = corners[:, :2] / corners[:, 2:]
    (u0, _), (u1, v1) = pixels.min(axis=0), pixels.max(axis=0)
    ends = HOMOGRAPHY.apply([[u0, v1], [u1, v1], [(u0 + u1) / 2, v1]])
    return (float(ends[2][0]), float(ends[2][1])), float(ends[0][0]), float(ends[1][0])


def pixel_error(floor_a: tuple[float, float], floor_b: tuple[float, float]) -> float:
    """How many image pixels apart two floor points are seen by this camera."""
    points = np.array([[*floor_a, 1], [*floor_b, 1]]) @ np.linalg.inv(HOMOGRAPHY.matrix).T
    a, b = points[:, :2] / points[:, 2:]
    return float(np.linalg.norm(a - b))


RED_CONTACT = box_bottom(RED)[0]
BLUE_CONTACT = box_bottom(BLUE)[0]


# --- a camera view and its frames --------------------------------------------------------------


def view(max_range_m: float = 6.0) -> CameraView:
    return CameraView(HOMOGRAPHY, FieldOfView.compute(HOMOGRAPHY, IMAGE_SIZE, max_range_m), IMAGE_SIZE, camera_id="c")


def patches(*extra: FloorPatch) -> list[FloorPatch]:
    return [FloorPatch.rect(*RED, RED_BGR), FloorPatch.rect(*BLUE, BLUE_BGR), *extra]


def analysis(floor: list[FloorPatch], seed: int = 0) -> FrameAnalysis:
    image = render_view(HOMOGRAPHY, IMAGE_SIZE, floor, noise_sigma=2.0, rng=np.random.default_rng(seed))
    return FrameAnalysis(Frame(image, 1000.0, 1))


def detector(path: Path, cam: CameraView | None = None, **spec: Any) -> ModelDetector:
    config = {"path": str(path), "classes": spec.pop("classes", CLASSES), **spec}
    return ModelDetector(cam or view(), {"models": {"colours": config}})


def find(det: ModelDetector, filter_def: str, frame: FrameAnalysis) -> tuple[Any, ...]:
    wanted = object_type(filter_def)
    det.check(wanted)
    return det.narrow(det.find(frame, wanted), wanted)


# --- detection ---------------------------------------------------------------------------------


@pytest.mark.parametrize("layout", ["v8", "v8t", "v5"])
def test_a_patch_comes_back_where_it_lies_on_the_floor(tmp_path: Path, layout: str) -> None:
    det = detector(colour_box_model(tmp_path / "m.onnx", layout))
    found = find(det, "model_colours", analysis(patches()))
    assert sorted(d.label for d in found) == ["blue", "red"]
    for d in found:
        rect = RED if d.label == "red" else BLUE
        contact, left, right = box_bottom(rect)
        # 640x480 letterboxed into 320x320: one input pixel is two of the frame's, and the renderer
        # rounds the patch's outline to whole pixels: each box edge is within 2.5 frame pixels
        # (1-3 cm of floor at 3-4 m from this camera).
        assert pixel_error(d.ground_contact_xy, contact) < 2.5, (d.label, d.ground_contact_xy, contact)
        assert math.dist(d.ground_contact_xy, contact) < 0.04
        # footprint "edge": as wide as the box's bottom edge, a few centimetres deep, just behind it.
        bx0, by0, bx1, by1 = d.bounds
        assert abs(bx0 - left) < 0.03 and abs(bx1 - right) < 0.03, d.bounds
        assert abs(by0 - rect[1]) < 0.04 and 0 < by1 - by0 < 0.15, d.bounds
        assert d.score == pytest.approx((RED_BGR[2] if d.label == "red" else BLUE_BGR[0]) / 255, abs=0.04)
        assert d.filter_def == "model_colours" and d.camera_id == "c"
        # The pixel box is the whole box (the far edge included), not the footprint strip.
        assert d.pixel_box.height > 20


def test_an_input_size_of_the_frame_itself_is_exact_to_a_pixel(tmp_path: Path) -> None:
    det = detector(colour_box_model(tmp_path / "m.onnx", fixed_size=None), input_size=[640, 480])
    assert det.models["colours"].input_size == (640, 480)
    (red,) = find(det, "model_colours_red", analysis(patches()))
    # No scaling: only the renderer's rounding of the patch to whole pixels is left.
    assert pixel_error(red.ground_contact_xy, RED_CONTACT) < 1.5


def test_letterbox_keeps_the_aspect_and_pads_grey() -> None:
    image = np.zeros((480, 640, 3), np.uint8)
    image[:, :, 2] = 255  # red in BGR
    blob, box = letterbox(image, (320, 320))
    assert blob.shape == (1, 3, 320, 320) and blob.dtype == np.float32
    assert (box.scale_x, box.scale_y, box.left, box.top) == (0.5, 0.5, 0, 40)
    assert blob[0, 0, 40:280].min() == 1.0 and blob[0, 2, 40:280].max() == 0.0  # RGB, 0-1
    assert blob[0, :, :40].ravel().tolist() == pytest.approx([114 / 255] * (3 * 40 * 320))


def test_footprint_box_maps_the_whole_box(tmp_path: Path) -> None:
    det = detector(colour_box_model(tmp_path / "m.onnx"), footprint="box")
    (red,) = find(det, "model_colours_red", analysis(patches()))
    _, by0, _, by1 = red.bounds
    # Rows of this camera are lines of constant y: the box's rows map to the rectangle's near and far edges.
    assert abs(by0 - RED[1]) < 0.02 and abs(by1 - RED[3]) < 0.03, red.bounds
    assert pixel_error(red.ground_contact_xy, RED_CONTACT) < 2.5


def test_class_filter_keeps_one_class(tmp_path: Path) -> None:
    det = detector(colour_box_model(tmp_path / "m.onnx"))
    frame = analysis(patches())
    (blue,) = find(det, "model_colours_blue", frame)
    assert blue.label == "blue" and pixel_error(blue.ground_contact_xy, BLUE_CONTACT) < 2.5
    assert find(det, "model_colours_green", frame) == ()
    with pytest.raises(InvalidArgument, match=r"filter_def: model 'colours' has no class 'purple' \(its classes: "
                       r"red, green, blue\)"):  # fmt: skip
        det.check(object_type("model_colours_purple"))
    assert det.kinds() == ("model_colours",)


def test_only_objects_on_the_floor_in_view_are_reported(tmp_path: Path) -> None:
    # The camera sees the floor to 6 m; a red patch at 8-9 m is in the picture but out of range.
    det = detector(colour_box_model(tmp_path / "m.onnx"))
    far = analysis([FloorPatch.rect(-0.5, 8.0, 0.5, 9.0, RED_BGR)])
    assert find(det, "model_colours", far) == ()
    near_range = detector(colour_box_model(tmp_path / "m.onnx"), view(max_range_m=10.0))
    (red,) = find(near_range, "model_colours", far)
    assert pixel_error(red.ground_contact_xy, (0.0, 8.0)) < 2.5


@pytest.mark.parametrize("layout", ["v8", "v5"])
def test_score_threshold_drops_weak_candidates(tmp_path: Path, layout: str) -> None:
    # Scores: red about 220/255 = 0.86, blue about 250/255 = 0.98 (YOLOv5: objectness x class).
    frame = analysis(patches())
    path = colour_box_model(tmp_path / "m.onnx", layout)
    assert sorted(d.label for d in find(detector(path, score_threshold=0.8), "model_colours", frame)) == ["blue", "red"]
    assert [d.label for d in find(detector(path, score_threshold=0.93), "model_colours", frame)] == ["blue"]
    assert find(detector(path, score_threshold=1.0), "model_colours", frame) == ()
    assert find(detector(path, score_threshold=0.0), "model_colours", analysis([])) == ()  # scores of 0: nothing


def test_ms_per_frame_of_the_test_model(tmp_path: Path) -> None:
    """Not a timed target (those are in benchmarks): prints what one frame costs, for the record."""
    det = detector(colour_box_model(tmp_path / "m.onnx", fixed_size=(640, 640)))
    frames = [analysis(patches(), seed) for seed in range(5)]
    started = time.perf_counter()
    for frame in frames:
        assert len(find(det, "model_colours", frame)) == 2
    print(f"colour-box test model, 640x640 input: {(time.perf_counter() - started) / 5 * 1000:.1f} ms per frame")


def test_a_model_shaped_like_an_ultralytics_export_loads_and_runs(tmp_path: Path) -> None:
    """Random weights in a small YOLO's shape: output [1, 84, N] for 80 classes, as `yolo export`
    writes it. Its class scores stay under 0.01, so it finds nothing; a 79-class config is refused."""
    path, _ = yolo_sized_model(tmp_path / "y.onnx", classes=80, size=320)
    coco = [f"class{i}" for i in range(80)]
    det = detector(path, classes=coco)
    model = det.models["colours"]
    assert (model.layout, model.output_shape, model.input_size) == ("[1, 4+nc, N]", (1, 84, 2100), (320, 320))
    assert find(det, "model_colours_class7", analysis(patches())) == ()
    with pytest.raises(FailedPrecondition, match=r"output \[1, 84, 2100\] is not a YOLO detection output for the 79"):
        detector(path, classes=coco[:79])


# --- refusals at start ---------------------------------------------------------------------------


def refused(make: Callable[[Path], Path], match: str, tmp_path: Path, **spec: Any) -> None:
    path = make(tmp_path / "m.onnx")
    with pytest.raises(FailedPrecondition, match=match) as caught:
        detector(path, **spec)
    assert str(path) in str(caught.value)


def test_missing_model_is_refused_at_start(tmp_path: Path) -> None:
    refused(lambda p: p, r"^models: colours: .*m\.onnx: no such file$", tmp_path)


def test_a_directory_is_refused(tmp_path: Path) -> None:
    def directory(p: Path) -> Path:
        p.mkdir()
        return p

    refused(directory, r"^models: colours: .*: not a file$", tmp_path)


def test_garbage_bytes_are_refused(tmp_path: Path) -> None:
    def garbage(p: Path) -> Path:
        p.write_bytes(np.random.default_rng(1).bytes(4096))
        return p

    refused(garbage, r"^models: colours: .*: not an ONNX model onnxruntime can load \(.+\)$", tmp_path)


def test_a_classifier_is_not_a_detection_model(tmp_path: Path) -> None:
    refused(
        classifier_model,
        r"^models: colours: .*: output \[1, 1000\] is not a YOLO detection output for the 3 classes configured: "
        r"expected \[1, 7, N\] \(YOLOv8/YOLO11\), \[1, N, 7\] or \[1, N, 8\] \(YOLOv5\)$",
        tmp_path,
    )


def test_a_model_without_an_image_input_is_refused(tmp_path: Path) -> None:
    refused(vector_model, r"input 'x' has shape \[1, 10\]; expected an image \[1, 3, height, width\]", tmp_path)


@pytest.mark.parametrize(
    ("oddity", "message"),
    [
        ("uint8", r"input 'images' is tensor\(uint8\); expected an image of float or float16$"),
        ("two-inputs", r"has 2 inputs \(images, scale\); a detection model takes one image \[1, 3, H, W\]$"),
        ("int-output", r"output is int64, not boxes and scores \(floats\)$"),
    ],
)
def test_models_that_do_not_take_an_image_or_give_boxes_are_refused(tmp_path: Path, oddity: str, message: str) -> None:
    refused(lambda p: odd_model(p, oddity), message, tmp_path)


@pytest.mark.parametrize("classes", [["red", "green"], ["red", "green", "blue", "cyan", "pink"]])
def test_the_wrong_number_of_classes_is_refused(tmp_path: Path, classes: list[str]) -> None:
    nc = len(classes)
    refused(
        colour_box_model,
        rf"output \[1, 7, 3\] is not a YOLO detection output for the {nc} classes configured: "
        rf"expected \[1, {4 + nc}, N\]",
        tmp_path,
        classes=classes,
    )


def test_too_many_classes_for_a_transposed_output_are_refused(tmp_path: Path) -> None:
    refused(
        lambda p: colour_box_model(p, "v8t"),
        r"output \[1, 3, 7\] is not a YOLO detection output for the 4 classes",
        tmp_path,
        classes=[*CLASSES, "cyan"],
    )


def test_an_input_size_other_than_the_models_fixed_one_is_refused(tmp_path: Path) -> None:
    refused(
        colour_box_model,
        r"input_size \[640, 480\] differs from the model's fixed input 320x320 \(width x height\)",
        tmp_path,
        input_size=[640, 480],
    )


@pytest.mark.parametrize(
    ("models", "message"),
    [
        ([], r"^models: expected a mapping of model name to \{path, classes, \.\.\.\}$"),
        ({"Yolo_v8": {}}, r"^models: model name 'Yolo_v8': 1-24 lower-case letters, digits and '-' \(no '_'"),
        ({"m": {"path": "m.onnx"}}, r"^models: m: classes: missing$"),
        ({"m": {"classes": ["a"]}}, r"^models: m: path: missing$"),
        ({"m": {"path": "", "classes": ["a"]}}, r"^models: m: path: expected the path of an \.onnx file$"),
        ({"m": {"path": "m", "classes": []}}, r"^models: m: classes: expected a non-empty list of class names"),
        ({"m": {"path": "m", "classes": "person"}}, r"^models: m: classes: expected a non-empty list"),
        ({"m": {"path": "m", "classes": ["a b"]}}, r"classes: .*'_ - \.' \('a b' is not\)$"),
        ({"m": {"path": "m", "classes": ["a", "a"]}}, r"^models: m: classes: 'a' appears twice$"),
        ({"m": {"path": "m", "classes": ["a"], "input_size": 8}}, r"^models: m: input_size: '8' must be a whole"),
        ({"m": {"path": "m", "classes": ["a"], "input_size": [640]}}, r"input_size: '\[640\]' must be a whole"),
        ({"m": {"path": "m", "classes": ["a"], "score_threshold": 1.5}},
         r"^models: m: score_threshold: '1.5' must be a number from 0 to 1$"),
        ({"m": {"path": "m", "classes": ["a"], "iou_threshold": "high"}},
         r"^models: m: iou_threshold: 'high' must be a number from 0 to 1$"),
        ({"m": {"path": "m", "classes": ["a"], "footprint": "cube"}},
         r"^models: m: footprint: 'cube' must be one of edge, box$"),
        ({"m": {"path": "m", "classes": ["a"], "treshold": 0.5}},
         r"^models: m: treshold: unknown key \(expected some of: path, classes, input_size, score_threshold, "),
        ({f"m{i}": {"path": "m", "classes": ["a"]} for i in range(9)}, r"^models: 9 models; at most 8 per camera$"),
    ],
)  # fmt: skip
def test_bad_model_config_is_refused_naming_the_key(models: Any, message: str) -> None:
    with pytest.raises(InvalidArgument, match=message):
        parse_models(models)
    with pytest.raises(InvalidArgument, match=message):
        ModelDetector(view(), {"models": models})


def test_unknown_detector_option_is_refused() -> None:
    with pytest.raises(InvalidArgument, match=r"^model: unknown option 'model' \(known: models\)$"):
        ModelDetector(view(), {"model": {}})


def test_no_models_serve_nothing_and_load_nothing() -> None:
    det = ModelDetector(view(), None)
    assert det.kinds() == () and det.models == {}
    # A camera without models never imports onnxruntime (about 15 MB): checked in a fresh interpreter.
    code = (
        "import sys\n"
        "from drvs.camera.node import CameraNode\n"
        "from tests.detectors.test_model_detector import view\n"
        "from drvs.detectors.model import ModelDetector\n"
        "ModelDetector(view(), None)\n"
        "sys.exit('onnxruntime' in sys.modules)\n"
    )
    root = Path(__file__).resolve().parents[2]
    assert subprocess.run([sys.executable, "-c", code], cwd=root, timeout=60).returncode == 0


# --- filter_def syntax -------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("filter_def", "kind", "label"),
    [
        ("model_yolo", "model_yolo", None),
        ("model_yolo_person", "model_yolo", "person"),
        ("model_yolo-v8_traffic_light", "model_yolo-v8", "traffic_light"),
        ("model_7_Cat.2", "model_7", "Cat.2"),
    ],
)
def test_filter_def_names_model_and_class(filter_def: str, kind: str, label: str | None) -> None:
    parsed = object_type(filter_def)
    assert (parsed.prefix, parsed.kind, parsed.key, parsed.params) == ("model", kind, kind, (kind[6:], label))


@pytest.mark.parametrize(
    ("filter_def", "message"),
    [
        ("model", r"^filter_def: 'model' names no model: expected model_<name> or model_<name>_<class>"),
        ("model_", r"^filter_def: model name '' in 'model_' must be 1-24 lower-case letters, digits and '-'$"),
        ("model_Yolo_person", r"^filter_def: model name 'Yolo' in 'model_Yolo_person' must be"),
        ("model_yolo_", r"^filter_def: class '' in 'model_yolo_' must be 1-32 letters, digits and '_ - \.'$"),
        ("model_yolo_a b", r"^filter_def: class 'a b' in 'model_yolo_a b' must be"),
        ("model_" + "y" * 25, r"^filter_def: model name 'y{25}' in"),
    ],
)
def test_malformed_model_filter_def_names_the_part(filter_def: str, message: str) -> None:
    with pytest.raises(InvalidArgument, match=message):
        object_type(filter_def)


# --- the camera's config file --------------------------------------------------------------------


def test_config_file_models_resolve_against_its_directory(tmp_path: Path) -> None:
    cfg = tmp_path / "cam.yaml"
    cfg.write_text(yaml.safe_dump({"id": "c", "source": "0", "homography": "h.yaml",
                                   "models": {"yolo": {"path": "models/y.onnx", "classes": ["person"]}}}))  # fmt: skip
    config = load_config({}, {}, cfg)
    assert config.models == {"yolo": ModelSpec("yolo", tmp_path / "models" / "y.onnx", ("person",))}


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"models": {"yolo": {"path": "y.onnx"}}}, r"^models \(from config .*cam\.yaml\): yolo: classes: missing$"),
        (
            {"models": {"yolo": {"path": "y.onnx", "classes": ["a"]}}, "detectors": "hsv"},
            r"^models: yolo configured, but detectors \(hsv\) leaves out model$",
        ),
    ],
)
def test_bad_models_in_a_config_file(tmp_path: Path, data: dict[str, Any], message: str) -> None:
    cfg = tmp_path / "cam.yaml"
    cfg.write_text(yaml.safe_dump({"id": "c", "source": "0", "homography": "h.yaml", **data}))
    with pytest.raises(InvalidArgument, match=message):
        load_config({}, {}, cfg)


# --- end to end: real processes --------------------------------------------------------------------


async def robot_cli(*args: str) -> ManagedProcess:
    proc = await ManagedProcess.entry_point("robot", "drvs-robot", *args).start()
    assert await proc.wait(timeout=60) == 0, proc.output()
    return proc


@pytest.mark.slow
@pytest.mark.timeout(320)  # its own waits (starts, runs, requests) add up to 290 s
async def test_camera_with_a_model_serves_it_end_to_end(tmp_path: Path) -> None:
    rec = record_camera(tmp_path, "modelcam", HOMOGRAPHY, IMAGE_SIZE, patches(), frames=10)
    colour_box_model(tmp_path / "colours.onnx", "v8")
    cfg = tmp_path / "cam.yaml"
    server, address = await start_server()
    cfg.write_text(yaml.safe_dump({
        "id": "modelcam", "source": str(rec.video), "homography": str(rec.homography_file), "server": address,
        "listen": "127.0.0.1:0", "max_range_m": 6, "detectors": "hsv,model",
        "models": {"colours": {"path": "colours.onnx", "classes": CLASSES}},
    }))  # fmt: skip
    camera = ManagedProcess.entry_point("modelcam", "drvs-camera", "--config", str(cfg), "--log-level", "INFO")
    try:
        await camera.start()
        await camera_ready(camera, "modelcam", timeout=60)
        listing = await robot_cli("cameras", "--server", address, "--json")
        (shown,) = [json.loads(line) for line in listing.lines if line.startswith("{")]
        assert shown["camera_id"] == "modelcam" and sorted(shown["detector_kinds"]) == ["hsv", "model_colours"]
        # (Around the blue patch, all of it in the camera's view: exit 0, nothing unseen.)
        asked = await robot_cli("detect", "--server", address, "--filter", "model_colours_blue", "--roi",
                                "-2,3.5,-0.2,5", "--json")  # fmt: skip
        (report,) = [json.loads(line) for line in asked.lines if line.startswith("{")]
        (blue,) = report["detections"]
        assert blue["label"] == "blue" and blue["score"] == pytest.approx(BLUE_BGR[0] / 255, abs=0.06), blue
        async with DrvsClient(address) as robot:
            (info,) = await robot.cameras()
            assert sorted(info.detector_kinds) == ["hsv", "model_colours"]
            result = await robot.detect("model_colours_red", (-3, 0, 3, 7), timeout_s=20)
            assert result.complete and not result.errors, result
            (red,) = result.detections
            assert red.label == "red" and red.score == pytest.approx(RED_BGR[2] / 255, abs=0.06)
            assert pixel_error(red.ground_contact_xy, RED_CONTACT) < 3  # through video compression
            every = await robot.detect("model_colours", (-3, 0, 3, 7), timeout_s=20)
            assert sorted(d.label for d in every.detections) == ["blue", "red"]
            # A region around the blue patch only, and a class this model does not have.
            only_blue = await robot.detect("model_colours", (-2, 3.5, -0.2, 5), timeout_s=20)
            assert [d.label for d in only_blue.detections] == ["blue"]
            purple = await robot.detect("model_colours_purple", (-3, 0, 3, 7), timeout_s=20)
            (refusal,) = purple.reports
            assert refusal.error_code == "INVALID_ARGUMENT" and refusal.detections == ()
            assert "filter_def: model 'colours' has no class 'purple' (its classes: red, green, blue)" in refusal.error
    finally:
        await camera.stop()
        await server.stop()


async def test_camera_with_a_broken_model_stops_at_start(tmp_path: Path) -> None:
    rec = record_camera(tmp_path, "badcam", HOMOGRAPHY, IMAGE_SIZE, [], frames=2)
    classifier_model(tmp_path / "classifier.onnx")
    cfg = tmp_path / "cam.yaml"
    cfg.write_text(yaml.safe_dump({
        "id": "badcam", "source": str(rec.video), "homography": str(rec.homography_file),
        "server": "127.0.0.1:9", "models": {"imagenet": {"path": "classifier.onnx", "classes": ["a", "b"]}},
    }))  # fmt: skip
    camera = await ManagedProcess.entry_point("badcam", "drvs-camera", "--config", str(cfg)).start()
    try:
        code = await camera.wait(timeout=60)
    finally:
        await camera.stop()
    assert code == 1, camera.output()
    assert (
        f"camera badcam cannot start: models: imagenet: {tmp_path / 'classifier.onnx'}: output [1, 1000] is not a "
        "YOLO detection output for the 2 classes configured" in camera.output()
    ), camera.output()


def test_a_model_whose_file_is_absent_leaves_the_others_serving(tmp_path: Path) -> None:
    present = {"path": str(colour_box_model(tmp_path / "m.onnx")), "classes": CLASSES}
    absent = {"path": str(tmp_path / "gone.onnx"), "classes": ["box"]}
    det = ModelDetector(view(), {"models": {"colours": present, "boxes": absent}})
    assert det.kinds() == ("model_colours",)
    (why,) = det.unavailable_kinds().values()
    assert list(det.unavailable_kinds()) == ["model_boxes"]
    assert str(why) == f"models: boxes: {tmp_path / 'gone.onnx'}: no such file"
    assert sorted(d.label for d in find(det, "model_colours", analysis(patches()))) == ["blue", "red"]
    # Every model absent: the detector is unavailable, each named.
    with pytest.raises(DetectorUnavailable, match=r"^models: boxes: .*gone\.onnx: no such file; models: more: "):
        ModelDetector(view(), {"models": {"boxes": absent, "more": {**absent, "path": str(tmp_path / "x.onnx")}}})

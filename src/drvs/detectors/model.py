"""The operator's own object-detection models: ``model_<name>`` and ``model_<name>_<class>``.

A camera's config file names its models::

    models:
      yolo:
        path: yolov8n.onnx          # relative to the config file
        classes: [person, bicycle, car]   # in the model's output order
        input_size: 640             # or [width, height]; default: the model's own fixed size, else 640
        score_threshold: 0.25       # optional, 0-1
        iou_threshold: 0.45         # optional, 0-1: per-class non-maximum suppression
        footprint: edge             # optional: edge (upright objects) or box (objects lying flat)

Each model is an ONNX file run by onnxruntime on the CPU (one InferenceSession per model, one
intra-op thread: the camera's heavy-detector pool runs frames side by side instead). Its output is
decoded as a YOLO-family detection head, the most common export, in one of three layouts
(`LAYOUTS`):

- ``[1, 4+nc, N]``: ultralytics YOLOv8 / YOLO11 (``yolo export format=onnx``): for each of N
  candidates cx, cy, w, h in input pixels, then nc class scores;
- ``[1, N, 4+nc]``: the same, transposed;
- ``[1, N, 5+nc]``: YOLOv5: cx, cy, w, h, objectness, nc class scores (score = objectness x class).

Only the model's first output is read. Exports with NMS built in (YOLOv10, ``nms=True``, output
``[1, N, 6]``) and models whose boxes are not in input pixels are not decoded. A model's layout
is told from its output shape and the number of classes configured, at start: a shape that fits
none of the three stops the camera with the shape and what was expected.

Frames are letterboxed to the input size (aspect kept, padding grey 114, as ultralytics does),
turned RGB, scaled to 0-1, NCHW float32; boxes are mapped back through the letterbox, kept above
`score_threshold`, then non-maximum suppression runs per class (OpenCV's NMSBoxesBatched).

On the floor: a detection's ground contact is the bottom centre of its box (where an upright object
meets the floor). Its outline, with the default ``footprint: edge``, is the floor under the box's
bottom `FOOTPRINT_ROWS_PX` pixel rows: as wide as the object where it stands, a few centimetres
deep. A 2-D box says where an upright thing touches the floor and how wide it is there, not how
deep it is; mapping the whole box through the floor homography would put a standing person's head
metres behind their feet, or above the horizon where it maps to nothing. ``footprint: box`` maps
the whole box instead, which is right for objects that lie flat on the floor (mats, markers,
spills). Only detections whose ground contact is in the camera's field of view are reported.

Everything that can be wrong with a model is found when the camera starts (`ModelDetector`'s
constructor loads each model and runs it once on a blank frame): a missing or unreadable file, a
file that is not ONNX, an input that is not one image, an output that does not fit the classes.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from drvs.core.errors import FailedPrecondition, InvalidArgument
from drvs.core.model import Detection, PixelBox
from drvs.core.object_types import CLASS_NAME_RE, MODEL_NAME_RE, MODEL_PREFIX, parse_model

from .base import CameraView, Detector, DetectorUnavailable, FrameAnalysis, ObjectType, register

#: Model names (no '_', which separates the class) and class names (which may hold '_': a class
#: is everything after the second '_') are the grammar's, drvs.core.object_types.
PREFIX = MODEL_PREFIX
#: What installs the runtime that runs the models (a base dependency, so only a damaged install lacks it).
ONNXRUNTIME_FIX = "pip install 'onnxruntime>=1.17,<2'"
#: A camera registers at most 16 object types in all; models leave room for the built-ins.
MAX_MODELS = 8
MAX_CLASSES = 1000
DEFAULT_INPUT_SIZE = 640
DEFAULT_SCORE_THRESHOLD = 0.25
DEFAULT_IOU_THRESHOLD = 0.45
FOOTPRINTS = ("edge", "box")
#: The strip of pixel rows at the bottom of a box that `footprint: edge` maps to the floor.
FOOTPRINT_ROWS_PX = 4.0
#: Candidates kept for NMS (the best-scoring), and detections reported per frame, at most.
MAX_CANDIDATES = 10_000
MAX_DETECTIONS = 300
#: onnxruntime threads per model: parallelism comes from the camera's heavy-detector pool.
INTRA_OP_THREADS = 1
LETTERBOX_GREY = 114
SPEC_KEYS = ("path", "classes", "input_size", "score_threshold", "iou_threshold", "footprint")
#: Output layouts decoded, by name: see the module docstring.
LAYOUTS = ("[1, 4+nc, N]", "[1, N, 4+nc]", "[1, N, 5+nc]")


@dataclass(frozen=True)
class ModelSpec:
    """One configured model, validated (its file is only opened by `ModelDetector`)."""

    name: str
    path: Path
    classes: tuple[str, ...]
    #: (width, height); None: the model's own fixed input size, else DEFAULT_INPUT_SIZE square.
    input_size: tuple[int, int] | None = None
    score_threshold: float = DEFAULT_SCORE_THRESHOLD
    iou_threshold: float = DEFAULT_IOU_THRESHOLD
    footprint: str = "edge"


def parse_models(raw: Any, where: str = "models", base: Path | None = None) -> dict[str, ModelSpec]:
    """The `models:` setting, validated: {name: ModelSpec}. Relative paths are resolved against
    `base` (the config file's directory). InvalidArgument names the model and key that is wrong."""
    if raw is None:
        return {}
    if not isinstance(raw, Mapping):
        raise InvalidArgument(f"{where}: expected a mapping of model name to {{path, classes, ...}}")
    if len(raw) > MAX_MODELS:
        raise InvalidArgument(f"{where}: {len(raw)} models; at most {MAX_MODELS} per camera")
    specs: dict[str, ModelSpec] = {}
    for name, spec in raw.items():
        if isinstance(spec, ModelSpec):
            specs[str(name)] = spec
            continue
        if not isinstance(name, str) or not MODEL_NAME_RE.fullmatch(name):
            raise InvalidArgument(
                f"{where}: model name {str(name)[:40]!r}: 1-24 lower-case letters, digits and '-' "
                "(no '_': it separates the class in model_<name>_<class>)"
            )
        specs[name] = _parse_spec(name, spec, f"{where}: {name}", base)
    return specs


def _parse_spec(name: str, spec: Any, where: str, base: Path | None) -> ModelSpec:
    if not isinstance(spec, Mapping):
        raise InvalidArgument(f"{where}: expected a mapping with {', '.join(SPEC_KEYS)}")
    unknown = [str(k) for k in spec if k not in SPEC_KEYS]
    if unknown:
        raise InvalidArgument(f"{where}: {unknown[0][:40]}: unknown key (expected some of: {', '.join(SPEC_KEYS)})")
    for required in ("path", "classes"):
        if required not in spec:
            raise InvalidArgument(f"{where}: {required}: missing")
    raw_path = spec["path"]
    if not isinstance(raw_path, (str, Path)) or not str(raw_path).strip():
        raise InvalidArgument(f"{where}: path: expected the path of an .onnx file")
    path = Path(raw_path)
    if base is not None and not path.is_absolute():
        path = base / path
    classes = spec["classes"]
    listed = isinstance(classes, (list, tuple))
    bad = (
        next((c for c in classes if not isinstance(c, str) or not CLASS_NAME_RE.fullmatch(c)), None) if listed else None
    )
    if not listed or not classes or bad is not None:
        detail = f" ({str(bad)[:40]!r} is not)" if bad is not None else ""
        raise InvalidArgument(
            f"{where}: classes: expected a non-empty list of class names in the model's output order, "
            f"each 1-32 letters, digits and '_ - .'{detail}"
        )
    if len(classes) > MAX_CLASSES:
        raise InvalidArgument(f"{where}: classes: {len(classes)} classes; at most {MAX_CLASSES}")
    seen: set[str] = set()
    for label in classes:
        if label in seen:
            raise InvalidArgument(f"{where}: classes: {label!r} appears twice")
        seen.add(label)
    input_size = _input_size(spec.get("input_size"), f"{where}: input_size")
    score = _fraction(spec.get("score_threshold", DEFAULT_SCORE_THRESHOLD), f"{where}: score_threshold")
    iou = _fraction(spec.get("iou_threshold", DEFAULT_IOU_THRESHOLD), f"{where}: iou_threshold")
    footprint = spec.get("footprint", "edge")
    if footprint not in FOOTPRINTS:
        raise InvalidArgument(f"{where}: footprint: {str(footprint)[:40]!r} must be one of {', '.join(FOOTPRINTS)}")
    return ModelSpec(name, path, tuple(classes), input_size, score, iou, str(footprint))


def _input_size(raw: Any, where: str) -> tuple[int, int] | None:
    if raw is None:
        return None
    values = [raw, raw] if isinstance(raw, int) else raw
    if (
        not isinstance(values, (list, tuple))
        or len(values) != 2
        or not all(isinstance(v, int) and not isinstance(v, bool) and 16 <= v <= 4096 for v in values)
    ):
        raise InvalidArgument(
            f"{where}: {str(raw)[:40]!r} must be a whole number of pixels or [width, height], 16-4096"
        )
    return int(values[0]), int(values[1])


def _fraction(raw: Any, where: str) -> float:
    value = float(raw) if isinstance(raw, (int, float)) and not isinstance(raw, bool) else math.nan
    if not (0.0 <= value <= 1.0):
        raise InvalidArgument(f"{where}: {str(raw)[:40]!r} must be a number from 0 to 1")
    return value


@dataclass(frozen=True)
class Letterbox:
    """How a frame was fitted into the model's input: scale, then padding (left, top)."""

    scale_x: float
    scale_y: float
    left: int
    top: int

    def undo(self, boxes: NDArray[np.float32]) -> NDArray[np.float64]:
        """Boxes (N x 4, x1 y1 x2 y2) in input pixels -> frame pixels."""
        out = boxes.astype(np.float64)
        out[:, [0, 2]] = (out[:, [0, 2]] - self.left) / self.scale_x
        out[:, [1, 3]] = (out[:, [1, 3]] - self.top) / self.scale_y
        return out


def letterbox(image: NDArray[np.uint8], size: tuple[int, int]) -> tuple[NDArray[np.float32], Letterbox]:
    """A BGR frame as the model's input: fitted into `size` (w, h) with its aspect kept, padded grey
    (114) on both sides, RGB, 0-1, NCHW float32."""
    if image.ndim == 2:
        image = np.asarray(cv2.cvtColor(image, cv2.COLOR_GRAY2BGR), dtype=np.uint8)
    h, w = image.shape[:2]
    width, height = size
    r = min(width / w, height / h)
    new_w, new_h = max(1, round(w * r)), max(1, round(h * r))
    resized = image if (new_w, new_h) == (w, h) else cv2.resize(image, (new_w, new_h), interpolation=cv2.INTER_LINEAR)
    left, top = (width - new_w) // 2, (height - new_h) // 2
    grey = (LETTERBOX_GREY,) * 3
    padded = cv2.copyMakeBorder(
        resized, top, height - new_h - top, left, width - new_w - left, cv2.BORDER_CONSTANT, value=grey
    )
    blob = np.asarray(cv2.dnn.blobFromImage(padded, scalefactor=1.0 / 255.0, swapRB=True), dtype=np.float32)
    return blob, Letterbox(new_w / w, new_h / h, left, top)


@dataclass
class LoadedModel:
    """A model's session and what was learnt about it at start."""

    spec: ModelSpec
    session: Any  # onnxruntime.InferenceSession
    input_name: str
    input_dtype: type[np.floating[Any]]
    input_size: tuple[int, int]
    #: One of LAYOUTS.
    layout: str
    output_shape: tuple[int, ...]


@dataclass(frozen=True)
class Boxes:
    """Decoded, suppressed detections in frame pixels."""

    xyxy: NDArray[np.float64]
    scores: NDArray[np.float32]
    class_ids: NDArray[np.int64]


def _fail(spec: ModelSpec, reason: str) -> FailedPrecondition:
    return FailedPrecondition(f"models: {spec.name}: {spec.path}: {reason}")


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return (text[0] if text else type(exc).__name__)[:300]


def load_model(spec: ModelSpec) -> LoadedModel:
    """Open, check and run a model once; FailedPrecondition names the path and what is wrong."""
    try:
        import onnxruntime as ort  # only cameras with models pay for onnxruntime
    except ImportError as exc:
        raise DetectorUnavailable(
            "model", f"models: {spec.name}: onnxruntime does not import ({exc})", ONNXRUNTIME_FIX
        ) from None
    path = spec.path
    if not path.exists():
        # Not the configuration's fault, nor the camera's: the file is not there (yet). The camera
        # serves its other detectors, and says so.
        raise DetectorUnavailable("model", f"models: {spec.name}: {path}: no such file")
    if not path.is_file():
        raise _fail(spec, "not a file")
    try:
        with path.open("rb") as f:
            f.read(1)
    except OSError as exc:
        raise _fail(spec, f"cannot read it ({exc.strerror or exc})") from None
    options = ort.SessionOptions()
    options.intra_op_num_threads = INTRA_OP_THREADS
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.log_severity_level = 3  # errors only: the camera's log says what matters
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    try:
        session = ort.InferenceSession(str(path), sess_options=options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime's own exception types (InvalidProtobuf, Fail, ...)
        raise _fail(spec, f"not an ONNX model onnxruntime can load ({_first_line(exc)})") from None
    inputs = session.get_inputs()
    if len(inputs) != 1:
        names = ", ".join(i.name for i in inputs)
        raise _fail(spec, f"has {len(inputs)} inputs ({names}); a detection model takes one image [1, 3, H, W]")
    source = inputs[0]
    shape = list(source.shape)
    dtypes: dict[str, type[np.floating[Any]]] = {"tensor(float)": np.float32, "tensor(float16)": np.float16}
    if source.type not in dtypes:
        raise _fail(spec, f"input {source.name!r} is {source.type}; expected an image of float or float16")

    def fixed(dim: Any) -> int | None:
        return dim if isinstance(dim, int) and dim > 0 else None

    if len(shape) != 4 or fixed(shape[0]) not in (None, 1) or fixed(shape[1]) not in (None, 3):
        raise _fail(spec, f"input {source.name!r} has shape {_shape(shape)}; expected an image [1, 3, height, width]")
    model_size = (fixed(shape[3]), fixed(shape[2]))
    if model_size[0] is not None and model_size[1] is not None:
        fixed_size = (model_size[0], model_size[1])
        if spec.input_size is not None and spec.input_size != fixed_size:
            raise _fail(
                spec,
                f"input_size {list(spec.input_size)} differs from the model's fixed input "
                f"{fixed_size[0]}x{fixed_size[1]} (width x height)",
            )
        size = fixed_size
    elif model_size[0] is not None or model_size[1] is not None:
        size = spec.input_size or (model_size[0] or DEFAULT_INPUT_SIZE, model_size[1] or DEFAULT_INPUT_SIZE)
    else:
        size = spec.input_size or (DEFAULT_INPUT_SIZE, DEFAULT_INPUT_SIZE)
    blank = np.full((1, 3, size[1], size[0]), LETTERBOX_GREY / 255.0, dtype=dtypes[source.type])
    try:
        output = np.asarray(session.run(None, {source.name: blank})[0])
    except Exception as exc:
        raise _fail(spec, f"fails on a {size[0]}x{size[1]} image ({_first_line(exc)})") from None
    if not np.issubdtype(output.dtype, np.floating):
        raise _fail(spec, f"output is {output.dtype}, not boxes and scores (floats)")
    layout = _layout(output.shape, len(spec.classes))
    if layout is None:
        nc = len(spec.classes)
        raise _fail(
            spec,
            f"output {_shape(list(output.shape))} is not a YOLO detection output for the {nc} classes "
            f"configured: expected [1, {4 + nc}, N] (YOLOv8/YOLO11), [1, N, {4 + nc}] or [1, N, {5 + nc}] (YOLOv5)",
        )
    return LoadedModel(spec, session, source.name, dtypes[source.type], size, layout, tuple(output.shape))


def _shape(shape: Sequence[Any]) -> str:
    return "[" + ", ".join(str(d) if d is not None else "?" for d in shape) + "]"


def _layout(shape: tuple[int, ...], nc: int) -> str | None:
    """Which of LAYOUTS an output of this shape is, for nc classes (None: none)."""
    if len(shape) != 3 or shape[0] != 1:
        return None
    _, a, b = shape
    if a == 4 + nc and b >= 1:
        return LAYOUTS[0]  # ultralytics' own export; wins when N happens to equal 4+nc too
    if b == 4 + nc and a >= 1:
        return LAYOUTS[1]
    if b == 5 + nc and a >= 1:
        return LAYOUTS[2]
    return None


def decode(model: LoadedModel, output: NDArray[Any], box: Letterbox, image_size: tuple[int, int]) -> Boxes:
    """A YOLO output (batch of one) -> boxes in frame pixels, above the threshold, after per-class NMS."""
    rows = np.asarray(output[0], dtype=np.float32)
    if model.layout == LAYOUTS[0]:
        rows = rows.T
    # YOLOv5: a class's score is objectness x the class's probability.
    class_scores = rows[:, 5:] * rows[:, 4:5] if model.layout == LAYOUTS[2] else rows[:, 4:]
    class_ids = class_scores.argmax(axis=1)
    scores = class_scores[np.arange(len(rows)), class_ids]
    keep = np.flatnonzero(np.isfinite(scores) & (scores >= model.spec.score_threshold) & (scores > 0))
    if len(keep) > MAX_CANDIDATES:
        keep = keep[np.argpartition(-scores[keep], MAX_CANDIDATES)[:MAX_CANDIDATES]]
    empty = Boxes(np.zeros((0, 4)), np.zeros(0, np.float32), np.zeros(0, np.int64))
    if len(keep) == 0:
        return empty
    cx, cy, w, h = (rows[keep, i] for i in range(4))
    xyxy = box.undo(np.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], axis=1))
    width, height = image_size
    xyxy[:, [0, 2]] = xyxy[:, [0, 2]].clip(0, width)
    xyxy[:, [1, 3]] = xyxy[:, [1, 3]].clip(0, height)
    sizes = xyxy[:, 2:] - xyxy[:, :2]
    good = np.flatnonzero(np.all(np.isfinite(xyxy), axis=1) & (sizes[:, 0] > 0) & (sizes[:, 1] > 0))
    if len(good) == 0:
        return empty
    xyxy, sizes, keep = xyxy[good], sizes[good], keep[good]
    xywh = [[float(x), float(y), float(w_), float(h_)] for (x, y), (w_, h_) in zip(xyxy[:, :2], sizes, strict=True)]
    chosen = cv2.dnn.NMSBoxesBatched(
        xywh,
        [float(s) for s in scores[keep]],
        [int(c) for c in class_ids[keep]],
        0.0,  # kept above the threshold already (OpenCV's test is strict: a threshold of 1 would keep nothing)
        model.spec.iou_threshold,
    )
    index = np.asarray(chosen, dtype=np.int64).reshape(-1)[:MAX_DETECTIONS]
    return Boxes(xyxy[index], scores[keep][index], class_ids[keep][index].astype(np.int64))


@register
class ModelDetector(Detector):
    """The operator's ONNX object-detection models (YOLO-family outputs), one session per model."""

    prefix = "model"
    example = "model_yolo_person"
    heavy = True

    def __init__(self, view: CameraView, options: Mapping[str, Any] | None = None) -> None:
        super().__init__(view, options)
        self.refuse_unknown_options("models")
        self.specs = parse_models(self.options.get("models"))
        self.models: dict[str, LoadedModel] = {}
        #: Configured models whose file is absent (or that onnxruntime cannot run here), and why:
        #: the others serve. All of them absent: the detector is unavailable.
        self.missing: dict[str, DetectorUnavailable] = {}
        try:
            for name, spec in self.specs.items():
                try:
                    self.models[name] = load_model(spec)
                except DetectorUnavailable as exc:
                    self.missing[name] = exc
        except BaseException:
            self.close()
            raise
        if self.missing and not self.models:
            first = next(iter(self.missing.values()))
            raise (
                DetectorUnavailable("model", "; ".join(e.reason for e in self.missing.values()), first.fix)
                if len(self.missing) > 1
                else first
            )

    @classmethod
    def parse(cls, filter_def: str) -> ObjectType:
        return parse_model(filter_def)

    def kinds(self) -> tuple[str, ...]:
        return tuple(PREFIX + name for name in self.models)

    def unavailable_kinds(self) -> dict[str, DetectorUnavailable]:
        return {PREFIX + name: why for name, why in self.missing.items()}

    def check(self, object_type: ObjectType) -> None:
        name, label = object_type.params
        model = self.models.get(name)
        if model is None:
            raise InvalidArgument(
                f"filter_def: this camera has no model {name!r} (its models: {', '.join(self.models) or 'none'})"
            )
        if label is not None and label not in model.spec.classes:
            classes = model.spec.classes
            shown = ", ".join(classes[:20]) + (f", ... ({len(classes)} in all)" if len(classes) > 20 else "")
            raise InvalidArgument(f"filter_def: model {name!r} has no class {label!r} (its classes: {shown})")

    def infer(self, model: LoadedModel, image: NDArray[np.uint8]) -> Boxes:
        """Run one model on one BGR frame: letterbox, inference, decoding, NMS."""
        blob, box = letterbox(image, model.input_size)
        output = model.session.run(None, {model.input_name: blob.astype(model.input_dtype, copy=False)})[0]
        return decode(model, np.asarray(output), box, (int(image.shape[1]), int(image.shape[0])))

    def find(self, analysis: FrameAnalysis, object_type: ObjectType) -> tuple[Detection, ...]:
        frame = analysis.frame
        self.view.check_frame(frame)
        name, _ = object_type.params
        model = self.models[name]
        boxes = self.infer(model, frame.image)
        found: list[Detection] = []
        # Boxes are in pixel-edge coordinates (pixel i spans [i, i+1), as YOLO's are); the homography
        # takes OpenCV's, where pixel i's centre is at i: half a pixel less.
        for (x1, y1, x2, y2), score, class_id in zip(boxes.xyxy - 0.5, boxes.scores, boxes.class_ids, strict=True):
            # The bottom edge of the box's lowest row: where an upright object meets the floor.
            contact = ((x1 + x2) / 2.0, min(y2, self.view.image_size[1] - 1.0))
            if not self.view.in_view(*contact):
                continue
            if model.spec.footprint == "box":
                outline = np.array([(x1, y1), (x2, y1), (x2, y2), (x1, y2)], dtype=np.float64)
            else:
                top = max(y1, y2 - FOOTPRINT_ROWS_PX)
                outline = np.array([(x1, top), (x2, top), (x2, y2), (x1, y2)], dtype=np.float64)
            detection = self.view.detection(
                outline,
                object_type.key,
                frame.capture_time,
                score=float(score),
                area_px=float((x2 - x1) * (y2 - y1)),
                contact_px=contact,
                label=model.spec.classes[int(class_id)],
            )
            if detection is None:
                continue
            left, upper = math.floor(x1 + 0.5), math.floor(y1 + 0.5)
            pixel_box = PixelBox(left, upper, max(1, math.ceil(x2 + 0.5) - left), max(1, math.ceil(y2 + 0.5) - upper))
            found.append(dataclasses.replace(detection, pixel_box=pixel_box))
        found.sort(key=lambda d: d.score, reverse=True)
        return tuple(found)

    def narrow(self, found: tuple[Detection, ...], object_type: ObjectType) -> tuple[Detection, ...]:
        _, label = object_type.params
        if label is None:
            return found
        return tuple(d for d in found if d.label == label)

    def close(self) -> None:
        self.models.clear()

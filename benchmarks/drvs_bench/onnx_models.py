"""Small ONNX detection models built with the `onnx` package, for tests and benchmarks of the
`model_<name>` detector (drvs.detectors.model). Nothing here is a trained network.

- `colour_box_model`: a YOLO-shaped "detector" whose graph finds red, green and blue patches from
  the pixels (thresholds on the RGB channels, then the bounding box of each colour by reductions)
  and writes one candidate per class (cx, cy, w, h in input pixels, then class scores) in the
  layout asked for. It is exact, so a patch at a known floor position must come back there: it
  checks the runtime path, preprocessing, decoding, letterbox undo and floor mapping, not how well
  a real network detects real objects.
- `yolo_sized_model`: random convolution weights in the shape of a small YOLO (a strided conv
  backbone, three heads at strides 8, 16 and 32, output [1, 4+nc, 8400] at 640), about as much
  arithmetic as a YOLOv8n: what a frame of a real small model costs on this CPU. It detects nothing
  (class scores are held near 0).
- `classifier_model`, `vector_model`: models that are not detection models, to be refused.

`onnx` is a development dependency (the `dev` extra): it is imported here, so only tests and
benchmarks import this module.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

#: The classes `colour_box_model` detects, in output order.
COLOUR_CLASSES = ("red", "green", "blue")


class _Graph:
    """A tiny onnx.helper builder that names intermediate values."""

    def __init__(self) -> None:
        self.nodes: list[onnx.NodeProto] = []
        self.initializers: list[onnx.TensorProto] = []
        self._n = 0

    def name(self) -> str:
        self._n += 1
        return f"v{self._n}"

    def const(self, value: Any, dtype: Any = np.float32) -> str:
        name = self.name()
        self.initializers.append(numpy_helper.from_array(np.asarray(value, dtype=dtype), name))
        return name

    def op(self, op_type: str, *inputs: str, **attrs: Any) -> str:
        out = self.name()
        self.nodes.append(helper.make_node(op_type, list(inputs), [out], **attrs))
        return out


def colour_box_model(path: Path, layout: str = "v8", *, fixed_size: tuple[int, int] | None = (320, 320)) -> Path:
    """A YOLO-shaped "detector" of red, green and blue patches (see the module docstring).

    layout: "v8" [1, 4+nc, nc], "v8t" [1, nc, 4+nc], "v5" [1, nc, 5+nc]. fixed_size: the input's
    (width, height), or None for dynamic height and width.
    """
    g = _Graph()
    channels = [g.op("Gather", "images", g.const(i, np.int64), axis=1) for i in range(3)]  # R, G, B: [1, H, W]
    shape = g.op("Shape", channels[0])
    height = g.op("Cast", g.op("Gather", shape, g.const(1, np.int64)), to=TensorProto.FLOAT)
    width = g.op("Cast", g.op("Gather", shape, g.const(2, np.int64)), to=TensorProto.FLOAT)
    xs = g.op("Range", g.const(0.0), width, g.const(1.0))
    ys = g.op("Range", g.const(0.0), height, g.const(1.0))
    half, low, big, one = g.const(0.5), g.const(0.3), g.const(1e6), g.const(1.0)
    nc = 3
    columns = []
    for k in range(3):
        others = [channels[j] for j in range(3) if j != k]
        mask = g.op("Cast", g.op("And", g.op("Greater", channels[k], half), g.op("Less", g.op("Max", *others), low)),
                    to=TensorProto.FLOAT)  # fmt: skip
        col = g.op("ReduceMax", mask, axes=[1], keepdims=0)  # [1, W]: does column x hold this colour?
        row = g.op("ReduceMax", mask, axes=[2], keepdims=0)  # [1, H]

        def extent(hits: str, positions: str) -> tuple[str, str]:
            last = g.op("ReduceMax", g.op("Mul", hits, positions), keepdims=0)
            misses = g.op("Mul", g.op("Sub", one, hits), big)
            first = g.op("ReduceMin", g.op("Add", g.op("Mul", hits, positions), misses), keepdims=0)
            return first, last

        x1, x2 = extent(col, xs)
        y1, y2 = extent(row, ys)
        # The score: the colour's brightest value inside the patch (0-1), so thresholds have something to cut.
        score = g.op("ReduceMax", g.op("Mul", mask, channels[k]), keepdims=0)
        # Pixel i spans [i, i+1): the box runs from the first hit to one past the last.
        w = g.op("Add", g.op("Sub", x2, x1), one)
        h = g.op("Add", g.op("Sub", y2, y1), one)
        cx = g.op("Add", x1, g.op("Mul", w, half))
        cy = g.op("Add", y1, g.op("Mul", h, half))
        if layout == "v5":  # objectness, then class probabilities
            values = [cx, cy, w, h, score, *[one if j == k else g.const(0.0) for j in range(nc)]]
        else:
            values = [cx, cy, w, h, *[score if j == k else g.const(0.0) for j in range(nc)]]
        items = [g.op("Reshape", v, g.const([1], np.int64)) for v in values]
        columns.append(g.op("Reshape", g.op("Concat", *items, axis=0), g.const([-1, 1], np.int64)))
    stacked = g.op("Unsqueeze", g.op("Concat", *columns, axis=1), g.const([0], np.int64))  # [1, 4+nc, N]
    output = stacked if layout == "v8" else g.op("Transpose", stacked, perm=[0, 2, 1])
    g.nodes.append(helper.make_node("Identity", [output], ["output0"]))
    dims: list[Any] = [1, 3, fixed_size[1], fixed_size[0]] if fixed_size else [1, 3, "height", "width"]
    graph = helper.make_graph(
        g.nodes,
        "colour_boxes",
        [helper.make_tensor_value_info("images", TensorProto.FLOAT, dims)],
        [helper.make_tensor_value_info("output0", TensorProto.FLOAT, [1, "rows", "columns"])],
        g.initializers,
    )
    return save(graph, path)


def classifier_model(path: Path) -> Path:
    """An image classifier: [1, 3, 224, 224] -> [1, 1000] (not a detection model)."""
    g = _Graph()
    pooled = g.op("Flatten", g.op("GlobalAveragePool", "images"))
    logits = g.op("MatMul", pooled, g.const(np.ones((3, 1000))))
    g.nodes.append(helper.make_node("Identity", [logits], ["logits"]))
    graph = helper.make_graph(
        g.nodes,
        "classifier",
        [helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, 224, 224])],
        [helper.make_tensor_value_info("logits", TensorProto.FLOAT, [1, 1000])],
        g.initializers,
    )
    return save(graph, path)


def vector_model(path: Path) -> Path:
    """A model whose input is a [1, 10] vector, not an image."""
    node = helper.make_node("Identity", ["x"], ["y"])
    graph = helper.make_graph(
        [node],
        "vector",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 10])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 10])],
    )
    return save(graph, path)


def odd_model(path: Path, oddity: str) -> Path:
    """Image-ish models a detector must refuse: "uint8" (a uint8 image input), "two-inputs" (an image
    and a second input), "int-output" (a [1, 7, 3] output of int64)."""
    image_type = TensorProto.UINT8 if oddity == "uint8" else TensorProto.FLOAT
    inputs = [helper.make_tensor_value_info("images", image_type, [1, 3, 32, 32])]
    if oddity == "two-inputs":
        inputs.append(helper.make_tensor_value_info("scale", TensorProto.FLOAT, [1]))
    g = _Graph()
    pooled = g.op("GlobalAveragePool", g.op("Cast", "images", to=TensorProto.FLOAT))  # [1, 3, 1, 1]
    shaped = g.op("Reshape", g.op("Tile", pooled, g.const([1, 7, 1, 1], np.int64)), g.const([1, 7, 3], np.int64))
    out_type = TensorProto.INT64 if oddity == "int-output" else TensorProto.FLOAT
    g.nodes.append(helper.make_node("Cast", [shaped], ["output0"], to=out_type))
    graph = helper.make_graph(
        g.nodes, "odd", inputs, [helper.make_tensor_value_info("output0", out_type, [1, 7, 3])], g.initializers
    )
    return save(graph, path)


def save(graph: onnx.GraphProto, path: Path) -> Path:
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def yolo_sized_model(path: Path, classes: int = 80, size: int = 640, seed: int = 0) -> tuple[Path, int]:
    """Random weights in the shape of a small YOLO: a stride-2 conv backbone (SiLU), heads at strides
    8, 16 and 32, output [1, 4+classes, N] (N = 8400 at 640), class scores at most 0.01 (so nothing
    is detected and decoding costs what a quiet scene costs). Returns the path and its multiply-adds
    per frame (a YOLOv8n is about 4.4 G, 8.7 GFLOPs)."""
    rng = np.random.default_rng(seed)
    g = _Graph()
    macs = 0

    def conv(x: str, cin: int, cout: int, side: int, k: int = 3, stride: int = 1, act: bool = True) -> str:
        nonlocal macs
        weight = rng.normal(0.0, (2.0 / (cin * k * k)) ** 0.5, (cout, cin, k, k))
        y = g.op("Conv", x, g.const(weight), g.const(np.zeros(cout)), kernel_shape=[k, k],
                 strides=[stride, stride], pads=[k // 2] * 4)  # fmt: skip
        macs += (side // stride) ** 2 * cout * cin * k * k
        return g.op("Mul", y, g.op("Sigmoid", y)) if act else y

    x, side, channels = "images", size, 3
    features = []
    for stage, width in enumerate((16, 32, 64, 128, 256)):
        x = conv(x, channels, width, side, stride=2)
        side, channels = side // 2, width
        if stage >= 1:
            for _ in range(3):
                x = conv(x, channels, channels, side)
        if stage >= 2:
            features.append((x, channels, side))
    outputs = 4 + classes
    scale = np.concatenate([[size, size, size / 4, size / 4], np.full(classes, 0.01)]).reshape(1, outputs, 1)
    heads = []
    for feature, cin, fside in features:
        y = conv(feature, cin, 64, fside)
        y = conv(y, 64, 64, fside)
        y = conv(y, 64, outputs, fside, k=1, act=False)
        flat = g.op("Reshape", y, g.const([1, outputs, -1], np.int64))
        heads.append(g.op("Mul", g.op("Sigmoid", flat), g.const(scale)))
    g.nodes.append(helper.make_node("Concat", heads, ["output0"], axis=2))
    graph = helper.make_graph(
        g.nodes,
        "yolo_sized",
        [helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, size, size])],
        [helper.make_tensor_value_info("output0", TensorProto.FLOAT, [1, outputs, "anchors"])],
        g.initializers,
    )
    return save(graph, path), macs

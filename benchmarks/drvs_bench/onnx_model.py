"""A synthetic YOLO-shaped ONNX detection model for the detectors benchmark: nothing downloaded.

A convolutional backbone (3x3 convolutions, stride-2 stages to 1/32) with three 1x1 heads at 1/8,
1/16 and 1/32 of a 640x640 input, concatenated into ultralytics YOLOv8's output layout
[1, 4 + classes, 8400]: the same input, output and decoding as a real export, and a compute of
the same order as YOLOv8n (`flops` says how much). Its weights are random (fixed seed): it
costs what such a network costs, and finds nothing (class scores are pushed to ~0), so it
measures a model's price, not its accuracy.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

INPUT = 640
#: (output channels, stride, repeats of a stride-1 convolution after it) per stage.
STAGES = ((16, 2, 0), (32, 2, 1), (64, 2, 2), (128, 2, 2), (256, 2, 2))
HEAD_STAGES = (2, 3, 4)  # 1/8, 1/16, 1/32


def build_model(path: Path, classes: int = 3, seed: int = 0, width: float = 1.0) -> dict[str, Any]:
    """Write the model (`width` scales every stage's channels: 0.25 for a smoke run); returns what
    it is (input, output shape, GFLOPs: multiply-adds x 2)."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    rng = np.random.default_rng(seed)
    nodes: list[Any] = []
    inits: list[Any] = []
    counter = [0]
    flops = 0

    def name() -> str:
        counter[0] += 1
        return f"t{counter[0]}"

    def const(value: Any) -> str:
        n = name()
        inits.append(numpy_helper.from_array(np.asarray(value, dtype=np.float32), n))
        return n

    def conv(x: str, cin: int, cout: int, k: int, stride: int, size: int, relu: bool = True, bias: float = 0.0) -> str:
        nonlocal flops
        w = const(rng.normal(0.0, np.sqrt(2.0 / (cin * k * k)), (cout, cin, k, k)))
        b = const(np.full(cout, bias))
        out = name()
        nodes.append(helper.make_node("Conv", [x, w, b], [out], kernel_shape=[k, k], strides=[stride, stride],
                                      pads=[k // 2] * 4))  # fmt: skip
        flops += 2 * cin * cout * k * k * (size // stride) ** 2
        if not relu:
            return out
        act = name()
        nodes.append(helper.make_node("Relu", [out], [act]))
        return act

    x, cin, size = "images", 3, INPUT
    heads: list[str] = []
    outputs = 4 + classes
    for i, (channels, stride, repeats) in enumerate(STAGES):
        cout = max(4, round(channels * width))
        x = conv(x, cin, cout, 3, stride, size)
        size //= stride
        cin = cout
        for _ in range(repeats):
            x = conv(x, cin, cin, 3, 1, size)
        if i in HEAD_STAGES:
            # Class logits far below zero: after the sigmoid every score is ~0, nothing is kept.
            h = conv(x, cin, outputs, 1, 1, size, relu=False, bias=-30.0)
            flat = name()
            nodes.append(helper.make_node("Reshape", [h, const_int(inits, name(), [1, outputs, -1])], [flat]))
            heads.append(flat)
    cat, sig, out = name(), name(), "output0"
    nodes.append(helper.make_node("Concat", heads, [cat], axis=2))
    nodes.append(helper.make_node("Sigmoid", [cat], [sig]))
    scale = np.ones((1, outputs, 1), dtype=np.float32)
    scale[0, :4, 0] = INPUT  # boxes in input pixels, as an export gives them
    nodes.append(helper.make_node("Mul", [sig, const(scale)], [out]))
    anchors = sum((INPUT // 2 ** (s + 1)) ** 2 for s in HEAD_STAGES)
    graph = helper.make_graph(
        nodes,
        "bench_yolo_shaped",
        [helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, INPUT, INPUT])],
        [helper.make_tensor_value_info(out, TensorProto.FLOAT, [1, outputs, anchors])],
        inits,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return {
        "model": "synthetic YOLOv8-shaped network (drvs_bench.onnx_model), random weights, finds nothing",
        "width": width,
        "input": [1, 3, INPUT, INPUT],
        "output": [1, outputs, anchors],
        "gflops": round(flops / 1e9, 2),
        "for_comparison": "YOLOv8n at 640: 8.7 GFLOPs (ultralytics)",
    }


def const_int(inits: list[Any], name: str, value: list[int]) -> str:
    from onnx import numpy_helper

    inits.append(numpy_helper.from_array(np.asarray(value, dtype=np.int64), name))
    return name

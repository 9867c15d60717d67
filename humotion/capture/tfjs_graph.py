"""Run the convolutional part of a TensorFlow.js graph model (model.json + weight shards) with torch.

The MoveNet pose models humotion ships (humotion/assets/capture/movenet_*; see MODEL_CARD.md) come as
TensorFlow.js graph models: a TensorFlow GraphDef written as JSON, plus the weights in a binary file
(float16 where the manifest says so). TensorFlow itself is a large dependency that humotion does not
otherwise need, and ONNX converters need it too, so this module reads that format and evaluates the
nodes that lead to the requested outputs, for the operations a MobileNet/FPN trunk uses (convolutions
with their fused bias and activation, depthwise convolutions, elementwise arithmetic, bilinear
resizing, concatenation, sigmoid). The models' own decoding steps (arg-max, gather, ...) are left
out: `humotion.capture.movenet` decodes the heads' outputs in numpy.

Tensors run in torch's NCHW layout; the graph's NHWC axes and per-channel constants are mapped onto
it. TensorFlow's "SAME" padding (asymmetric for even kernels or strides) is reproduced exactly.
"""

from __future__ import annotations

import base64
import json
import math
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

_DTYPES = {"float32": np.float32, "int32": np.int32}


def load_weights(model_json: dict, folder: Path) -> dict[str, np.ndarray]:
    """{name: array} of every weight in the model's manifest, each of any shape (the manifest's:
    (kh, kw, in, out) for a convolution), float16 ones widened to float32."""
    weights = {}
    for group in model_json["weightsManifest"]:
        data = b"".join((folder / path).read_bytes() for path in group["paths"])
        offset = 0
        for spec in group["weights"]:
            shape = [int(s) for s in spec["shape"]]
            count = int(np.prod(shape)) if shape else 1
            quantization = spec.get("quantization")
            if quantization is not None and quantization.get("dtype") == "float16":
                raw = np.frombuffer(data, np.float16, count, offset)
                offset += 2 * count
                value = raw.astype(np.float32)
            elif quantization is not None:
                raise ValueError(f"weight {spec['name']}: quantisation {quantization} is not supported")
            else:
                dtype = _DTYPES[spec["dtype"]]
                value = np.frombuffer(data, dtype, count, offset).copy()
                offset += value.itemsize * count
            weights[spec["name"]] = value.reshape(shape)
    return weights


def _attr(node: dict, key: str, default=None):
    value = node.get("attr", {}).get(key)
    if value is None:
        return default
    if "s" in value:
        return base64.b64decode(value["s"]).decode()
    if "list" in value:
        items = value["list"]
        if "i" in items:
            return [int(i) for i in items["i"]]
        if "s" in items:
            return [base64.b64decode(s).decode() for s in items["s"]]
        return []
    if "i" in value:
        return int(value["i"])
    if "f" in value:
        return float(value["f"])
    if "b" in value:
        return bool(value["b"])
    return value


def _same_padding(size: int, kernel: int, stride: int, dilation: int) -> tuple[int, int]:
    """TensorFlow's SAME padding (before, after) along one axis."""
    effective = (kernel - 1) * dilation + 1
    total = max((math.ceil(size / stride) - 1) * stride + effective - size, 0)
    return total // 2, total - total // 2


class TFJSGraph:
    """A TensorFlow.js graph model evaluated up to chosen nodes; see the module docstring.

    path: the model.json (its weight files beside it). outputs: names of the nodes to compute.
    Call with an NHWC float32 or int32 tensor (the model's input) for {output name: NCHW tensor}.
    """

    def __init__(self, path: str | Path, outputs: Sequence[str]):
        path = Path(path)
        model = json.loads(path.read_text())
        self.nodes = {node["name"]: node for node in model["modelTopology"]["node"]}
        missing = [name for name in outputs if name not in self.nodes]
        if missing:
            raise ValueError(f"{path}: no nodes named {missing}")
        weights = load_weights(model, path.parent)
        self.outputs = list(outputs)
        self._order = self._topological(outputs)
        self._consts: dict[str, torch.Tensor] = {}
        for name in self._order:
            node = self.nodes[name]
            if node["op"] == "Const":
                self._consts[name] = torch.from_numpy(np.ascontiguousarray(weights[name]))
        self._prepare_kernels()

    def _topological(self, outputs: Sequence[str]) -> list[str]:
        order, seen = [], set()

        def visit(name: str) -> None:
            stack = [(name, False)]
            while stack:
                current, done = stack.pop()
                if done:
                    order.append(current)
                    continue
                if current in seen:
                    continue
                seen.add(current)
                stack.append((current, True))
                for source in self.nodes[current].get("input", []):
                    stack.append((source.split(":")[0].lstrip("^"), False))

        for name in outputs:
            visit(name)
        return order

    def _prepare_kernels(self) -> None:
        """Convolution weights turned from TensorFlow's HWIO (HWCM for depthwise) to torch's OIHW."""
        self._kernels: dict[str, torch.Tensor] = {}
        for name in self._order:
            node = self.nodes[name]
            if node["op"] in ("_FusedConv2D", "Conv2D"):
                kernel = self._consts[node["input"][1]]
                self._kernels[name] = kernel.permute(3, 2, 0, 1).contiguous()
            elif node["op"] in ("DepthwiseConv2dNative", "FusedDepthwiseConv2dNative"):
                kernel = self._consts[node["input"][1]]  # (H, W, C, M)
                h, w, c, m = kernel.shape
                self._kernels[name] = kernel.permute(2, 3, 0, 1).reshape(c * m, 1, h, w).contiguous()

    @torch.no_grad()
    def __call__(self, image: torch.Tensor) -> dict[str, torch.Tensor]:
        values: dict[str, torch.Tensor] = {}
        for name in self._order:
            node = self.nodes[name]
            op = node["op"]
            if op == "Const":
                continue
            inputs = [self._value(source, values) for source in node.get("input", []) if not source.startswith("^")]
            values[name] = self._run(node, op, inputs, image)
        return {name: values[name] for name in self.outputs}

    def _value(self, source: str, values: dict) -> torch.Tensor:
        name, _, index = source.partition(":")
        value = values[name] if name in values else self._consts[name]
        if isinstance(value, (list, tuple)):
            return value[int(index or 0)]
        return value

    def _run(self, node: dict, op: str, x: list, image: torch.Tensor):
        if op == "Placeholder":
            return image.permute(0, 3, 1, 2).float()
        if op == "Cast":
            return x[0].float() if _attr(node, "DstT", {}).get("type") == "DT_FLOAT" else x[0].to(torch.int32)
        if op in ("Sub", "Mul", "Add", "AddV2", "RealDiv", "Maximum", "Minimum"):
            a, b = (_to_nchw(v, other) for v, other in ((x[0], x[1]), (x[1], x[0])))
            return {"Sub": torch.sub, "Mul": torch.mul, "Add": torch.add, "AddV2": torch.add, "RealDiv": torch.div,
                    "Maximum": torch.maximum, "Minimum": torch.minimum}[op](a, b)
        if op in ("_FusedConv2D", "Conv2D", "DepthwiseConv2dNative", "FusedDepthwiseConv2dNative"):
            return self._conv(node, op, x)
        if op == "Relu":
            return F.relu(x[0])
        if op == "Relu6":
            return F.relu6(x[0])
        if op == "Sigmoid":
            return torch.sigmoid(x[0])
        if op == "ResizeBilinear":
            size = [int(v) for v in x[1].tolist()]
            if _attr(node, "align_corners", False):
                return F.interpolate(x[0], size=size, mode="bilinear", align_corners=True)
            if not _attr(node, "half_pixel_centers", False):
                raise ValueError(f"{node['name']}: ResizeBilinear without half-pixel centres is not supported")
            return F.interpolate(x[0], size=size, mode="bilinear", align_corners=False)
        if op == "ConcatV2":
            axis = int(x[-1])
            return torch.cat(x[:-1], dim=_NHWC_TO_NCHW[axis])
        if op == "Shape":  # of an NCHW tensor, reported in the graph's NHWC order
            n, c, h, w = x[0].shape
            return torch.tensor([n, h, w, c], dtype=torch.int32)
        if op == "StridedSlice" and x[0].dim() == 1:
            begin, end, stride = int(x[1][0]), int(x[2][0]), int(x[3][0])
            if _attr(node, "shrink_axis_mask", 0) & 1:
                return x[0][begin]
            return x[0][begin:end:stride]
        if op == "Pack" and all(v.dim() == 0 for v in x):
            return torch.stack([v.to(torch.int32) for v in x])
        if op in ("Identity", "Squeeze", "ExpandDims", "Unpack") and x[0].dim() == 4:
            return [x[0]] if op == "Unpack" else x[0]  # batch-of-one reshuffles of the image (no-ops in NCHW)
        raise ValueError(f"{node['name']}: operation {op} is not supported by this runner")

    def _conv(self, node: dict, op: str, x: list) -> torch.Tensor:
        kernel = self._kernels[node["name"]]
        strides = _attr(node, "strides", [1, 1, 1, 1])[1:3]
        dilations = _attr(node, "dilations", [1, 1, 1, 1])[1:3]
        padding = _attr(node, "padding", "VALID")
        depthwise = "Depthwise" in op
        inp = x[0]
        if padding == "SAME":
            pad_h = _same_padding(inp.shape[2], kernel.shape[2], strides[0], dilations[0])
            pad_w = _same_padding(inp.shape[3], kernel.shape[3], strides[1], dilations[1])
            if pad_h[0] == pad_h[1] and pad_w[0] == pad_w[1]:
                pad = (pad_h[0], pad_w[0])
            else:
                inp, pad = F.pad(inp, (pad_w[0], pad_w[1], pad_h[0], pad_h[1])), (0, 0)
        elif padding == "VALID":
            pad = (0, 0)
        else:
            raise ValueError(f"{node['name']}: padding {padding} is not supported")
        groups = inp.shape[1] if depthwise else 1
        out = F.conv2d(inp, kernel, None, tuple(strides), pad, tuple(dilations), groups)
        for i, fused in enumerate(_attr(node, "fused_ops", []) if op.startswith(("_Fused", "Fused")) else []):
            if fused == "BiasAdd":
                out = out + x[2].reshape(1, -1, 1, 1)
            elif fused == "Relu":
                out = F.relu(out)
            elif fused == "Relu6":
                out = F.relu6(out)
            else:
                raise ValueError(f"{node['name']}: fused operation {fused} is not supported")
        return out


_NHWC_TO_NCHW = {0: 0, 1: 2, 2: 3, 3: 1, -1: 1}


def _to_nchw(value: torch.Tensor, other: torch.Tensor) -> torch.Tensor:
    """A constant shaped for NHWC broadcasting ((C,), (1, 1, 1, C), ...) made to broadcast in NCHW."""
    if other.dim() == 4 and value.dim() >= 1 and value.shape[-1] > 1 and value.numel() == value.shape[-1]:
        return value.reshape(1, -1, 1, 1).to(other.dtype)
    return value.to(other.dtype) if value.is_floating_point() != other.is_floating_point() else value

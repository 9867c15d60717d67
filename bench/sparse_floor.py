"""What the sparse tracker's per-frame ONNX session spends its time on, on this CPU (one thread).

    .venv/bin/python bench/sparse_floor.py [--rounds 7]

Prints medians over rounds that alternate between the variants (a busy machine slows them alike):
1. session.run of the shipped per-frame graph of the accurate network (128 wide) with ONNX
   Runtime's MatMulAddFusion on (ORT's default) and off, and their ratio; and a frame through
   humotion.sparse.frame.OnnxStream (what SparseTracker runs: fusion off, inputs and outputs
   bound once, no dict of arrays per frame);
2. the cost per node of ONNX Runtime itself: a chain of 300 trivial Add nodes on 3 numbers;
3. session.run of the same frame function for untrained networks 96 and 64 wide (the default
   network is 64 wide), exported here (about a minute): how much the size of the weights matters.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch
from onnx import TensorProto, helper, numpy_helper

from humotion.sparse.frame import INPUTS, OnnxStream, example_inputs, export_onnx
from humotion.sparse.model import SparseConfig, SparsePoser
from humotion.sparse.tracker import SHIPPED_WEIGHTS, load_weights

NARROW = {"96 wide": dict(hidden=96, feedforward=192, decoder=192, embed=24),
          "64 wide": dict(hidden=64, feedforward=128, decoder=128, embed=16)}


def session(model, fusion: bool = False) -> ort.InferenceSession:
    options = ort.SessionOptions()
    options.intra_op_num_threads = options.inter_op_num_threads = 1
    return ort.InferenceSession(model, options, providers=["CPUExecutionProvider"],
                                disabled_optimizers=[] if fusion else ["MatMulAddFusion"])


def add_chain(nodes: int) -> bytes:
    """An ONNX model of `nodes` Add nodes in a row on a (3,) float tensor."""
    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, [3])
    y = helper.make_tensor_value_info(f"y{nodes}", TensorProto.FLOAT, [3])
    chain = [helper.make_node("Add", ["x" if i == 0 else f"y{i}", "one"], [f"y{i + 1}"]) for i in range(nodes)]
    graph = helper.make_graph(chain, "chain", [x], [y], [numpy_helper.from_array(np.ones(3, np.float32), "one")])
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)], ir_version=9).SerializeToString()


def median_ms(run, repeats: int) -> float:
    for _ in range(20):
        run()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    return statistics.median(times) * 1000


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=7)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    shipped, shipped_onnx = load_weights("accurate"), SHIPPED_WEIGHTS["accurate"].with_suffix(".onnx")
    feeds = {"shipped": {n: v.numpy() for n, v in zip(INPUTS, example_inputs(shipped))}}
    sessions = {"shipped, fusion on": (session(str(shipped_onnx), fusion=True), "shipped"),
                "shipped, fusion off": (session(str(shipped_onnx)), "shipped")}
    stream, frame = OnnxStream(shipped_onnx), list(feeds["shipped"].values())
    stream.start(frame[6], frame[7], frame[8:])       # offsets, eye, state
    with tempfile.TemporaryDirectory() as folder:
        for name, sizes in NARROW.items():
            torch.manual_seed(0)
            model = SparsePoser(SparseConfig(**sizes)).eval()
            print(f"exporting the untrained {name} network ...", file=sys.stderr)
            path = export_onnx(model, Path(folder) / f"{name.split()[0]}.onnx")
            feeds[name] = {n: v.numpy() for n, v in zip(INPUTS, example_inputs(model))}
            sessions[name] = (session(str(path)), name)
        chains = {n: session(add_chain(n)) for n in (1, 301)}
        results = {name: [] for name in list(sessions) + ["stream", "per node"]}
        x = {"x": np.zeros(3, np.float32)}
        for _ in range(args.rounds):
            for name, (s, feed) in sessions.items():
                results[name].append(median_ms(lambda: s.run(None, feeds[feed]), 300))
            results["stream"].append(median_ms(lambda: stream(*frame[:3]), 300))
            one, many = (median_ms(lambda: chains[n].run(None, x), 2000) for n in (1, 301))
            results["per node"].append((many - one) / 300 * 1000)   # microseconds
    ms = {name: statistics.median(values) for name, values in results.items()}
    print(f"one CPU thread, medians of {args.rounds} alternating rounds")
    print(f"  session.run, shipped graph, MatMulAddFusion on   {ms['shipped, fusion on']:.3f} ms")
    print(f"  session.run, shipped graph, MatMulAddFusion off  {ms['shipped, fusion off']:.3f} ms "
          f"(ratio {ms['shipped, fusion off'] / ms['shipped, fusion on']:.2f})")
    print(f"  OnnxStream frame, shipped graph (I/O binding)    {ms['stream']:.3f} ms "
          f"(ratio to session.run, fusion off {ms['stream'] / ms['shipped, fusion off']:.2f})")
    print(f"  ONNX Runtime per node (chain of trivial Adds)    {ms['per node']:.2f} us")
    for name in NARROW:
        print(f"  session.run, untrained {name} network          {ms[name]:.3f} ms "
              f"(ratio to shipped {ms[name] / ms['shipped, fusion off']:.2f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

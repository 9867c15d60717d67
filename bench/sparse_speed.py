"""Sparse tracking speed on this CPU: one live stream on one thread, and many streams batched.

    .venv/bin/python bench/sparse_speed.py [--weights PATH|NAME] [--frames 600] [--passes 1]
        [--baseline-weights OLD.pt|NAME] [--baseline-onnx OLD.onnx]

Prints, for one stream on one CPU thread, the per-frame latency (median and 99th percentile) of
the network step alone (SparsePoser.step) and of the whole SparseTracker.update (signals,
network, forward kinematics of the body, then the arm and foot solve of humotion.sparse.solve)
in PyTorch and with runtime="onnx" (ONNX Runtime), the latter also without the solve (solve=None),
against the 11.1 ms a 90 Hz headset frame lasts. Each pass runs every tracker through the whole
clip in turn, in a different order each pass, so a busy machine slows them alike; they do not
alternate frame by frame, which would let one evict the other's weights from the CPU caches
between frames (that doubled the ONNX tracker's time). The input poses are numpy arrays, as an
application's would be. --baseline-weights adds an ONNX tracker with other weights (an earlier
release's network, say), --baseline-onnx one running another export of the frame function (an
earlier version's, of the same weights unless --baseline-weights), and its ratio to the current one.
A fixed numpy workload of about the same duration is timed alongside, in the same passes: its
p99 / median is this machine's own jitter (a deterministic computation's tail), the floor under
the trackers' p99. Then frames per second for B streams run together (SparsePoser.forward over a batch).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import numpy as np
import torch

from humotion.assets import demo_clip_path
from humotion.canonical import to_canonical
from humotion.io import load_motion
from humotion.sparse.frame import OnnxStream
from humotion.sparse.recording import HeadsetFrame, stream_from_motion
from humotion.sparse.tracker import SparseTracker, load_weights

FRAME_BUDGET_MS = 1000 / 90


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(round(q / 100 * (len(ordered) - 1))))]


def numpy_frame(frame: HeadsetFrame) -> HeadsetFrame:
    """The frame with its poses as numpy arrays, as an application's would be."""
    def device(pose):
        return None if pose is None else (pose[0].numpy(), pose[1].numpy())
    return HeadsetFrame(frame.timestamp, device(frame.head), device(frame.left), device(frame.right))


def warm(times: list[float], frames: int) -> list[float]:
    """times of several passes over frames frames, without the first 10 of each pass."""
    return [x for start in range(0, len(times), frames) for x in times[start + 10:start + frames]]


class FixedWorkload:
    """The same small matrix products every call, timed like a tracker (reset, update): how much
    a deterministic computation's time varies on this machine."""

    def __init__(self, products: int = 20):
        self.matrix = np.random.default_rng(0).random((64, 64), dtype=np.float32)
        self.products = products

    def reset(self) -> None:
        pass

    def update(self, frame: HeadsetFrame) -> None:
        x = self.matrix
        for _ in range(self.products):
            x = np.tanh(x @ self.matrix * 0.01)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--weights", default="default", help="a .pt file or a shipped network's name (default, accurate)")
    parser.add_argument("--frames", type=int, default=600, help="frames of the clip timed per pass")
    parser.add_argument("--passes", type=int, default=1, help="times the clip is run through the trackers")
    parser.add_argument("--baseline-weights", metavar="PATH|NAME", help="weights of a network to compare with")
    parser.add_argument("--baseline-onnx", metavar="PATH", help="an ONNX export of the frame function to compare with")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)

    motion = to_canonical(load_motion(demo_clip_path()))
    stream = stream_from_motion(motion, "HT", generator=torch.Generator().manual_seed(0))
    signals = stream.signals()
    model = load_weights(args.weights)
    n = min(args.frames, len(stream))

    step_ms, state = [], None
    with torch.no_grad():
        for t in range(n):
            frame = {k: v[t] for k, v in signals.items()}
            start = time.perf_counter()
            _, state = model.step(frame, state)
            step_ms.append((time.perf_counter() - start) * 1000)

    trackers = {"tracker (torch)": SparseTracker(model, runtime="torch"), "tracker (onnx)": SparseTracker(model, runtime="onnx"),
                "onnx, no solve": SparseTracker(model, runtime="onnx", solve=None)}
    baseline = args.baseline_weights or args.baseline_onnx
    if baseline:
        trackers["baseline (onnx)"] = SparseTracker(load_weights(args.baseline_weights or args.weights), runtime="onnx")
    if args.baseline_onnx:
        trackers["baseline (onnx)"]._stream = OnnxStream(args.baseline_onnx)    # the same tracker, another file
    trackers["fixed workload"] = FixedWorkload()
    tracker_ms = {label: [] for label in trackers}
    frames = [numpy_frame(stream.frame(t)) for t in range(n)]
    labels = list(trackers)
    for k in range(args.passes):
        for label in labels[k % len(labels):] + labels[:k % len(labels)]:   # a different order each pass
            tracker = trackers[label]
            tracker.reset()
            for frame in frames:
                start = time.perf_counter()
                tracker.update(frame)
                tracker_ms[label].append((time.perf_counter() - start) * 1000)

    print(f"one stream, one CPU thread, {n} frames x {args.passes} passes (first 10 of each dropped as warm-up); "
          f"budget {FRAME_BUDGET_MS:.1f} ms at 90 Hz")
    medians, tails = {}, {}
    for label, times in [("network step", step_ms[10:])] + [(k, warm(v, n)) for k, v in tracker_ms.items()]:
        medians[label], p99 = statistics.median(times), percentile(times, 99)
        tails[label] = p99 / medians[label]
        budget = "" if label == "fixed workload" else f"   = {FRAME_BUDGET_MS / medians[label]:5.1f}x under budget"
        print(f"  {label:16} median {medians[label]:6.3f} ms   p99 {p99:6.3f} ms{budget}")
    print(f"  p99 / median: tracker (onnx) {tails['tracker (onnx)']:.2f}, "
          f"fixed workload {tails['fixed workload']:.2f} (this machine's jitter)")
    print(f"  the solve's share of the ONNX tracker's median: "
          f"{medians['tracker (onnx)'] - medians['onnx, no solve']:.3f} ms")
    if baseline:
        print(f"  tracker (onnx) / baseline (onnx) medians: {medians['tracker (onnx)'] / medians['baseline (onnx)']:.2f}")

    print("many streams batched (SparsePoser.forward), one CPU thread:")
    frames = 60
    for batch in (1, 16, 64, 256):
        batched = {k: v[:frames].expand(batch, *v[:frames].shape) for k, v in signals.items()}
        with torch.no_grad():
            start = time.perf_counter()
            model(batched)
            seconds = time.perf_counter() - start
        print(f"  {batch:4d} streams x {frames} frames: {batch * frames / seconds:9.0f} frames/s")
    return 0


if __name__ == "__main__":
    sys.exit(main())

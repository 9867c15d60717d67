"""Sparse tracking speed on this CPU: one live stream on one thread, and many streams batched.

    .venv/bin/python bench/sparse_speed.py [--weights PATH] [--frames 600]

Prints, for one stream on one CPU thread, the per-frame latency (median and 99th percentile) of
the network step alone (SparsePoser.step) and of the whole SparseTracker.update (signals,
network, forward kinematics of the body) in PyTorch and with runtime="onnx" (ONNX Runtime),
against the 11.1 ms a 90 Hz headset frame lasts;
then frames per second for B streams run together (SparsePoser.forward over a batch).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import torch

from humotion.assets import demo_clip_path
from humotion.canonical import to_canonical
from humotion.io import load_motion
from humotion.sparse import signals as sg
from humotion.sparse.model import load_sparse_model
from humotion.sparse.recording import stream_from_motion
from humotion.sparse.tracker import DEFAULT_WEIGHTS, SparseTracker

FRAME_BUDGET_MS = 1000 / 90


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(round(q / 100 * (len(ordered) - 1))))]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--weights", default=str(DEFAULT_WEIGHTS))
    parser.add_argument("--frames", type=int, default=600, help="frames timed per measurement")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)

    motion = to_canonical(load_motion(demo_clip_path()))
    stream = stream_from_motion(motion, "HT", generator=torch.Generator().manual_seed(0))
    signals = stream.signals()
    model = load_sparse_model(args.weights)
    n = min(args.frames, len(stream))

    step_ms, state = [], None
    with torch.no_grad():
        for t in range(n):
            frame = {k: v[t] for k, v in signals.items()}
            start = time.perf_counter()
            _, state = model.step(frame, state)
            step_ms.append((time.perf_counter() - start) * 1000)

    def time_tracker(tracker: SparseTracker) -> list[float]:
        times = []
        for t in range(n):
            args_t = [(getattr(stream, f"{d}_rotations")[t], getattr(stream, f"{d}_positions")[t]) for d in sg.DEVICES]
            start = time.perf_counter()
            tracker.update(*args_t, bool(stream.visible[t, 0]), bool(stream.visible[t, 1]), float(stream.timestamps[t]))
            times.append((time.perf_counter() - start) * 1000)
        return times

    rows = [("network step", step_ms), ("tracker (torch)", time_tracker(SparseTracker(model))),
            ("tracker (onnx)", time_tracker(SparseTracker(model, runtime="onnx")))]

    print(f"one stream, one CPU thread, {n} frames (first 10 dropped as warm-up); budget {FRAME_BUDGET_MS:.1f} ms at 90 Hz")
    for label, times in rows:
        median, p99 = statistics.median(times[10:]), percentile(times[10:], 99)
        print(f"  {label:16} median {median:6.3f} ms   p99 {p99:6.3f} ms   = {FRAME_BUDGET_MS / median:5.1f}x under budget")

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

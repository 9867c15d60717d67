"""Refinement after the network, in hand tracking (HT): what happens when a hand re-enters the view.

    .venv/bin/python bench/sparse_refine.py [--weights PATH] [--max-clips 8]

On the CMU test subjects with simulated HT visibility, for the network alone (root anchored to
the headset, as SparseTracker runs it), the network +
refinement with the plain squared data term, and + refinement with the robust term, prints the
largest and the median frame-to-frame jump of the wrist on the frames where a hand re-enters the
view (cm), and the hand and upper-body MPJPE (cm) over all frames.
"""

from __future__ import annotations

import argparse
import statistics
import sys

import torch

from humotion.canonical import JOINTS, to_canonical
from humotion.sparse import metrics
from humotion.sparse import signals as sg
from humotion.sparse.batches import DEFAULT_DATA
from humotion.sparse.evaluation import simulate_and_track, test_sets
from humotion.sparse.model import load_sparse_model
from humotion.sparse.refine import RefineConfig, refine
from humotion.sparse.tracker import DEFAULT_WEIGHTS


WRISTS = [JOINTS.index("left_wrist"), JOINTS.index("right_wrist")]


def reentry_jumps(positions: torch.Tensor, visible: torch.Tensor) -> list[float]:
    """Wrist jumps (cm) from the frame before to the frame a hand becomes visible again."""
    jumps = []
    for k, joint in enumerate(WRISTS):
        back = (visible[1:, k] & ~visible[:-1, k]).nonzero()[:, 0] + 1
        jumps += [float((positions[t, joint] - positions[t - 1, joint]).norm() * 100) for t in back]
    return jumps


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--weights", default=str(DEFAULT_WEIGHTS))
    parser.add_argument("--max-clips", type=int, default=8)
    parser.add_argument("--max-seconds", type=float, default=20.0)
    parser.add_argument("--alpha", type=float, default=RefineConfig.alpha, help="robust loss shape a")
    parser.add_argument("--scale", type=float, default=RefineConfig.scale_m, help="robust loss scale c, metres")
    parser.add_argument("--smooth", type=float, default=RefineConfig.smooth_weight, help="acceleration weight")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    model = load_sparse_model(args.weights)
    fps = float(getattr(model, "fps", 30.0))
    rows = {"network": [], "+ refine (L2)": [], "+ refine (robust)": []}
    errors = {name: [] for name in rows}
    for i, clip in enumerate(test_sets(DEFAULT_DATA, args.max_clips)["CMU test"]):
        truth = to_canonical(clip.load()).resample(fps)[: int(args.max_seconds * fps)]
        run = simulate_and_track(model, truth, "HT", seed=i)
        world_p = truth.world_positions()
        r, p, visible, net = run.rotations, run.positions, run.visible, run.tracked
        if not (visible[1:] & ~visible[:-1]).any():
            continue
        candidates = {"network": net}
        for label, robust in (("+ refine (L2)", False), ("+ refine (robust)", True)):
            config = RefineConfig(robust=robust, alpha=args.alpha, scale_m=args.scale, weight=2 * args.scale**2,
                                  smooth_weight=args.smooth)
            candidates[label] = refine(net, r, p, visible, sg.eye_offset(truth.skeleton), config)
        for label, motion in candidates.items():
            pos = motion.world_positions()
            rows[label] += reentry_jumps(pos, visible)
            errors[label].append((metrics.mpjpe(pos, world_p, metrics.HANDS), metrics.mpjpe(pos, world_p, metrics.UPPER_BODY)))
        print(f"  clip {clip.name}: {int((visible[1:] & ~visible[:-1]).sum())} re-entries", file=sys.stderr)
    print(f"{'HT, CMU test':20} {'re-entries':>10} {'max jump':>9} {'median':>7} {'hand':>7} {'upper':>7}")
    for label, jumps in rows.items():
        hand = statistics.mean(e[0] for e in errors[label])
        upper = statistics.mean(e[1] for e in errors[label])
        print(f"{label:20} {len(jumps):10d} {max(jumps):9.2f} {statistics.median(jumps):7.2f} {hand:7.2f} {upper:7.2f}")
    print("units: cm (wrist jump between the frame before and the frame a hand re-enters the view)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Which root trajectory to give the tracked body (issue 27 item 3), each with and without the arm
and foot solve (humotion.sparse.solve), on the held-out CMU subjects and a sample of HDM05.

    .venv/bin/python bench/sparse_root.py [--cmu 12] [--hdm05 40]

Options: "anchored" (the root moved so the eyes meet the headset: SparseTracker's default),
"own" (the trajectory the network integrates), "anchored xz + own y" (horizontal from the
anchoring, height from the network's own trajectory), "anchored, lower sole on floor" (anchored,
then moved vertically so the lower foot's sole is on the floor, Y = 0, on every frame). Prints
frame-weighted MPJPE, lower-body and pelvis error (cm) per data set, scenario and option. HDM05:
every (189 // N)-th clip, the first N of them; clips cut to 60 s.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
import torch

from humotion.motion import Motion
from humotion.sparse import metrics
from humotion.sparse import solve as sv
from humotion.sparse.batches import DEFAULT_DATA
from humotion.sparse.evaluation import FLOOR, prepare, simulate_and_track, test_sets
from humotion.sparse.tracker import load_weights


def grounded(motion: Motion) -> Motion:
    """The motion moved vertically, frame by frame, so its lower sole is on the floor."""
    body = sv.BodyGeometry.of(motion.skeleton)
    soles = sv.sole_heights(motion.world_positions().double().numpy(), body.clearance, FLOOR).min(-1)
    shift = torch.zeros(motion.num_frames, 3)
    shift[:, 1] = torch.from_numpy(soles).float()
    return Motion(motion.skeleton, motion.rotations, motion.root_positions - shift, motion.fps)


def options(model, motion: Motion, scenario: str, seed: int):
    """(the anchored run, {option: Motion})."""
    run = simulate_and_track(model, motion, scenario, seed)
    own = simulate_and_track(model, motion, scenario, seed, anchor=False).tracked
    anchored = run.tracked
    mixed = torch.stack([anchored.root_positions[:, 0], own.root_positions[:, 1], anchored.root_positions[:, 2]], -1)
    return run, {"anchored": anchored, "own": own,
                 "anchored xz + own y": Motion(motion.skeleton, anchored.rotations, mixed, motion.fps),
                 "anchored, lower sole on floor": grounded(anchored)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--weights", default="default", help="a .pt file or a shipped network's name")
    parser.add_argument("--data", default=DEFAULT_DATA)
    parser.add_argument("--cmu", type=int, default=12, help="first N CMU test clips")
    parser.add_argument("--hdm05", type=int, default=40, help="N HDM05 clips spread over the set")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    model = load_weights(args.weights)
    sets = test_sets(args.data)
    hdm05 = sets["HDM05"]
    sets = {"CMU test": sets["CMU test"][:args.cmu], "HDM05": hdm05[::max(1, len(hdm05) // args.hdm05)][:args.hdm05]}
    for name, clips in sets.items():
        motions = [m for m in (prepare(c.load(), model.fps, 60.0) for c in clips) if m is not None]
        for scenario in ("MC", "HT"):
            sums = {}
            for seed, motion in enumerate(motions):
                run, tracked = options(model, motion, scenario, seed)
                true = motion.world_positions()
                for label, body in tracked.items():
                    for solve in (False, True):
                        out = sv.solve_body(body, run.rotations, run.positions, run.visible, floor=FLOOR) if solve else body
                        p = out.world_positions()
                        row = sums.setdefault((label, solve), np.zeros(4))
                        row += np.array([metrics.mpjpe(p, true), metrics.mpjpe(p, true, metrics.LOWER_BODY),
                                         metrics.mpjpe(p, true, ("pelvis",)), 1.0]) * motion.num_frames
            for (label, solve), row in sums.items():
                print(f"{name:8} {scenario} {label:30} solve={solve!s:5} MPJPE {row[0] / row[3]:6.2f} "
                      f"lower {row[1] / row[3]:6.2f} pelvis {row[2] / row[3]:6.2f}  ({len(motions)} clips, "
                      f"{int(row[3])} frames)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

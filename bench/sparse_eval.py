"""Sparse tracking accuracy on held-out subjects: one table, MC and HT, CMU test split and HDM05.

    .venv/bin/python bench/sparse_eval.py                       # shipped weights + baselines
    .venv/bin/python bench/sparse_eval.py --weights fixed=runs/fixed/sparse_poser.pt --json

Rows: the network (shipped weights unless --weights replaces them) as SparseTracker runs it, its
root anchored to the headset; "hold last hand" (the same network fed the last seen pose of a
hand that left the view, marked visible: the usual workaround without a mask token); "own
trajectory" (the same network with the root trajectory it integrates itself, no anchoring); and
any further --weights LABEL=PATH (e.g. the fixed-token and
loss ablations trained with `humotion train sparse --mask-token fixed` / `--ablate-loss ...`).
Test data: the CMU subjects of the collection's test split (never trained on; each take once) and, across
datasets, HDM05 (evaluation only). HT visibility uses the default frustum with random tracking
losses, drawn from a fixed seed so every row sees the same hands.
Metrics: humotion.sparse.metrics (MPJRE deg, MPJPE cm, MPJVE cm/s, Jitter 10^2 m/s^3, hand,
upper and lower body MPJPE cm), averaged over frames of every clip.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

from humotion import rotations as rot
from humotion.canonical import to_canonical
from humotion.data import MotionCollection
from humotion.motion import Motion
from humotion.sparse import metrics
from humotion.sparse import signals as sg
from humotion.sparse.model import load_sparse_model
from humotion.sparse.tracker import DEFAULT_WEIGHTS, anchor_to_head

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "mocap"


def test_sets(root: Path, max_clips: int | None) -> dict[str, list]:
    """Clips of the CMU test subjects and of HDM05. The split is the training's (computed on the
    whole tree); each CMU take counts once (the game-rig copies of CMU takes are left out)."""
    everything = MotionCollection.load(root, progress=False)
    test = everything.filter(subjects=everything.split()["test"])
    sets = {"CMU test": test.filter(exclude=("hdm05_jointlearning", "cmu_iclone_ccskeleton")).clips,
            "HDM05": test.filter(sources=("hdm05_jointlearning",)).clips}
    return {name: clips[:max_clips] if max_clips else clips for name, clips in sets.items()}


def hold_last_seen(rotations: torch.Tensor, positions: torch.Tensor, visible: torch.Tensor):
    """Device poses where an unseen hand keeps its last seen pose and counts as visible
    (frames before it is first seen stay unseen). rotations (T, 3, 3, 3), positions (T, 3, 3)."""
    rotations, positions, held = rotations.clone(), positions.clone(), visible.clone()
    for k in (0, 1):
        last = None
        for t in range(len(visible)):
            if visible[t, k]:
                last = t
            elif last is not None:
                rotations[t, k + 1], positions[t, k + 1], held[t, k] = rotations[last, k + 1], positions[last, k + 1], True
    return rotations, positions, held


def evaluate_clip(model, motion, scenario: str, hold: bool, seed: int, anchor: bool = True) -> tuple[dict, int]:
    """Metrics of one canonical motion (already at the model's rate) and its frame count.
    anchor: root placed so the eyes meet the headset (SparseTracker's default), else the
    network's own integrated trajectory."""
    world_r, world_p = motion.world()
    r, p = sg.device_poses(world_r, world_p, sg.eye_offset(motion.skeleton))
    visible = sg.simulate_visibility(r, p, scenario, sg.Frustum(), sg.Dropout() if scenario == "HT" else None,
                                     motion.fps, torch.Generator().manual_seed(seed))
    if hold:
        r, p, visible = hold_last_seen(r, p, visible)
    with torch.no_grad():
        out = model(sg.hide_unseen(sg.pose_signals(r, p, visible)))
    predicted = Motion(motion.skeleton, rot.matrix_to_quat(out["rotations"]), out["root_positions"], motion.fps)
    if anchor:
        predicted = anchor_to_head(predicted, p[:, 0])
    pred_p = predicted.world_positions()
    true_local = motion.rotations_as("matrix")
    return metrics.evaluate(pred_p, world_p, out["rotations"], true_local, motion.fps), motion.num_frames


def evaluate(model, clips, scenario: str, hold: bool, fps: float, max_seconds: float, anchor: bool = True) -> dict:
    totals, frames = {}, 0
    for i, clip in enumerate(clips):
        motion = to_canonical(clip.load()).resample(fps)
        motion = motion[: int(max_seconds * fps)] if max_seconds else motion
        if motion.num_frames < 8:
            continue
        scores, n = evaluate_clip(model, motion, scenario, hold, seed=i, anchor=anchor)
        for key, value in scores.items():
            totals[key] = totals.get(key, 0.0) + value * n
        frames += n
    return {key: value / frames for key, value in totals.items()} | {"frames": frames}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--weights", action="append", default=[], metavar="LABEL=PATH",
                        help="a model to evaluate (repeatable; default: the shipped weights as 'network')")
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--max-clips", type=int, help="first N clips of each test set (quick runs)")
    parser.add_argument("--max-seconds", type=float, default=60.0, help="cut clips to this length")
    parser.add_argument("--json", action="store_true", help="print the table as JSON")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)

    weights = [w.split("=", 1) for w in args.weights] or [["network", str(DEFAULT_WEIGHTS)]]
    models = {label: load_sparse_model(path) for label, path in weights}
    fps = models[weights[0][0]].fps
    first = models[weights[0][0]]
    rows = [(label, model, False, True) for label, model in models.items()]
    rows[1:1] = [("hold last hand", first, True, True), ("own trajectory", first, False, False)]
    sets = test_sets(args.data, args.max_clips)
    results = []
    for set_name, clips in sets.items():
        for scenario in ("MC", "HT"):
            for label, model, hold, anchor in rows:
                if hold and scenario == "MC":
                    continue  # controllers never lose the hands
                start = time.perf_counter()
                scores = evaluate(model, clips, scenario, hold, fps, args.max_seconds, anchor)
                results.append({"data": set_name, "scenario": scenario, "model": label, **scores,
                                "seconds": round(time.perf_counter() - start, 1)})
                print(f"  done {set_name} {scenario} {label}", file=sys.stderr)
    if args.json:
        print(json.dumps(results, indent=1))
        return 0
    keys = ("MPJRE", "MPJPE", "MPJVE", "Jitter", "hand", "upper", "lower")
    print(f"{'data':9} {'scen':4} {'model':18} " + " ".join(f"{k:>7}" for k in keys) + "  frames")
    for r in results:
        print(f"{r['data']:9} {r['scenario']:4} {r['model']:18} " + " ".join(f"{r[k]:7.2f}" for k in keys) + f"  {r['frames']}")
    print("units: MPJRE deg; MPJPE, hand, upper, lower cm; MPJVE cm/s; Jitter 10^2 m/s^3")
    return 0


if __name__ == "__main__":
    sys.exit(main())

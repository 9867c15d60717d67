"""Accuracy of sparse tracking on motion capture: headset signals synthesised from real motion,
the network's whole-body motion compared with the truth (metrics of humotion.sparse.metrics).

    sets = test_sets(DEFAULT_DATA)                        # CMU test subjects, HDM05
    rows = evaluate_models({"network": model}, sets)      # one row per data set, scenario and model
    print(format_table(rows))

Used by `humotion eval sparse` and bench/sparse_eval.py. Every clip is mapped onto the canonical
body (its own bone lengths) and resampled to the model's frame rate; HT visibility (the default
frustum plus random tracking losses) is drawn from a seed per clip, so every model sees the same
hands. Rows besides the models': "hold last hand" (the first model fed the last seen pose of a
hand that left the view, marked visible: the usual workaround without a mask token) and "own
trajectory" (the first model's root trajectory as it integrates it, without anchoring to the
headset).

Every model row is solved after its model as SparseTracker solves it (humotion.sparse.solve:
arms to the tracked hands, feet locked and above the floor), the same solve for every method;
"network alone (no solve)" is the first model without it, and "truth" gives the motion
capture's own foot figures. Feet: the floor is the capture's ground plane, Y = 0 (given to the
solve, as a headset's stage space gives it; CMU subject 03 walks on uneven terrain above it);
contacts by the rule of solve.foot_contacts applied to each row's own motion (the truth's to the
truth).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from tqdm.auto import tqdm

from humotion import rotations as rot
from humotion.canonical import to_canonical
from humotion.data import MotionCollection
from humotion.motion import Motion
from humotion.sparse import metrics
from humotion.sparse import signals as sg
from humotion.sparse import solve as sv
from humotion.sparse.tracker import anchor_to_head

METRICS = ("MPJRE", "MPJPE", "MPJVE", "Jitter", "hand", "upper", "lower", "unseen", "target", "reach", "beyond",
           "pen", "depth", "skate")
UNITS = ("units: MPJRE deg; MPJPE, hand, upper, lower cm; MPJVE cm/s; Jitter 10^2 m/s^3; "
         "unseen: wrist error (cm) while its hand is not seen; target: wrist to the tracked hand (cm) while seen; "
         "reach: the same while the hand is within the arm's length of the shoulder, beyond: % of seen wrist-frames not; "
         "pen: % frames a foot is > 2 cm below the floor, depth: the deepest (cm); skate: foot speed in contact (cm/s)")
FLOOR = 0.0
"""The floor's height in the test data (the capture's ground plane), metres."""
COUNTS = {"unseen": "unseen_count", "target": "target_count", "reach": "reach_count", "beyond": "target_count",
          "skate": "contact_count"}
"""Metrics averaged over their own counts (wrist-frames, foot-frames in contact) rather than frames;
"depth" is the maximum over clips."""
SCENARIOS = ("MC", "HT")
HOLD_LAST, OWN_TRAJECTORY, NO_SOLVE, TRUTH = "hold last hand", "own trajectory", "network alone (no solve)", "truth"


def test_sets(root: str | Path, max_clips: int | None = None, progress: bool = False) -> dict[str, list]:
    """Clips of the CMU test subjects and of HDM05 under a mocap tree, as {name: [Clip]}.

    The split is the training's (MotionCollection.split() on the whole tree); each CMU take
    counts once (the game-rig copies of CMU takes are left out). progress: a progress bar (on
    stderr) while files not yet in the cache are read (minutes for the whole tree, once)."""
    everything = MotionCollection.load(root, progress=progress)
    test = everything.filter(subjects=everything.split()["test"])
    sets = {"CMU test": test.filter(exclude=("hdm05_jointlearning", "cmu_iclone_ccskeleton")).clips,
            "HDM05": test.filter(sources=("hdm05_jointlearning",)).clips}
    return {name: clips[:max_clips] if max_clips else clips for name, clips in sets.items()}


def hold_last_seen(rotations: torch.Tensor, positions: torch.Tensor, visible: torch.Tensor):
    """Device poses where an unseen hand keeps its last seen pose and counts as visible
    (frames before it is first seen stay unseen). rotations (T, 3, 3, 3), positions (T, 3, 3),
    visible (T, 2) bool."""
    rotations, positions, held = rotations.clone(), positions.clone(), visible.clone()
    for k in (0, 1):
        last = None
        for t in range(len(visible)):
            if visible[t, k]:
                last = t
            elif last is not None:
                rotations[t, k + 1], positions[t, k + 1], held[t, k] = rotations[last, k + 1], positions[last, k + 1], True
    return rotations, positions, held


@dataclass
class SimulatedRun:
    """A motion seen through a simulated headset and tracked: device rotations (T, 3, 3, 3) and
    positions (T, 3, 3) (head at the eyes, wrists), visible (T, 2) what the headset saw (also
    when the network was fed held hands), the tracked Motion (root anchored to the headset unless
    asked otherwise) and its local rotation matrices (T, 22, 3, 3)."""

    rotations: torch.Tensor
    positions: torch.Tensor
    visible: torch.Tensor
    tracked: Motion
    tracked_rotations: torch.Tensor


def simulate_and_track(model, motion: Motion, scenario: str, seed: int, hold: bool = False,
                       anchor: bool = True) -> SimulatedRun:
    """A canonical motion, already at the model's frame rate, as a headset would see it, tracked.

    scenario: "MC" (hands always seen) or "HT" (frustum + random losses drawn from seed).
    hold: feed the last seen hand pose instead of the mask token. anchor: root placed so the
    eyes meet the headset (SparseTracker's default), else the network's own trajectory."""
    world_r, world_p = motion.world()
    r, p = sg.device_poses(world_r, world_p, sg.eye_offset(motion.skeleton))
    visible = sg.simulate_visibility(r, p, scenario, sg.Frustum(), sg.Dropout() if scenario == "HT" else None,
                                     motion.fps, torch.Generator().manual_seed(seed))
    fed = hold_last_seen(r, p, visible) if hold else (r, p, visible)
    with torch.no_grad():
        out = model(sg.hide_unseen(sg.pose_signals(*fed)))
    tracked = Motion(motion.skeleton, rot.matrix_to_quat(out.rotations), out.root_positions, motion.fps)
    return SimulatedRun(r, p, visible, anchor_to_head(tracked, p[:, 0]) if anchor else tracked, out.rotations)


def evaluate_clip(model, motion: Motion, scenario: str, seed: int, hold: bool = False,
                  anchor: bool = True, solve: bool = True) -> dict[str, float]:
    """Metrics of one canonical motion at the model's frame rate (see simulate_and_track; solve:
    the tracked body solved by humotion.sparse.solve.solve_body, as SparseTracker does), with
    "unseen" (NaN when no hand is ever unseen), "unseen_count" (wrist-frames unseen) and the
    counts of "target", "reach" and "skate" (:data:`COUNTS`)."""
    run = simulate_and_track(model, motion, scenario, seed, hold, anchor)
    tracked, rotations = run.tracked, run.tracked_rotations
    if solve:
        tracked = sv.solve_body(tracked, run.rotations, run.positions, run.visible, floor=FLOOR)
        rotations = tracked.rotations_as("matrix")
    positions, true = tracked.world_positions(), motion.world_positions()
    scores = metrics.evaluate(positions, true, rotations, motion.rotations_as("matrix"), motion.fps)
    scores["unseen"], scores["unseen_count"] = metrics.unseen_hand_error(positions, true, run.visible)
    scores["target"], scores["target_count"] = metrics.target_error(positions, run.positions[:, 1:], run.visible)
    scores["reach"], scores["reach_count"], scores["beyond"] = metrics.reach_error(
        positions, run.positions[:, 1:], run.visible, sv.arm_lengths(motion.skeleton))
    return scores | foot_scores(positions, motion)


def foot_scores(positions: torch.Tensor, truth: Motion) -> dict[str, float]:
    """"pen", "depth", "skate" and "contact_count" (humotion.sparse.metrics) of positions (T, 22, 3)
    metres on truth's skeleton, the floor at FLOOR."""
    body = sv.BodyGeometry.of(truth.skeleton)
    pen, depth = metrics.penetration(positions, body.clearance, FLOOR)
    contacts = sv.foot_contacts(positions.double().numpy(), body.clearance, FLOOR, truth.fps)
    skate, count = metrics.skating(positions, contacts, truth.fps)
    return {"pen": pen, "depth": depth, "skate": skate, "contact_count": count}


def prepare(motion: Motion, fps: float, max_seconds: float | None) -> Motion | None:
    """The motion on the canonical body at fps, cut to max_seconds; None when under 8 frames."""
    motion = to_canonical(motion).resample(fps)
    if max_seconds:
        motion = motion[: int(max_seconds * fps)]
    return motion if motion.num_frames >= 8 else None


def evaluate_motions(model, motions: list[Motion], scenario: str, hold: bool = False,
                     anchor: bool = True, bar: tqdm | None = None, solve: bool = True) -> dict[str, float]:
    """Frame-weighted means of the metrics over prepared motions ("unseen" weighted by the
    clips' unseen wrist-frames, "target" and "skate" likewise by their counts, "depth" the worst
    clip's; None when there are none), plus "frames" and "clips". model None: the truth's own
    foot figures (other metrics None).
    bar: a progress bar advanced by one per clip."""
    totals, weights = dict.fromkeys(METRICS, 0.0), dict.fromkeys(METRICS, 0)
    for seed, motion in enumerate(motions):
        scores = (evaluate_clip(model, motion, scenario, seed, hold, anchor, solve) if model is not None
                  else dict.fromkeys(METRICS, float("nan")) | dict.fromkeys(COUNTS.values(), 0)
                  | foot_scores(motion.world_positions(), motion))
        if bar is not None:
            bar.update()
        for key in METRICS:
            weight = scores[COUNTS[key]] if key in COUNTS else motion.num_frames
            if key == "depth" and scores[key] == scores[key]:
                totals[key], weights[key] = max(totals[key], scores[key]), 1
            elif weight and scores[key] == scores[key]:     # NaN: not measured
                totals[key] += scores[key] * weight
                weights[key] += weight
    if not weights["pen"]:
        raise ValueError("nothing to evaluate: every clip is shorter than 8 frames at the model's rate")
    return ({key: totals[key] / weights[key] if weights[key] else None for key in METRICS}
            | {"frames": weights["pen"], "clips": len(motions)})


def evaluate_models(models: dict, sets: dict[str, list], scenarios=SCENARIOS, max_seconds: float | None = 60.0,
                    baselines: bool = True, progress: bool = True) -> list[dict]:
    """One row per data set, scenario and model: {"data", "scenario", "model", metrics...}.

    models: {label: SparsePoser} (the first one's frame rate is used for all); sets: {name:
    [Clip or Motion]}; baselines: add the "hold last hand" (HT) and "own trajectory" rows of
    the first model; always the first model without the solve (NO_SOLVE) and the truth's foot
    figures (TRUTH, scenario "-"). progress: progress bars on stderr (tqdm), one per data set,
    advanced per clip loaded and per clip evaluated, described by the row being computed."""
    first = next(iter(models.values()))
    rows_spec = [(label, model, False, True, True) for label, model in models.items()]
    rows_spec[1:1] = [(NO_SOLVE, first, False, True, False)]
    if baselines:
        rows_spec[2:2] = [(HOLD_LAST, first, True, True, True), (OWN_TRAJECTORY, first, False, False, True)]
    results = []
    for set_name, clips in sets.items():
        rows = [(scenario, *spec) for scenario in scenarios for spec in rows_spec
                if not (spec[2] and scenario == "MC")]          # controllers never lose the hands: no hold row
        with tqdm(total=len(clips) * (1 + len(rows)), desc=f"{set_name}: loading", unit="clip",
                  disable=not progress, leave=False) as bar:
            motions = []
            for clip in clips:
                motion = prepare(clip if isinstance(clip, Motion) else clip.load(), first.fps, max_seconds)
                motions += [motion] if motion is not None else []
                bar.update()
            bar.total = len(clips) + len(motions) * len(rows)      # clips under 8 frames are not evaluated
            for scenario, label, model, hold, anchor, solve in rows:
                bar.set_description(f"{set_name}: {scenario} {label}")
                scores = evaluate_motions(model, motions, scenario, hold, anchor, bar, solve)
                results.append({"data": set_name, "scenario": scenario, "model": label, **scores})
            results.append({"data": set_name, "scenario": "-", "model": TRUTH,
                            **evaluate_motions(None, motions, "MC")})
    return results


def format_table(rows: list[dict]) -> str:
    """The rows as a fixed-width text table with a units line."""
    width = max([len(r["model"]) for r in rows] + [18])
    data_width = max([len(r["data"]) for r in rows] + [9])
    lines = [f"{'data':{data_width}} {'scen':4} {'model':{width}} " + " ".join(f"{k:>7}" for k in METRICS) + "  frames"]
    for r in rows:
        lines.append(f"{r['data']:{data_width}} {r['scenario']:4} {r['model']:{width}} "
                     + " ".join("      -" if r[k] is None else f"{r[k]:7.2f}" for k in METRICS) + f"  {r['frames']}")
    return "\n".join(lines + [UNITS])

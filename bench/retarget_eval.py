"""Retargeting accuracy on real pairs: the same CMU take on two skeletons. One table.

    .venv/bin/python bench/retarget_eval.py [--data ../shared/data/mocap] [--max-seconds 30] [--weights W.pt]

Pairs: every take of CMU subjects 01, 02, 03, 05, 06 held both on the performer's own 31-joint
ASF/AMC skeleton (120 Hz) and on the 100-joint game rig (cmu_iclone_ccskeleton, 60 Hz). The AMC
is resampled to 60 Hz; the pairs' durations agree to a frame and no time shift fits better than
none (checked and printed). The game-rig takes were "centred" by their author (moved to the
origin, turned to face +Z), so each result is put in its ground truth's frame by one yaw and one
horizontal shift per clip (the mean pelvis facing and position difference), the same for
every method. The classical retargeter stands its result on the target's floor, here the
truth's (Rig.floor_of: what a take on the target rig tells it); the others keep their own.

Cross-format pairs: 23 takes of Li et al.'s exponential-map CMU set (cmu_expmap_li2018: the
38-joint tree of CMU's BVH conversion, every take on subject 02's skeleton, 1.51 m tall as the
conversion drops the thorax and wrist bones), 14 also held as ASF/AMC and 11 on the game rig
(02_01 and 07_01 both): EXPMAP_AMC and EXPMAP_GAME. The set names actions, not takes; which take
each file holds was found by matching knee and elbow angle sequences against every ASF/AMC and
game-rig take here (at most 0.04 rad RMS over the whole take; 0.07 rad and more against any
other take). The files' rows are 120 Hz, CMU's rate: the first row is the conversion's T-pose,
dropped, and row k + 1 is AMC frame k. Exp-map takes are resampled to 60 Hz like the AMC
(Motion.resample: slerp).

Rows:
- cross 31->100: the AMC retargeted onto the game rig; ground truth the game-rig take (made by
  iClone's retargeter, so this measures agreement with a professional tool).
- cross 100->31: the game-rig take retargeted onto the performer's ASF skeleton; ground truth
  the original capture.
- cross 38->31, 31->38: the exp-map take onto the performer's ASF skeleton and back; ground truth
  the AMC, and the exp-map take. The conversion copied the AMC's local rotations onto subject
  02's bones (they agree to 0.05 degrees), so copying rotations would score 0 here by
  construction (as in intra rows), but for the root: the conversion composed its Euler angles
  as Rz Rx Ry, the AMC's order being Rz Ry Rx (the AMC's feet skate less), which turns the
  pelvis by up to 16-20 degrees on the soccer takes (10_05, 10_06, 11_01; 1.3 at most on the
  others). Copying rotations scores that difference.
- cross 38->100, 100->38: the exp-map take onto the game rig and back; ground truth the game-rig
  take, and the exp-map take.
- intra 31->31: a take onto a skeleton of the same structure and rest pose with another
  subject's bone lengths (subject 01 -> 02's lengths, 02 -> 03, ...). Ground truth: that skeleton
  driven by the source's own local rotations, root scaled by the hip-height ratio (what a
  performer with those proportions would do, stride scaling with the leg).
Methods: naive copy (local rotations copied joint to joint through the correspondence, root
unscaled; humotion.retarget.copy_rotations), classical (humotion.retarget.retarget), learned (the
networks alone, humotion.retarget.learned.retarget_learned with feet=False; shipped weights unless
--weights, trained without subjects 01, 02, 03, 05, 06, so every 31/100 pair here is unseen) and
learned+IK (the same with the classical foot-contact IK after it, feet=True, its default). The
exp-map skeleton counts as the learned model's CMU domain: it has the 25 joints the networks
model on the 31-joint skeleton, by name and parent (its thorax of no length). The shipped
networks never saw that skeleton, but saw the motion of 13 of the 14 exp-map/ASF pairs (subjects
10, 11, 16 as ASF/AMC, 07 on the game rig; all but 02_01) and of 2 of the 11 exp-map/game-rig
pairs (07) in training.
Columns:
- err: Mixamo-style, mean over frames and the 21 key joints (canonical points, pelvis excluded)
  of the squared position error divided by the target's standing height squared, x 1000;
  "rel" with the pelvis subtracted per frame, "glob" with the root trajectory included.
- kept: share of the source's foot contacts (ankles and toes) where the target's foot is in
  contact too (same detector, thresholds scaled to the target's height).
- skate: mean horizontal foot speed (cm/s) of the target during the source's contacts; the
  ground truth's own skating is in the last column.
- fps: frames retargeted per second on a 60 s clip (one CPU thread).

--characters prints instead the character route's rows (bench/retarget_characters.py: the
shared glTF/VRM characters against the BVH route, feet on the floor, seconds per minute).
"""

from __future__ import annotations

import argparse
import glob
import math
import re
import sys
import time
from functools import partial
from pathlib import Path

import numpy as np
import torch

from humotion.canonical import JOINTS
from humotion.io import load_motion
from humotion.motion import Motion
from humotion.retarget import Rig, contacts_kept, copy_rotations, foot_contacts, foot_skating, retarget
from humotion.retarget.classical import FOOT_POINTS
from humotion.retarget.learned import retarget_learned
from humotion.skeleton import Skeleton

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "mocap"
SUBJECTS = ("01", "02", "03", "05", "06")
METHODS = {"naive copy": copy_rotations, "classical": partial(retarget, progress=False)}
EXPMAP = "cmu_expmap_li2018/data"
# Exp-map takes (files under EXPMAP, without .txt.gz) and the same take held as ASF/AMC and on
# the game rig, found by pose matching (module docstring).
EXPMAP_AMC = {
    "test/soccer/soccer_1": "cmu_fairmotion/11_01.amc",
    "train/running/running_2": "cmu_sxaxmz/amc/16/16_36__run.amc.gz",
    "train/soccer/soccer_4": "cmu_sxaxmz/amc/10/10_05__walk.amc.gz",
    "train/soccer/soccer_5": "cmu_sxaxmz/amc/10/10_06__walk.amc.gz",
    "train/walking/walking_1": "cmu_mocgui_s02/02_01.amc",
    "train/walking/walking_4": "cmu_visdoom_mocapplayer/amc/07_01-walk.amc",
    "train/walking_extra/walking_18": "cmu_sxaxmz/amc/10/10_04__walk.amc.gz",
    "train/walking_extra/walking_27": "cmu_sxaxmz/amc/16/16_15__walk.amc.gz",
    "train/walking_extra/walking_28": "cmu_sxaxmz/amc/16/16_16__walk.amc.gz",
    "train/walking_extra/walking_29": "cmu_sxaxmz/amc/16/16_21__walk.amc.gz",
    "train/walking_extra/walking_30": "cmu_sxaxmz/amc/16/16_22__walk.amc.gz",
    "train/walking_extra/walking_31": "cmu_sxaxmz/amc/16/16_31__walk.amc.gz",
    "train/walking_extra/walking_32": "cmu_sxaxmz/amc/16/16_32__walk.amc.gz",
    "train/walking_extra/walking_33": "cmu_sxaxmz/amc/16/16_47__walk.amc.gz",
}
EXPMAP_GAME = {
    "test/basketball/basketball_1": "cmu_iclone_ccskeleton/006_07.bvh.gz",
    "train/basketball/basketball_1": "cmu_iclone_ccskeleton/006_02.bvh.gz",
    "train/basketball/basketball_2": "cmu_iclone_ccskeleton/006_03.bvh.gz",
    "train/basketball/basketball_3": "cmu_iclone_ccskeleton/006_04.bvh.gz",
    "train/basketball/basketball_4": "cmu_iclone_ccskeleton/006_05.bvh.gz",
    "train/basketball/basketball_5": "cmu_iclone_ccskeleton/006_06.bvh.gz",
    "train/walking/walking_1": "cmu_iclone_ccskeleton/002_01.bvh.gz",
    "train/walking/walking_2": "cmu_iclone_ccskeleton/005_01.bvh.gz",
    "train/walking/walking_3": "cmu_iclone_ccskeleton/006_01.bvh.gz",
    "train/walking/walking_4": "cmu_iclone_ccskeleton/007_01.bvh.gz",
    "train/walking/walking_5": "cmu_iclone_ccskeleton/007_02.bvh.gz",
}


def paired_takes(data: Path) -> list[tuple[Path, Path]]:
    """(CMU AMC, game-rig BVH) of every take held on both skeletons."""
    pairs = []
    for bvh in sorted((data / "cmu_iclone_ccskeleton").glob("0*.bvh.gz")):
        subject, take = re.match(r"0(\d\d)_(\d\d)", bvh.name).groups()
        if subject not in SUBJECTS:
            continue
        candidates = [data / f"cmu_cyun9601/amc/{subject}/{subject}_{take}.amc.gz",
                      data / f"cmu_mocgui_s02/{subject}_{take}.amc"]
        candidates += [Path(p) for p in glob.glob(str(data / f"cmu_sxaxmz/amc/{subject}/{subject}_{take}__*.amc.gz"))]
        amc = next((p for p in candidates if p.is_file()), None)
        if amc is not None:
            pairs.append((amc, bvh))
    return pairs


def expmap_take(path: Path) -> Motion:
    """An exp-map take without the conversion's T-pose first row (module docstring)."""
    return load_motion(path)[1:]


def facing(rig: Rig, motion: Motion) -> tuple[torch.Tensor, torch.Tensor]:
    """Per frame: pelvis yaw (F,) radians and key points (F, 22, 3), from forward kinematics."""
    world, positions = motion.world()
    pelvis = world[:, rig.joint("pelvis")] @ torch.as_tensor(rig.alignment[0], dtype=world.dtype)
    forward = pelvis[..., 2]
    return torch.atan2(forward[:, 0], forward[:, 2]), rig.points(world, positions, JOINTS)


def aligned(rig: Rig, motion: Motion, truth: Motion) -> tuple[torch.Tensor, torch.Tensor]:
    """Key points (F, 22, 3) of motion turned and shifted into truth's frame, and truth's."""
    yaw_m, pts = facing(rig, motion)
    yaw_t, truth_pts = facing(rig, truth)
    n = min(len(pts), len(truth_pts))
    pts, truth_pts, diff = pts[:n], truth_pts[:n], (yaw_t[:n] - yaw_m[:n])
    yaw = math.atan2(float(diff.sin().mean()), float(diff.cos().mean()))
    c, s = math.cos(yaw), math.sin(yaw)
    turn = torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=pts.dtype)
    pts = pts @ turn.T
    shift = (truth_pts[:, 0] - pts[:, 0]).mean(0) * torch.tensor([1.0, 0.0, 1.0])
    return pts + shift, truth_pts


def best_lag(rig: Rig, motion: Motion, truth: Motion, span: int = 6) -> int:
    """Frame shift of truth against motion (within +-span) that makes their poses agree best."""
    pts, truth_pts = aligned(rig, motion, truth)
    pts, truth_pts = pts - pts[:, :1], truth_pts - truth_pts[:, :1]
    n = len(pts) - 2 * span
    errors = {lag: float((pts[span:span + n] - truth_pts[span + lag:span + lag + n]).norm(dim=-1).mean())
              for lag in range(-span, span + 1)}
    return min(errors, key=errors.get)


def foot_points(rig: Rig, motion: Motion) -> torch.Tensor:
    return rig.points(*motion.world(), FOOT_POINTS)


def scores(method, source: Motion, source_rig: Rig, target: Rig, truth: Motion) -> dict[str, float]:
    floor = {"floor": target.floor_of(truth)} if method is METHODS["classical"] else {}
    result = method(source, target, source_rig=source_rig, **floor)
    pts, truth_pts = aligned(target, result, truth)
    height2 = target.standing_height() ** 2
    glob_err = ((pts - truth_pts) ** 2).sum(-1)[:, 1:].mean() / height2
    rel = (pts - pts[:, :1]) - (truth_pts - truth_pts[:, :1])
    src_feet, out_feet, truth_feet = (foot_points(r, m) for r, m in
                                      ((source_rig, source), (target, result), (target, truth)))
    n = min(len(src_feet), len(out_feet), len(truth_feet))
    src_contacts = foot_contacts(src_feet[:n], source.fps, source_rig.standing_height())
    out_contacts = foot_contacts(out_feet[:n], result.fps, target.standing_height())
    return {"rel": 1000 * float((rel ** 2).sum(-1)[:, 1:].mean() / height2), "glob": 1000 * float(glob_err),
            "kept": 100 * contacts_kept(src_contacts, out_contacts),
            "skate": 100 * foot_skating(out_feet[:n], src_contacts, source.fps),
            "truth skate": 100 * foot_skating(truth_feet[:n], src_contacts, source.fps), "frames": n}


def compare(rows: dict, methods: dict, a: tuple[str, Motion], b: tuple[str, Motion]) -> int:
    """Rows 'cross A->B' and 'cross B->A' of a pair of takes (label, motion): each retargeted
    onto the other's skeleton, the other the ground truth. Returns the time shift of b against
    a that fits best (best_lag)."""
    (label_a, take_a), (label_b, take_b) = a, b
    rig_a, rig_b = Rig.of(take_a.skeleton, label=take_a.name), Rig.of(take_b.skeleton, label=take_b.name)
    for name, method in methods.items():
        rows.setdefault((f"cross {label_a}->{label_b}", name), []).append(scores(method, take_a, rig_a, rig_b, take_b))
        rows.setdefault((f"cross {label_b}->{label_a}", name), []).append(scores(method, take_b, rig_b, rig_a, take_a))
    return best_lag(rig_a, retarget(take_b, rig_a, source_rig=rig_b, feet=False, progress=False), take_a)


def with_lengths_of(skeleton: Skeleton, other: Skeleton) -> Skeleton:
    """skeleton's tree and rest directions with other's bone lengths (same joint names)."""
    def rescaled(offsets: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
        length = offsets.norm(dim=1, keepdim=True)
        return torch.where(length > 1e-9, offsets / length.clamp_min(1e-12), 0.0) * reference.norm(dim=1, keepdim=True)

    order = [other.index(n) for n in skeleton.names]
    ends = [other.end_site_names.index(n) for n in skeleton.end_site_names]
    offsets = rescaled(skeleton.offsets, other.offsets[order])
    offsets[0] = skeleton.offsets[0]
    return Skeleton(skeleton.names, skeleton.parents, offsets, skeleton.end_site_parents,
                    rescaled(skeleton.end_site_offsets, other.end_site_offsets[ends]), skeleton.end_site_names)


def concatenated(motions: list[Motion], frames: int) -> Motion:
    """The motions one after another, cut to `frames` (for timing only)."""
    m = motions[0]
    return Motion(m.skeleton, torch.cat([x.rotations for x in motions])[:frames],
                  torch.cat([x.root_positions for x in motions])[:frames], m.fps, name="timing")


def frames_per_second(method, motion: Motion, target: Rig) -> float:
    source_rig = Rig.of(motion.skeleton)
    start = time.perf_counter()
    method(motion, target, source_rig=source_rig)
    return len(motion) / (time.perf_counter() - start)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--max-seconds", type=float, default=0, help="cut clips to this length (0: whole)")
    parser.add_argument("--weights", type=Path, help="learned retargeter weights (default: the shipped ones)")
    parser.add_argument("--characters", action="store_true", help="the character route's rows instead")
    args = parser.parse_args(argv)
    if args.characters:
        from retarget_characters import main as characters

        return characters(["--data", str(args.data.parent)])
    torch.set_num_threads(1)
    methods = {**METHODS, "learned": partial(retarget_learned, weights=args.weights, feet=False),
               "learned+IK": partial(retarget_learned, weights=args.weights)}

    def cut(motion: Motion) -> Motion:
        return motion[: int(args.max_seconds * motion.fps)] if args.max_seconds else motion

    pairs = paired_takes(args.data)
    rows: dict[tuple[str, str], list[dict]] = {}
    lags = []
    cmu_by_subject: dict[str, list[Motion]] = {}
    game_clips: list[Motion] = []
    for amc, bvh in pairs:
        cmu, game = load_motion(amc), load_motion(bvh)
        cmu_by_subject.setdefault(amc.name[:2], []).append(cmu)
        game_clips.append(game)
        lags.append(compare(rows, methods, ("31", cut(cmu.resample(game.fps))), ("100", cut(game))))
    # Cross-format: exp-map takes against the same takes as ASF/AMC and on the game rig.
    expmap_clips: list[Motion] = []
    for label, table in (("31", EXPMAP_AMC), ("100", EXPMAP_GAME)):
        for name, path in table.items():
            expmap, other = expmap_take(args.data / EXPMAP / f"{name}.txt.gz"), load_motion(args.data / path)
            expmap_clips.append(expmap)
            lags.append(compare(rows, methods, (label, cut(other.resample(60.0))), ("38", cut(expmap.resample(60.0)))))
    # Intra: each subject's takes onto its own skeleton given the next subject's bone lengths.
    subjects = sorted(cmu_by_subject)
    for i, subject in enumerate(subjects):
        other = cmu_by_subject[subjects[(i + 1) % len(subjects)]][0].skeleton
        for cmu in cmu_by_subject[subject]:
            source = cut(cmu.resample(60.0))
            source_rig = Rig.of(source.skeleton)
            target = Rig.of(with_lengths_of(source.skeleton, other))
            scale = target.hip_height() / source_rig.hip_height()
            truth = Motion(target.skeleton, source.rotations, source.root_positions * scale, source.fps)
            for name, method in methods.items():
                rows.setdefault(("intra 31->31", name), []).append(scores(method, source, source_rig, target, truth))

    # Speed on a 60 s clip: CMU and exp-map at 120 Hz, the game rig at 60 Hz.
    cmu_minute = concatenated(cmu_by_subject["02"], 7200)
    game_minute = concatenated([g for g in game_clips if g.skeleton.num_joints == game_clips[0].skeleton.num_joints], 3600)
    expmap_minute = concatenated(expmap_clips, 7200)
    game_rig, cmu_rig, expmap_rig = (Rig.of(m.skeleton) for m in (game_clips[0], cmu_minute, expmap_minute))
    intra_rig = Rig.of(with_lengths_of(cmu_minute.skeleton, cmu_by_subject["03"][0].skeleton))
    timing = {"cross 31->100": (cmu_minute, game_rig), "cross 100->31": (game_minute, cmu_rig),
              "intra 31->31": (cmu_minute, intra_rig), "cross 38->31": (expmap_minute, cmu_rig),
              "cross 31->38": (cmu_minute, expmap_rig), "cross 38->100": (expmap_minute, game_rig),
              "cross 100->38": (game_minute, expmap_rig)}
    speed = {(direction, name): frames_per_second(method, motion, rig)
             for direction, (motion, rig) in timing.items() for name, method in methods.items()}

    frames = {d: sum(r["frames"] for r in rows[(d, "classical")]) for d in ("cross 31->100", "cross 38->31", "cross 38->100")}
    print(f"{len(pairs)} paired takes ({', '.join(sorted({a.name[:2] for a, _ in pairs}))}), {frames['cross 31->100']} "
          f"frames at 60 Hz; exp-map takes (38 joints) paired with ASF/AMC: {len(EXPMAP_AMC)} "
          f"({frames['cross 38->31']} frames), with the game rig: {len(EXPMAP_GAME)} ({frames['cross 38->100']} frames); "
          f"pose-matching time shift per pair: {min(lags)} to {max(lags)} frames")
    header = f"{'direction':<15}{'method':<12}{'err rel':>9}{'err glob':>10}{'kept %':>8}{'skate cm/s':>12}{'fps':>9}{'truth skate':>13}"
    print(header)
    print("-" * len(header))
    for (direction, method) in sorted(rows, key=lambda key: (key[0], list(methods).index(key[1]))):
        results = rows[(direction, method)]
        weights = np.array([r["frames"] for r in results], dtype=float)
        mean = {k: float(np.average([r[k] for r in results], weights=weights)) for k in results[0] if k != "frames"}
        print(f"{direction:<15}{method:<12}{mean['rel']:>9.3f}{mean['glob']:>10.3f}{mean['kept']:>8.1f}"
              f"{mean['skate']:>12.2f}{speed[(direction, method)]:>9.0f}{mean['truth skate']:>13.2f}")
    print("err: mean squared key-joint position error / target height^2 x 1000, frame-weighted over clips")
    return 0


if __name__ == "__main__":
    sys.exit(main())

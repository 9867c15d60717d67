"""Video-capture accuracy on held-out subjects: one table, each stage and each refinement term.

    .venv/bin/python bench/capture_eval.py [--weights runs/lift/lifter_best.pt] [--max-clips 12]

Data: the CMU test subjects of the collection's split (never trained on), each clip cut to
--max-seconds at 30 fps, filmed by one random virtual camera per clip (fixed seeds) and turned
into detector-like 2D keypoints (humotion.capture.keypoints.corrupt: jitter, biases, outliers,
swaps, occluders, dropped keypoints), smoothed by the One-Euro filter as capture's tracker does. Everyone's height is given (as `--height` would), so the
template is the right size; its proportions are the template's, not the subject's.
Rows: the lifting network alone (its joints x height); + bone-length correction onto the
template (and, to tell the correction from the template's proportions, onto the subject's own
bone lengths); + joint angles and refinement (the pipeline); the refinement with each term off;
and with the weights it had before bench/capture_reprojection.py (E_key 1 with plain squares,
E_temporal 1).
Metrics (joints relative to the pelvis, camera frame): MPJPE and PA-MPJPE (mm), acceleration
error (mm / frame^2), bone-length standard deviation across frames (mm, mean over bones), and
the share of frames with any joint past its anatomical limit (humotion.capture.limits: knees
bent the wrong way or folded, elbows folded, hips flexed or extended too far, the neck bent too
far; ground-truth test motion stays inside them all).

A second table follows each clip into the world, as capture() does (humotion.capture.camera: the
camera's pitch and height from everyone's standing axes and foot contacts, each person's tilt
straightened to the floor's vertical, the refinement holding planted feet on the floor; rows
without the soles held because they stand still in the image, with 75 L-BFGS steps a pass
(the previous release's) instead of the default, and with the previous release's image speed
under which a sole counts as still), beside
the ground truth's own figures (the mocap on its floor, y = 0 under its lowest sole): the camera's
pitch and height errors against the random camera's (deg, m), trunk lean (pelvis to neck, degrees
from vertical) and its error against the truth's frame by frame, foot skating (cm/s: the mean
horizontal speed of planted soles, humotion.capture.camera.contact_soles, over frames planted
on both sides of a step; "skating" takes the soles planted in the row's own motion, "true skate"
those planted in the truth, so a motion whose feet never stop cannot hide its sliding by
planting nothing), floor penetration (cm: the mean depth of the lowest sole under the
floor) and the reprojection error of the world keypoints through the camera the result states
(px, median and 95th percentile over keypoints of confidence >= 0.5).
"""

from __future__ import annotations

import argparse
from dataclasses import replace
import sys
import time

import numpy as np
import torch

from humotion import rotations as rot
from humotion.capture.filters import OneEuroConfig, OneEuroFilter
from humotion.capture.joint_angles import correct_bone_lengths
from humotion.capture.keypoints import DetectorNoise, body_keypoints_3d, corrupt, random_camera
from humotion.capture.lifting import load_lifter, procrustes_align
from humotion.capture.limits import share_past_limits
from humotion.capture.camera import SOLES, contact_soles
from humotion.capture.pipeline import (CaptureConfig, Segment, camera_pose, initial_fit, refined, reprojection_error,
                                       straightened, to_world)
from humotion.capture.prior import PosePrior
from humotion.capture.refine import TERMS, CaptureRefineConfig, intrinsics
from humotion.capture.template import bone_lengths
from humotion.motion import Motion
from humotion.sparse.batches import DEFAULT_DATA
from humotion.sparse.evaluation import prepare, test_sets

def filmed(motion, seed: int):
    """(true joints (T, 22, 3) camera frame, pixels (T, 21, 2), confidence (T, 21), camera): the
    noisy keypoints smoothed by the One-Euro filter capture's tracker applies (its defaults)."""
    g = torch.Generator().manual_seed(seed)
    world_r, world_p = motion.world()
    points = body_keypoints_3d(world_r, world_p, motion.skeleton)
    camera = random_camera(g, torch.cat([points, world_p], 1).flatten(0, 1))
    pixels, depth = camera.project(points)
    noisy, confidence = corrupt(pixels, g, DetectorNoise(), camera.size, depth)
    smoother = OneEuroFilter(OneEuroConfig())
    smoothed = [smoother(k.numpy(), c.numpy(), t / motion.fps)
                for t, (k, c) in enumerate(zip(noisy, confidence))]
    noisy = torch.as_tensor(np.stack([k for k, _ in smoothed]))
    confidence = torch.as_tensor(np.stack([c for _, c in smoothed]))
    return camera.to_camera(world_p), noisy, confidence, camera


def scores(pred: torch.Tensor, true: torch.Tensor) -> dict[str, float]:
    """Metrics of the module docstring for (T, 22, 3) joints in metres (pelvis-relative)."""
    pred, true = pred - pred[:, :1], true - true[:, :1]
    bones = bone_lengths(pred)[:, 1:]
    accel = (pred.diff(n=2, dim=0) - true.diff(n=2, dim=0)).norm(dim=-1).mean() if len(pred) > 2 else torch.tensor(0.0)
    return {"MPJPE": float((pred - true).norm(dim=-1).mean() * 1000),
            "PA-MPJPE": float((procrustes_align(pred, true) - true).norm(dim=-1).mean() * 1000),
            "accel": float(accel * 1000), "bone std": float(bones.std(0).mean() * 1000),
            "past limits %": 100 * share_past_limits(pred)}


def joints_of(fit) -> torch.Tensor:
    """(T, 22, 3) joints of a CameraFrameFit, metres."""
    return Motion(fit.skeleton, rot.convert(fit.rotations, "rotvec", "quat"), fit.root, 30.0).world_positions()


def lean_deg(joints: torch.Tensor) -> torch.Tensor:
    """(T,) degrees between the pelvis-to-neck line of world joints (T, 22, 3) and the vertical (Y)."""
    from humotion.canonical import JOINTS

    spine = joints[:, JOINTS.index("neck")] - joints[:, JOINTS.index("pelvis")]
    return torch.rad2deg(torch.acos((spine[:, 1] / spine.norm(dim=-1)).clamp(-1, 1)))


def planted_soles(soles: torch.Tensor, fps: float = 30.0) -> torch.Tensor:
    """(T, 4) bool: world soles (T, 4, 3) planted (humotion.capture.camera.contact_soles, floor y = 0)."""
    return contact_soles(soles, torch.tensor([0.0, 1.0, 0.0]), fps)


def feet_figures(soles: torch.Tensor, planted: torch.Tensor, fps: float = 30.0) -> tuple[float, float]:
    """(skating cm/s, penetration cm) of world soles (T, 4, 3) over the floor y = 0: skating over
    the frames planted (T, 4) on both sides of a step (module docstring)."""
    still = planted[1:] & planted[:-1]
    speed = soles.diff(dim=0)[..., [0, 2]].norm(dim=-1) * fps
    skating = float(speed[still].mean()) * 100 if still.any() else 0.0
    return skating, float(soles[..., 1].amin(1).clamp_max(0).neg().mean()) * 100


def world_scores(truth, camera, fit, segment, prior, refine: CaptureRefineConfig, feet: bool | None = True
                 ) -> dict[str, float]:
    """The second table's figures for one clip: fit (a CameraFrameFit) taken into the world as
    capture() does with the refinement refine (feet=False: without its foot terms; None: as before
    this camera's estimate, a level camera assumed, no tilt straightened, no foot terms), against
    truth: (the random camera, its floor's y, the truth's lean (T,) degrees, its planted soles (T, 4))."""
    pose = camera_pose([fit], [segment], 30.0, CaptureConfig(height_m=float(fit.skeleton.height()),
                                                          pitch_deg=None if feet is not None else 0.0), [],
                       camera=camera)
    if feet is not None:
        fit = straightened(fit, segment, camera, pose)
    config = refine if feet else replace(refine, floor=0.0, skate=0.0, support=0.0)
    person = to_world(refined(fit, segment, camera, prior, config, pose, 30.0), segment, 30.0, pose)
    pitch = float(torch.rad2deg(torch.asin(-truth[0].rotation[2, 1])))
    height = float(truth[0].position[1] - truth[1])
    soles = person.keypoints[:, SOLES]
    skating, penetration = feet_figures(soles, planted_soles(soles))
    reprojection = reprojection_error([person], camera, pose)
    return {"pitch err": abs(pose.pitch_deg - pitch), "height err": abs(pose.height - height),
            "lean": float(lean_deg(person.joints).mean()),
            "lean err": float((lean_deg(person.joints) - truth[2]).abs().mean()),
            "skating": skating, "true skate": feet_figures(soles, truth[3])[0], "penetration": penetration,
            "reproj med": reprojection["median"] or 0.0, "reproj p95": reprojection["p95"] or 0.0}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--weights", help="lifting weights (default: shipped)")
    parser.add_argument("--max-clips", type=int, default=12)
    parser.add_argument("--max-seconds", type=float, default=10.0)
    parser.add_argument("--key", type=float, default=CaptureRefineConfig.key, help="the refinement's E_key weight")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    lifter, prior = load_lifter(args.weights), PosePrior.load()
    base = CaptureRefineConfig(key=args.key)
    variants = {"+ refinement": base}       # the foot terms act in the world table (they need the floor)
    variants.update({f"  without E_{term}": base.without(term) for term in TERMS if term not in ("floor", "skate", "support")})
    variants["  old weights"] = replace(base, key=1.0, robust=0.0, temporal=1.0)   # before the real-clip reprojection work
    rows: dict[str, list] = {"network only": [], "+ bone correction": [], "  (subject's own bones)": [],
                             **{k: [] for k in variants}}
    world: dict[str, list] = {"ground truth": [], "capture (world)": [], "  without still soles": [],
                              "  75 L-BFGS steps": [], "  still under 0.5 m/s": [], "  without foot terms": [],
                              "  level camera (before)": []}
    world_variants = {"  without still soles": replace(base, still_speed=0.0),
                      "  75 L-BFGS steps": replace(base, iterations=75),
                      "  still under 0.5 m/s": replace(base, still_speed=0.5)}
    seconds = 0.0
    frames_total = 0
    for seed, clip in enumerate(test_sets(DEFAULT_DATA, args.max_clips)["CMU test"]):
        motion = prepare(clip.load(), 30.0, args.max_seconds)
        if motion is None:
            continue
        true, pixels, confidence, full_camera = filmed(motion, seed)
        camera = intrinsics(full_camera)
        segment = Segment(0, np.arange(motion.num_frames), np.arange(motion.num_frames) / motion.fps, pixels, confidence)
        start = time.perf_counter()
        fit = initial_fit(segment, camera, lifter, motion.skeleton.height())
        seconds += time.perf_counter() - start
        rows["network only"].append((scores(fit.lifted, true), motion.num_frames))
        for row, skeleton in (("+ bone correction", fit.skeleton), ("  (subject's own bones)", motion.skeleton)):
            rows[row].append((scores(correct_bone_lengths(fit.lifted, skeleton), true), motion.num_frames))
        for label, config in variants.items():
            start = time.perf_counter()
            result = refined(fit, segment, camera, prior, config)
            seconds += (time.perf_counter() - start) if label == "+ refinement" else 0.0
            rows[label].append((scores(joints_of(result), true), motion.num_frames))
        world_r, world_p = motion.world()
        soles = body_keypoints_3d(world_r, world_p, motion.skeleton)[:, SOLES]
        floor = float(soles[..., 1].min())
        shifted = soles - torch.tensor([0.0, floor, 0.0])
        truth = (full_camera, floor, lean_deg(world_p), planted_soles(shifted))
        skating, penetration = feet_figures(shifted, truth[3])
        world["ground truth"].append(({"pitch err": 0.0, "height err": 0.0, "lean": float(lean_deg(world_p).mean()),
                                       "lean err": 0.0, "skating": skating, "true skate": skating,
                                       "penetration": penetration,
                                       "reproj med": 0.0, "reproj p95": 0.0}, motion.num_frames))
        world["capture (world)"].append((world_scores(truth, camera, fit, segment, prior, base), motion.num_frames))
        for label, config in world_variants.items():
            world[label].append((world_scores(truth, camera, fit, segment, prior, config), motion.num_frames))
        world["  without foot terms"].append((world_scores(truth, camera, fit, segment, prior, base, feet=False),
                                              motion.num_frames))
        world["  level camera (before)"].append((world_scores(truth, camera, fit, segment, prior, base, feet=None),
                                                 motion.num_frames))
        frames_total += motion.num_frames
        print(f"  {clip.name}: {motion.num_frames} frames", file=sys.stderr)
    keys = ("MPJPE", "PA-MPJPE", "accel", "bone std", "past limits %")
    print(f"CMU test subjects, {frames_total} frames at 30 fps, one random camera per clip, detector-like noise")
    print(f"{'stage':24} " + " ".join(f"{k:>13}" for k in keys))
    for label, results in rows.items():
        weight = sum(n for _, n in results)
        means = [sum(r[k] * n for r, n in results) / weight for k in keys]
        print(f"{label:24} " + " ".join(f"{m:13.2f}" for m in means))
    print("units: MPJPE, PA-MPJPE, bone std mm; accel mm/frame^2; past limits: % of frames with a knee, elbow, "
          "hip or neck past its anatomical limit (humotion.capture.limits)")
    keys = ("pitch err", "height err", "lean", "lean err", "skating", "true skate", "penetration", "reproj med",
            "reproj p95")
    print(f"\n{'world (one camera, floor)':26} " + " ".join(f"{k:>11}" for k in keys))
    for label, results in world.items():
        weight = sum(n for _, n in results)
        means = [sum(r[k] * n for r, n in results) / weight for k in keys]
        print(f"{label:26} " + " ".join(f"{m:11.2f}" for m in means))
    print("units: pitch err deg, height err m (camera's, found vs true); lean, lean err deg (trunk from vertical; "
          "error against the truth's per frame); skating cm/s (soles planted by the row's own motion), true skate cm/s "
          "(soles planted in the truth); penetration cm (lowest sole under "
          "the floor); reproj px (world keypoints through the stated camera)")
    refine_ms = 1000 * seconds / max(frames_total, 1)
    print(f"time per frame of lifting + correction + angles + refinement (one thread): {refine_ms:.1f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Real footage: the camera found, where the reprojection error comes from, and the feet on the floor.

    .venv/bin/python bench/capture_reprojection.py [--videos hikers aisle intel] [--cache runs/capture_tracks] [--weights PATH]
                                                   [--floor-images docs/images] [--feet-images docs/images]

The clips are ../shared/data/video (see SOURCE.md there). Each is followed as `humotion capture`
follows it (MoveNet, the tracker, One-Euro smoothing; --cache keeps these 2D tracks between runs),
then taken to 3D twice, stage by stage:

- before: the camera from the lifted people alone (their standing axes and the floor of their
  planted feet: humotion.capture.camera.estimate_camera), the refinement's E_key at weight 1
  with plain squares, E_temporal at 1, the foot terms at 1000 and 50 iterations a pass (as
  before this bench);
- no still: as after, but no soles held for standing still in the image;
- after: the camera from upright people in the image first (humotion.capture.metrology), and
  the refinement's defaults (humotion.capture.refine.CaptureRefineConfig).

For each, the reprojection error (pixels; median and 95th percentile over keypoints of
confidence >= 0.5, as capture.json reports it) after each stage: the lifter's pose on the
template skeleton with the root placed by reprojection ("initial"), its tilt straightened to
the floor's vertical, the refinement without the foot terms, and with them (what capture.json
holds: the world joints through the camera the file states). Beside it, the 2D keypoints' own
jitter: the median distance of a confident keypoint from the mean of its two neighbours in time,
over sqrt(1.5) (white noise of standard deviation s per axis gives about 1.18 s; real motion adds
to it, so it bounds the detector's frame-to-frame noise from above; its bias is not seen).

Posture: "knees bent", the median flexion of everyone's knees over all frames (degrees; the
lifter bends standing people's knees where the camera looks down steeply). Feet and floor,
world frame: skating (cm/s, mean horizontal speed of planted soles over frames
planted on both sides of a step), floating (% of frames whose lowest sole is more than 5 cm over
the floor: people here walk or stand) and floor penetration (cm, mean depth of the lowest sole under
the floor), as bench/capture_eval.py reports them on synthetic data. Id switches are in
bench/capture_people.py. --floor-images writes the estimated floor (a 1 m grid) and horizon over
one frame (capture_floor_<clip>.png) of each clip whose camera came from the image, to check it
by eye; --feet-images writes each clip's feet after (capture_feet_<clip>.png): every segment's
lowest sole over time and a side view of everyone on that frame.
"""

from __future__ import annotations

import argparse
import pickle
import sys
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import torch

from capture_eval import feet_figures, planted_soles
from humotion.canonical import JOINTS, PARENTS
from humotion.capture.camera import SOLES
from humotion.capture.follow import make_detector
from humotion.capture.lifting import load_lifter
from humotion.capture.overlay import draw_floor
from humotion.capture.people import PeopleTracker
from humotion.capture.pipeline import (CaptureConfig, camera_pose, default_camera, fit_points, initial_fit, refined,
                                       segments_of, straightened, to_world, track_video)
from humotion.capture.prior import PosePrior
from humotion.capture.refine import CaptureRefineConfig, intrinsics
from humotion.io.video import open_frames

ROOT = Path(__file__).resolve().parents[1]
VIDEOS = ROOT.parent / "shared" / "data" / "video"
CLIPS = {"hikers": ("openmpf_video_02_hikers.mp4", 100), "aisle": ("intel_store-aisle-detection.gif", 30),
         "intel": ("intel_one-by-one-person-detection_first40s.mp4", 250)}
"""name: (file, the frame the floor is drawn on)."""
BONES = [(j, p) for j, p in enumerate(PARENTS) if p >= 0]
"""The canonical skeleton's bones (joint, parent), for the side view."""
BEFORE = CaptureRefineConfig(key=1.0, robust=0.0, temporal=1.0, floor=1000.0, skate=1000.0, support=0.0,
                             iterations=50, still_speed=0.0)
NO_STILL = CaptureRefineConfig(still_speed=0.0)
"""The refinement without the soles held for standing still in the image."""


def tracks(name: str, cache: Path | None):
    """track_video's result for a clip (from cache when there)."""
    stored = cache / f"{name}.pkl" if cache else None
    if stored is not None and stored.is_file():
        return pickle.loads(stored.read_bytes())
    with open_frames(VIDEOS / CLIPS[name][0]) as frames:
        result = track_video(frames, make_detector("movenet"), PeopleTracker(filter_config=CaptureConfig().filter),
                             None, progress=False)
    if stored is not None:
        stored.parent.mkdir(parents=True, exist_ok=True)
        stored.write_bytes(pickle.dumps(result))
    return result


def pixel_errors(points: torch.Tensor, segment, camera, min_confidence: float = 0.5) -> torch.Tensor:
    """(N,) pixels between camera-frame points (T, 21, 3) projected and the segment's confident keypoints."""
    projected, _ = intrinsics(camera).project(points)
    distance = (projected - segment.keypoints).norm(dim=-1)
    return distance[segment.confidence >= min_confidence]


def jitter(segments, min_confidence: float = 0.5) -> float:
    """The 2D keypoints' frame-to-frame noise bound of the module docstring (pixels)."""
    values = []
    for s in segments:
        if len(s.frames) < 3:
            continue
        middle = s.keypoints[1:-1] - (s.keypoints[:-2] + s.keypoints[2:]) / 2
        sure = (s.confidence[:-2] >= min_confidence) & (s.confidence[1:-1] >= min_confidence) & \
               (s.confidence[2:] >= min_confidence)
        values.append(middle.norm(dim=-1)[sure])
    return float(torch.cat(values).quantile(0.5)) / 1.5 ** 0.5 if values else float("nan")


def knee_bend(people) -> float:
    """Degrees, the median over people, frames and sides of the knee's flexion (180 degrees minus
    the angle at the knee between hip and ankle): about 5 for people standing, 20-30 walking."""
    bends = []
    for person in people:
        for side in ("left", "right"):
            hip, knee, ankle = (person.joints[:, JOINTS.index(f"{side}_{j}")] for j in ("hip", "knee", "ankle"))
            cos = torch.nn.functional.cosine_similarity(hip - knee, ankle - knee, dim=-1)
            bends.append(180.0 - torch.rad2deg(torch.acos(cos.clamp(-1, 1))))
    return float(torch.cat(bends).median())


def run(name: str, segments, fps: float, camera, lifter, prior, image_camera: bool, refine: CaptureRefineConfig):
    """({stage: errors (N,)}, feet (skating, floating, penetration), the camera pose, the people's
    world motions (humotion.capture.pipeline.PersonMotion)): one clip taken to 3D."""
    config = CaptureConfig(refine=refine)
    fits = [initial_fit(s, camera, lifter, config.height_of(s.person)) for s in segments]
    pose = camera_pose(fits, segments, fps, config, [], camera=camera if image_camera else None)
    floor = None if pose.source == "level" else pose
    stages = {k: [] for k in ("initial", "straightened", "refined, no feet", "refined (capture.json)")}
    skating, floating, penetration, weights, people = [], [], [], [], []
    for segment, fit in zip(segments, fits):
        stages["initial"].append(pixel_errors(fit_points(fit)[1], segment, camera))
        fit = straightened(fit, segment, camera, pose)
        stages["straightened"].append(pixel_errors(fit_points(fit)[1], segment, camera))
        free = refined(fit, segment, camera, prior, replace(refine, floor=0.0, skate=0.0), None, fps)
        stages["refined, no feet"].append(pixel_errors(fit_points(free)[1], segment, camera))
        person = to_world(refined(fit, segment, camera, prior, refine, floor, fps), segment, fps, pose)
        people.append(person)
        world_camera = pose.camera_in_world(camera)
        projected, _ = world_camera.project(person.keypoints)
        sure = segment.confidence >= 0.5
        distance = (projected - segment.keypoints).norm(dim=-1)
        stages["refined (capture.json)"].append(distance[sure])
        if len(segment.frames) > 2:
            soles = person.keypoints[:, SOLES]
            s, p = feet_figures(soles, planted_soles(soles, fps), fps)
            skating.append(s)
            penetration.append(p)
            floating.append(float((soles[..., 1].amin(1) > 0.05).float().mean()) * 100)
            weights.append(len(segment.frames))
    errors = {k: torch.cat(v).double() for k, v in stages.items()}
    feet = tuple(float(np.average(v, weights=weights)) for v in (skating, floating, penetration))
    return errors, feet, pose, people


def feet_picture(people, frame: int, title: str, path: Path) -> None:
    """A PNG of the people's feet on the floor: each segment's lowest sole over time (cm above the
    floor) and a side view of everyone on the given frame (world z and y, metres)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, (heights, side) = plt.subplots(1, 2, figsize=(13, 4.5))
    for person in people:
        soles = person.keypoints[:, SOLES]
        heights.plot(person.segment.times, soles[..., 1].amin(1) * 100, lw=0.8)
        at = (person.segment.frames == frame).nonzero()
        if len(at):
            t = int(at[0, 0])
            for a, b in BONES:
                side.plot(person.joints[t, [a, b], 2], person.joints[t, [a, b], 1], "k-", lw=1)
            side.plot(soles[t, :, 2], soles[t, :, 1], "r.", ms=4)
    heights.set(xlabel="time (s)", ylabel="lowest sole above the floor (cm)", title=f"{title}: every segment")
    side.axhline(0.0, color="g", lw=1)
    side.set(xlabel="z (m, towards the camera)", ylabel="y (m)", title=f"side view, frame {frame} (soles red)")
    side.set_aspect("equal")
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=80)
    plt.close(figure)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--videos", nargs="*", default=list(CLIPS), choices=list(CLIPS))
    parser.add_argument("--cache", type=Path, help="keep the 2D tracks here between runs")
    parser.add_argument("--weights", help="lifting weights (default: shipped)")
    parser.add_argument("--floor-images", type=Path, help="write capture_floor_<clip>.png here")
    parser.add_argument("--feet-images", type=Path, help="write capture_feet_<clip>.png here (the 'after' people)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    if not all((VIDEOS / CLIPS[n][0]).is_file() for n in args.videos):
        print(f"footage not found under {VIDEOS}", file=sys.stderr)
        return 1
    lifter, prior = load_lifter(args.weights), PosePrior.load()
    print("reprojection px (median / p95, keypoints of confidence >= 0.5); feet: skating cm/s, floating %, penetration cm")
    for name in args.videos:
        tracked = tracks(name, args.cache)
        people, fps, size, count = tracked.people, tracked.fps, tracked.size, tracked.frames
        segments = [s for person, obs in sorted(people.items()) for s in segments_of(person, obs, 3)]
        camera = default_camera(*size)
        print(f"\n{name}: {count} frames, {len(segments)} segments of {len(people)} people, "
              f"2D jitter {jitter(segments):.2f} px")
        for label, image_camera, refine in (("before", False, BEFORE), ("no still", True, NO_STILL),
                                            ("after", True, CaptureRefineConfig())):
            errors, (skating, floating, penetration), pose, world = run(name, segments, fps, camera, lifter, prior, image_camera, refine)
            print(f"  {label:8s} camera from {pose.source!r}: pitch {pose.pitch_deg:5.1f} deg, roll {pose.roll_deg:5.1f} "
                  f"deg, height {pose.height:.2f} m; skating {skating:5.1f} cm/s, floating {floating:4.1f}%, "
                  f"penetration {penetration:.2f} cm")
            print("         " + "  ".join(f"{k} {float(v.median()):5.1f} / {float(v.quantile(0.95)):5.1f}"
                                         for k, v in errors.items())
                  + f"  knees bent {knee_bend(world):5.1f} deg")
            if args.floor_images and label == "after" and pose.source == "people in the image":
                with open_frames(VIDEOS / CLIPS[name][0]) as frames:
                    image = next(im for index, _, im in frames if index >= min(CLIPS[name][1], count - 1))
                out = args.floor_images / f"capture_floor_{name}.png"
                out.parent.mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(out), cv2.cvtColor(draw_floor(image, camera, pose), cv2.COLOR_RGB2BGR))
            if args.feet_images and label == "after":
                feet_picture(world, CLIPS[name][1], f"{name}, {len(world)} segments", args.feet_images / f"capture_feet_{name}.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())

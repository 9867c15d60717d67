"""Standing height from one image: does fitting the body model to a person's 2D keypoints beat
video capture's fixed 165 cm default (humotion.capture.template.DEFAULT_HEIGHT)? One table.

    .venv/bin/python bench/height_from_image.py [--people 40] [--seed 0]
    .venv/bin/python bench/height_from_image.py --frames 12 [--people 12] [--stride 20]   # from a video

--frames T: the video version. Each person gets T frames of ONE held-out clip (every --stride-th
frame at 120 fps, from a random start, the clip's horizontal root motion scaled to the person's
height), one random camera for the whole clip (random_camera over all frames' points) and
detector-like noise with one window's biases and occluder (corrupt over the T frames). Estimate
(c): fit_shape_to_keypoint_frames, one shape for all frames, a pose and translation per frame;
with the assumed level 60-degree camera (as capture) and, as an upper bound, the true camera; on
exact keypoints; and on detector-like keypoints without the per-clip bias (bias 0, jitter 1; the
outliers, swaps and occluders kept). Measured (T = 12, stride 20, seeds 0 and 1 with --people 6,
pooled: 12 children + 12 adults, ~11 s per estimate on one CPU thread), median |error| (signed):
children default 30.9 cm (+30.9), video fit 35.5 (+35.5), true camera 39.4, exact keypoints 22.3;
adults default 15.1 (+5.2), video fit 15.5 (+10.6), exact keypoints 9.2. No win on detector-like
keypoints: the per-clip keypoint bias and the shape prior pull children towards adult heights.

People: --people children (standing height < 1.4 m) and --people adults (>= 1.4 m), shapes drawn
from the body model's population (body.sample_shapes: the Gaussian of its training subjects'
shape latents; children are about 8% of it, so both groups are filled by rejection), heights as
the model measures them (its rest mesh). Each gets one frame of real mocap of the CMU subjects
held out of the body model's training poses (MotionCollection.split()'s test subjects),
retargeted onto their own rig (body.pose_from_canonical). Views: one random camera each
(humotion.capture.keypoints.random_camera: any direction, 2.5-8 m, 45-90 degree lenses, 0.3-2.2
m high, VGA to full HD); the body's 21 detector keypoints (humotion.body.fitting's definitions)
projected and spoilt like a detector's (humotion.capture.keypoints.corrupt: per-keypoint bias
and jitter, outliers, left/right swaps, occluders, dropped and out-of-image keypoints).

Estimates: (a) the 165 cm default; (b) the height of the body fitted to the keypoints
(humotion.body.fitting.fit_to_keypoints: shape, pose and placement free; a level camera of 60
degrees assumed, as capture does, the true lens being unknown), on the detector-like keypoints
and, to tell the fit's limits from the detector's noise, on the exact ones. Errors: median
absolute error in cm and in % of the true height, and in brackets the median signed error (the
bias), cm. The bodies come from the fitted model itself, so the keypoints' definitions match
exactly and the shape prior is the population's own: a setting that favours (b).
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import torch

from humotion.body.fitting import body_points, fit_shape_to_keypoint_frames, fit_to_keypoints
from humotion.body.model import load_body_model, mesh_height
from humotion.canonical import to_canonical
from humotion.capture.detection import KEYPOINTS
from humotion.capture.keypoints import DetectorNoise, VirtualCamera, corrupt, random_camera
from humotion.capture.template import DEFAULT_HEIGHT
from humotion.io import load_motion

MOCAP = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "mocap"
HELD_OUT_CLIPS = ("cmu_cyun9601/amc/03", "cmu_sxaxmz/amc/06", "cmu_sxaxmz/amc/09", "cmu_sxaxmz/amc/93",
                  "cmu_visdoom_mocapplayer/amc/09_06-run.amc")
"""CMU subjects 03, 06, 09 and 93: the test subjects of MotionCollection.split() (seed 0) found in
the mocap folder (the body model's training poses come from its train subjects)."""
CHILD = 1.4
"""Metres: below this standing height a person counts as a child."""


def held_out_poses(count: int, generator: torch.Generator) -> torch.Tensor:
    """(count, 22, 4) canonical local rotations: a clip drawn uniformly, then a frame in its middle 80%."""
    paths = sorted(p for entry in HELD_OUT_CLIPS for p in ([MOCAP / entry] if (MOCAP / entry).is_file()
                                                           else (MOCAP / entry).iterdir()))
    clips = [to_canonical(load_motion(p)).rotations for p in paths]
    poses = []
    for c in torch.randint(len(clips), (count,), generator=generator).tolist():
        frames = len(clips[c])
        poses.append(clips[c][int(frames * (0.1 + 0.8 * torch.rand((), generator=generator)))])
    return torch.stack(poses)


def people(body, per_group: int, generator: torch.Generator) -> torch.Tensor:
    """(2 per_group, shape_latent) shape latents: per_group children, then per_group adults."""
    groups = [[], []]
    while min(len(g) for g in groups) < per_group:
        shapes = body.sample_shapes(1000, generator)
        with torch.no_grad():
            heights = mesh_height(body.decode_shape(shapes))
        for g, chosen in enumerate((heights < CHILD, heights >= CHILD)):
            groups[g].extend(shapes[chosen])
    return torch.stack(groups[0][:per_group] + groups[1][:per_group])


def filmed(body, shapes: torch.Tensor, generator: torch.Generator):
    """Per person: true height (m), exact and detector-like keypoints (P, 21, 2) pixels with
    their confidences (P, 21), and image sizes (P, 2) pixels."""
    canonical = held_out_poses(len(shapes), generator)
    pose = torch.cat([body.pose_from_canonical(c, shape=s[None]) for c, s in zip(canonical, shapes)])
    with torch.no_grad():
        out = body(shape=shapes, pose=pose)
    points = body_points(body, out.joints, out.vertices, KEYPOINTS)
    camera = random_camera(generator, torch.cat([points, out.joints], dim=1))
    pixels, depth = camera.project(points)
    exact, exact_confidence = corrupt(pixels[:, None], generator, DetectorNoise.none(), camera.size, depth[:, None])
    noisy, confidence = corrupt(pixels[:, None], generator, DetectorNoise(), camera.size, depth[:, None])
    return (mesh_height(out.rest_vertices), (exact[:, 0], exact_confidence[:, 0]), (noisy[:, 0], confidence[:, 0]),
            camera.size)


def assumed_camera(image_size, hfov_deg: float = 60.0) -> VirtualCamera:
    """A level camera with the given field of view, principal point at the image centre."""
    width, height = (float(x) for x in image_size)
    focal = width / 2 / math.tan(math.radians(hfov_deg) / 2)
    level = torch.diag(torch.tensor([1.0, -1.0, -1.0]))  # world Y up, looking along -Z
    return VirtualCamera(focal, focal, width / 2, height / 2, width, height, level, torch.zeros(3))


def estimate_height(body, keypoints: torch.Tensor, confidences: torch.Tensor, image_size,
                    hfov_deg: float = 60.0) -> float:
    """Standing height (m) of the body fitted to one person's keypoints (21, 2) pixels with
    confidences (21,), seen by a level camera with the given field of view at the image centre."""
    camera = assumed_camera(image_size, hfov_deg)
    return float(fit_to_keypoints(body, keypoints, confidences, camera).height[0])


def held_out_clip(frames: int, stride: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """(frames, 22, 4) canonical rotations and (frames, 3) root positions (m) of one held-out clip
    drawn uniformly (among those long enough; else the stride shrinks), every stride-th frame from
    a random start."""
    paths = sorted(p for entry in HELD_OUT_CLIPS for p in ([MOCAP / entry] if (MOCAP / entry).is_file()
                                                           else (MOCAP / entry).iterdir()))
    clip = to_canonical(load_motion(paths[int(torch.randint(len(paths), (1,), generator=generator))]))
    step = max(1, min(stride, (len(clip.rotations) - 1) // max(frames - 1, 1)))
    span = step * (frames - 1) + 1
    first = int(torch.randint(len(clip.rotations) - span + 1, (1,), generator=generator))
    chosen = torch.arange(first, first + span, step)[:frames]
    return clip.rotations[chosen], clip.root_positions[chosen]


def filmed_video(body, shape: torch.Tensor, frames: int, stride: int, generator: torch.Generator):
    """One person (shape (shape_latent,)) in a clip: true height (m), the camera, exact and
    detector-like keypoints ((T, 21, 2) pixels, (T, 21) confidences)."""
    canonical, root = held_out_clip(frames, stride, generator)
    pose = body.pose_from_canonical(canonical, shape=shape[None])
    with torch.no_grad():
        height = mesh_height(body.decode_shape(shape[None]))[0]
        moved = (root - root[:1]) * torch.tensor([1.0, 0.0, 1.0]) * height / 1.7   # horizontal motion, scaled
        out = body(shape=shape[None].expand(len(pose), -1), pose=pose, translation=moved)
    points = body_points(body, out.joints, out.vertices, KEYPOINTS)
    camera = random_camera(generator, torch.cat([points, out.joints], dim=1).reshape(-1, 3))
    pixels, depth = camera.project(points)
    exact = corrupt(pixels, generator, DetectorNoise.none(), camera.size, depth)
    noisy = corrupt(pixels, generator, DetectorNoise(), camera.size, depth)
    unbiased = corrupt(pixels, generator, DetectorNoise(bias=0.0, jitter=1.0), camera.size, depth)
    return height, camera, exact, noisy, unbiased


def video_main(body, args, generator: torch.Generator) -> None:
    """The --frames table: default vs the shared-shape fit over T frames."""
    shapes = people(body, args.people, generator)
    truth, columns, seconds = [], {"(a) default 165 cm": [], "(c) video fit, assumed camera": [],
                                   "(c) video fit, true camera": [], "(c) video fit, exact kp, assumed": [],
                                   "(c) video fit, no bias, assumed": []}, []
    for i, shape in enumerate(shapes):
        height, camera, exact, noisy, unbiased = filmed_video(body, shape, args.frames, args.stride, generator)
        truth.append(float(height))
        columns["(a) default 165 cm"].append(DEFAULT_HEIGHT)
        for name, (keypoints, confidences), cam in (
                ("(c) video fit, assumed camera", noisy, assumed_camera(camera.size)),
                ("(c) video fit, true camera", noisy, camera),
                ("(c) video fit, exact kp, assumed", exact, assumed_camera(camera.size)),
                ("(c) video fit, no bias, assumed", unbiased, assumed_camera(camera.size))):
            start = time.perf_counter()
            try:
                estimate = float(fit_shape_to_keypoint_frames(body, keypoints, confidences, cam).height[0])
            except ValueError:
                estimate = float("nan")
            seconds.append(time.perf_counter() - start)
            columns[name].append(estimate)
        print(f"  person {i}: true {100 * height:.1f} cm, " + ", ".join(
            f"{100 * v[-1]:.1f}" for k, v in columns.items() if k.startswith("(c)")), flush=True)
    truth = torch.tensor(truth)
    groups = {"children (< 1.4 m)": truth < CHILD, "adults (>= 1.4 m)": truth >= CHILD, "all": truth > 0}
    print(f"height from {args.frames} video frames (stride {args.stride} at 120 fps): median |error| (median "
          f"signed error), {len(truth)} people, {sum(seconds) / len(seconds):.1f} s per estimate")
    print(f"{'':34}" + "".join(f"{g:>28}" for g in groups))
    for name, estimates in columns.items():
        estimates = torch.tensor(estimates)
        ok = torch.isfinite(estimates)
        print(f"{name:34}" + "".join(f"{summary(estimates[rows & ok], truth[rows & ok]):>28}"
                                     for rows in groups.values()))


def summary(estimates: torch.Tensor, truth: torch.Tensor) -> str:
    error = estimates - truth
    cm, share = 100 * error.abs().median(), 100 * (error.abs() / truth).median()
    return f"{cm:5.1f} cm {share:5.1f}% ({100 * error.median():+5.1f})"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--people", type=int, default=40, help="children, and as many adults")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--frames", type=int, default=0, help="T > 0: the video version, T frames per person")
    parser.add_argument("--stride", type=int, default=20, help="video: frames apart at 120 fps")
    args = parser.parse_args()
    torch.set_num_threads(1)
    generator = torch.Generator().manual_seed(args.seed)
    body = load_body_model("low")
    if args.frames > 0:
        video_main(body, args, generator)
        return
    truth, exact, noisy, sizes = filmed(body, people(body, args.people, generator), generator)
    usable = ((exact[1] > 0).sum(1) >= 3) & ((noisy[1] > 0).sum(1) >= 3)
    start = time.perf_counter()
    columns = {"(a) default 165 cm": torch.full_like(truth, DEFAULT_HEIGHT)}
    for name, (keypoints, confidences) in (("(b) fit, exact keypoints", exact), ("(b) fit, detector-like", noisy)):
        columns[name] = torch.tensor([estimate_height(body, k, c, s) if ok else float("nan")
                                      for k, c, s, ok in zip(keypoints, confidences, sizes, usable)])
    seconds = (time.perf_counter() - start) / (2 * int(usable.sum()))
    groups = {"children (< 1.4 m)": truth < CHILD, "adults (>= 1.4 m)": truth >= CHILD, "all": truth > 0}
    print(f"height from one image: median |error| (median signed error), {int(usable.sum())} of {len(truth)} "
          f"people with 3+ keypoints, {seconds:.2f} s per estimate")
    print(f"{'':26}" + "".join(f"{g:>28}" for g in groups))
    for name, estimates in columns.items():
        print(f"{name:26}" + "".join(f"{summary(estimates[rows & usable], truth[rows & usable]):>28}"
                                     for rows in groups.values()))


if __name__ == "__main__":
    main()

"""Standing height from one image: does fitting the body model to a person's 2D keypoints beat
video capture's fixed 165 cm default (humotion.capture.template.DEFAULT_HEIGHT)? One table.

    .venv/bin/python bench/height_from_image.py [--people 40] [--seed 0]

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

from humotion.body.fitting import body_points, fit_to_keypoints
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


def estimate_height(body, keypoints: torch.Tensor, confidences: torch.Tensor, image_size,
                    hfov_deg: float = 60.0) -> float:
    """Standing height (m) of the body fitted to one person's keypoints (21, 2) pixels with
    confidences (21,), seen by a level camera with the given field of view at the image centre."""
    width, height = (float(x) for x in image_size)
    focal = width / 2 / math.tan(math.radians(hfov_deg) / 2)
    level = torch.diag(torch.tensor([1.0, -1.0, -1.0]))  # world Y up, looking along -Z
    camera = VirtualCamera(focal, focal, width / 2, height / 2, width, height, level, torch.zeros(3))
    return float(fit_to_keypoints(body, keypoints, confidences, camera).height[0])


def summary(estimates: torch.Tensor, truth: torch.Tensor) -> str:
    error = estimates - truth
    cm, share = 100 * error.abs().median(), 100 * (error.abs() / truth).median()
    return f"{cm:5.1f} cm {share:5.1f}% ({100 * error.median():+5.1f})"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--people", type=int, default=40, help="children, and as many adults")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    generator = torch.Generator().manual_seed(args.seed)
    body = load_body_model("low")
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

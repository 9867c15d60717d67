"""Feet on one floor (humotion.capture.camera, refine's E_floor and E_skate): a walk filmed by a
known camera (synthetic 2D keypoints projected from mocap, never presented as real) comes out
with planted feet on the floor and not sliding."""

from pathlib import Path

import numpy as np
import pytest
import torch

from humotion.canonical import to_canonical
from humotion.capture.camera import SOLES, contact_soles
from humotion.capture.keypoints import VirtualCamera, body_keypoints_3d
from humotion.capture.lifting import load_lifter
from humotion.capture.pipeline import (CaptureConfig, Segment, camera_pose, default_camera, initial_fit, refined,
                                       straightened, to_world)
from humotion.capture.prior import PosePrior
from humotion.capture.refine import CaptureRefineConfig

WALK = Path(__file__).resolve().parents[2] / "shared" / "data" / "mocap" / "cmu_sxaxmz" / "amc" / "16" / "16_18__walk.amc.gz"
FPS = 30.0


def foot_figures(soles: torch.Tensor, fps: float = FPS) -> tuple[float, float, torch.Tensor]:
    """(skating cm/s: mean horizontal speed of planted soles, penetration cm: mean depth under
    y = 0 of the lowest sole, planted (T, 4)) of world soles (T, 4, 3), Y up, floor at 0."""
    planted = contact_soles(soles, torch.tensor([0.0, 1.0, 0.0]), fps)
    still = planted[1:] & planted[:-1]
    speed = soles.diff(dim=0)[..., [0, 2]].norm(dim=-1) * fps
    skating = float(speed[still].mean()) * 100 if still.any() else 0.0
    penetration = float(soles[..., 1].amin(1).clamp_max(0).neg().mean()) * 100
    return skating, penetration, planted


@pytest.fixture(scope="module")
def filmed_walk():
    if not WALK.is_file():
        pytest.skip("mocap missing")
    from humotion.io import load_motion

    motion = to_canonical(load_motion(WALK)).resample(FPS)[:75]
    world_r, world_p = motion.world()
    world_p = world_p - torch.tensor([0.0, float(body_keypoints_3d(world_r, world_p, motion.skeleton)[..., SOLES, 1].min()), 0.0])
    keypoints = body_keypoints_3d(world_r, world_p, motion.skeleton)
    centre = world_p[:, 0].mean(0)
    intrinsics = default_camera(1280, 720)
    eye = centre + torch.tensor([4.0, 0.0, 5.0])
    eye[1] = 2.0
    camera = VirtualCamera.looking_at(eye, centre, 60.0, 1280, 720)
    pixels, _ = camera.project(keypoints)
    g = torch.Generator().manual_seed(0)
    pixels = pixels + 1.5 * torch.randn(pixels.shape, generator=g)
    return motion, keypoints, pixels, intrinsics


def test_a_filmed_walk_keeps_planted_feet_on_the_floor_without_sliding(filmed_walk):
    motion, keypoints, pixels, camera = filmed_walk
    torch.set_num_threads(1)
    truth_skate, truth_depth, _ = foot_figures(keypoints[:, SOLES])
    segment = Segment(0, np.arange(len(pixels)), np.arange(len(pixels)) / FPS, pixels, torch.ones(len(pixels), 21))
    config = CaptureConfig()
    fit = initial_fit(segment, camera, load_lifter(), motion.skeleton.height())
    pose = camera_pose([fit], [segment], FPS, config, [])
    fit = straightened(fit, segment, camera, pose)
    loose = to_world(refined(fit, segment, camera, PosePrior.load(), CaptureRefineConfig(floor=0, skate=0)),
                     segment, FPS, pose)
    held = to_world(refined(fit, segment, camera, PosePrior.load(), CaptureRefineConfig(), pose, FPS), segment, FPS, pose)
    loose_skate, _, _ = foot_figures(loose.keypoints[:, SOLES])
    skate, depth, planted = foot_figures(held.keypoints[:, SOLES])
    above = held.keypoints[:, SOLES, 1][planted]
    assert planted.any(1).float().mean() > 0.8                   # a walk plants a foot nearly all the time
    print(f"skating {skate:.1f} cm/s (without the foot terms {loose_skate:.1f}, truth {truth_skate:.1f}), "
          f"penetration {depth:.2f} cm (truth {truth_depth:.2f}), planted soles 90% within {float(above.abs().quantile(0.9)) * 100:.2f} cm")
    assert float(above.abs().quantile(0.9)) < 0.02               # planted soles on the floor within 2 cm
    assert depth < 2.0                                           # no sole more than 2 cm under it, on average
    assert skate < max(0.5 * loose_skate, truth_skate + 10.0), (skate, loose_skate, truth_skate)

"""Feet on one floor (humotion.capture.camera, refine's E_floor and E_skate): a walk filmed by a
known camera (synthetic 2D keypoints projected from mocap, never presented as real) comes out
with planted feet on the floor and not sliding."""

from pathlib import Path

import numpy as np
import pytest
import torch

from humotion.canonical import to_canonical
from humotion.capture.camera import SOLES, contact_soles, still_soles
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


def truth_sliding(soles: torch.Tensor, planted: torch.Tensor, fps: float = FPS) -> float:
    """cm/s: the mean horizontal speed of world soles (T, 4, 3) over the frames the truth plants
    (T, 4) on both sides of a step."""
    still = planted[1:] & planted[:-1]
    return float(soles.diff(dim=0)[..., [0, 2]].norm(dim=-1)[still].mean() * fps * 100)


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

    # the soles the truth plants slide less when those still in the image are held too
    truth_planted = foot_figures(keypoints[:, SOLES])[2]
    unheld = to_world(refined(fit, segment, camera, PosePrior.load(), CaptureRefineConfig(still_speed=0.0), pose, FPS),
                      segment, FPS, pose)
    sliding = [truth_sliding(person.keypoints[:, SOLES], truth_planted) for person in (held, unheld)]
    print(f"sliding on the truth's planted soles {sliding[0]:.1f} cm/s (without still soles {sliding[1]:.1f})")
    assert sliding[0] < 0.7 * sliding[1], sliding


def test_still_soles_reads_planted_feet_from_the_image_whatever_the_depth_says():
    """A sole whose pixels stay put is planted, even while the fit swings it 30 cm in depth; a
    sole that crosses the image is not, nor one held 40 cm up, nor one undetected with its ankle;
    a sole the detector does not give (MoveNet: no heels or toes) is judged by its ankle; the
    window is in seconds, so 10 fps footage is judged like 30 fps."""
    from humotion.capture.detection import KEYPOINTS

    for fps in (10.0, 30.0):
        t = torch.arange(int(fps)) / fps
        n = len(t)
        up = torch.tensor([0.0, -1.0, 0.0])
        soles = torch.zeros(n, 4, 3)
        soles[..., 2] = 5.0                                               # 5 m from the camera
        soles[:, 0, 2] += 0.3 * torch.sin(2 * torch.pi * 2 * t)            # the fit's depth swings
        soles[:, 3, 1] = -0.4                                             # held up (y is down)
        keypoints = torch.full((n, 21, 2), 400.0)
        keypoints[:, SOLES[1], 0] += 1000.0 * 1.2 * t / 5.0               # crosses at 1.2 m/s
        confidence = torch.ones(n, 21)
        right_heel, right_ankle = KEYPOINTS.index("right_heel"), KEYPOINTS.index("right_ankle")
        confidence[:, [right_heel, right_ankle]] = 0.1                     # undetected, ankle too
        still = still_soles(keypoints, confidence, t.double(), soles, up, focal=1000.0, max_speed=0.5)
        assert still[:, 0].all() and not still[:, 1:].any(), (fps, still.float().mean(0))

        movenet = confidence.clone()
        movenet[:, SOLES] = 0.0                                           # no heels or toes
        keypoints[:, KEYPOINTS.index("left_ankle"), 0] += 1000.0 * 1.2 * t / 5.0   # the left ankle moves
        still = still_soles(keypoints, movenet, t.double(), soles, up, focal=1000.0, max_speed=0.5)
        assert not still.any()
        keypoints[:, KEYPOINTS.index("left_ankle"), 0] = 400.0                        # and now stays
        assert still_soles(keypoints, movenet, t.double(), soles, up, focal=1000.0, max_speed=0.5)[:, :2].all()

"""Refinement after the network: fits the upper body to observations, leaves the legs alone."""

import pytest
import torch

from humotion import rotations as rot
from humotion.assets import demo_clip_path
from humotion.canonical import JOINTS, to_canonical
from humotion.io import load_motion
from humotion.motion import Motion
from humotion.sparse.refine import UPPER_JOINTS, RefineConfig, refine, robust_loss

HEAD_OFFSET = torch.tensor([0.0, 0.08, 0.09])
SENSORS = [JOINTS.index(j) for j in ("head", "left_wrist", "right_wrist")]


def observations(motion: Motion):
    r, p = motion.world()
    r, p = r[:, SENSORS], p[:, SENSORS].clone()
    p[:, 0] += (r[:, 0] @ HEAD_OFFSET[:, None])[..., 0]
    return r, p


@pytest.fixture(scope="module")
def truth() -> Motion:
    return to_canonical(load_motion(demo_clip_path()))[60:90]


def perturbed(truth: Motion) -> Motion:
    g = torch.Generator().manual_seed(0)
    rotvec = rot.convert(truth.rotations, "quat", "rotvec")
    for name in ("left_shoulder", "right_shoulder", "left_elbow", "spine2"):
        rotvec[:, JOINTS.index(name)] += torch.randn(3, generator=g) * 0.25
    return Motion(truth.skeleton, rot.convert(rotvec, "rotvec", "quat"), truth.root_positions + 0.03, truth.fps)


def wrist_error(motion: Motion, truth: Motion) -> float:
    return float((motion.world_positions()[:, SENSORS[1:]] - truth.world_positions()[:, SENSORS[1:]]).norm(dim=-1).mean())


def test_refinement_pulls_hands_to_observations_and_keeps_the_legs(truth):
    predicted = perturbed(truth)
    obs_r, obs_p = observations(truth)
    visible = torch.ones(len(truth), 2, dtype=torch.bool)
    fitted = refine(predicted, obs_r, obs_p, visible, HEAD_OFFSET, RefineConfig(robust=False))
    before, after = wrist_error(predicted, truth), wrist_error(fitted, truth)
    assert after < 0.25 * before, (before, after)
    legs = [i for i, j in enumerate(JOINTS) if j not in UPPER_JOINTS and j != "pelvis"]
    assert torch.equal(fitted.rotations[:, legs], predicted.rotations[:, legs])


def test_robust_term_resists_a_far_off_hand(truth):
    predicted = truth[:]
    obs_r, obs_p = observations(truth)
    obs_p = obs_p.clone()
    obs_p[10:, 1] += torch.tensor([0.0, 0.0, 0.6])  # the left hand "re-enters" 60 cm away
    visible = torch.ones(len(truth), 2, dtype=torch.bool)
    jump = {}
    for robust in (False, True):
        fitted = refine(predicted, obs_r, obs_p, visible, HEAD_OFFSET, RefineConfig(robust=robust))
        wrist = fitted.world_positions()[:, SENSORS[1]]
        jump[robust] = float(wrist.diff(dim=0).norm(dim=-1).max())
    assert jump[True] < 0.5 * jump[False], jump


def test_robust_loss_shape():
    r = torch.tensor([0.0, 0.05, 1.0])
    value = robust_loss(r, a=1.0, b=1.0, c=0.05)
    assert value[0] == 0 and value[1] < value[2]
    # near zero it is quadratic: rho ~ (r/c)^2 / 2 * b
    assert robust_loss(torch.tensor(1e-3), 1.0, 1.0, 0.05) == pytest.approx(0.5 * (1e-3 / 0.05) ** 2, rel=1e-3)
    # far away it grows like |r| for a = 1, far slower than the square
    assert robust_loss(torch.tensor(1.0), 1.0, 1.0, 0.05) < 25

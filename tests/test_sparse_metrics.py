"""Sparse-tracking metrics against hand-computed answers."""

import math

import pytest
import torch

from humotion import rotations as rot
from humotion.sparse import metrics


def test_position_metrics_known_answers():
    true = torch.zeros(10, 22, 3)
    pred = true.clone()
    pred[..., 0] += 0.03  # every joint 3 cm off, constantly
    assert metrics.mpjpe(pred, true) == pytest.approx(3.0)
    assert metrics.mpjve(pred, true, fps=30) == pytest.approx(0.0, abs=1e-5)
    assert metrics.mpjpe(pred, true, metrics.HANDS) == pytest.approx(3.0)
    # A joint moving at constant velocity has no jerk; a 1 cm step has a known jerk.
    steady = torch.arange(10.0)[:, None, None].expand(10, 22, 3) * 0.01
    assert metrics.jitter(steady, fps=30) == pytest.approx(0.0, abs=1e-4)
    step = torch.zeros(10, 22, 3)
    step[5:, :, 1] = 0.01
    # third differences of a unit step: 1, -2, 1 over three windows -> mean |jerk| over 7 windows
    expected = 0.01 * 30**3 * (1 + 2 + 1) / 7 / 100
    assert metrics.jitter(step, fps=30) == pytest.approx(expected, rel=1e-4)
    # velocity error: one joint moving 1 cm per frame at 30 fps against a still truth
    moving = torch.zeros(10, 22, 3)
    moving[:, 0, 0] = torch.arange(10.0) * 0.01
    assert metrics.mpjve(moving, torch.zeros(10, 22, 3), fps=30) == pytest.approx(30.0 / 22, rel=1e-4)


def test_rotation_error_in_degrees():
    true = rot.quat_to_matrix(rot.quat_identity(5, 22))
    pred = rot.convert(torch.tensor([0.0, 0.0, math.radians(10)]).expand(5, 22, 3), "rotvec", "matrix")
    assert metrics.mpjre(pred, true) == pytest.approx(10.0, abs=1e-3)
    scores = metrics.evaluate(torch.zeros(5, 22, 3), torch.zeros(5, 22, 3), pred, true, fps=30)
    assert set(scores) == {"MPJRE", "MPJPE", "MPJVE", "Jitter", "hand", "upper", "lower"}


def test_unseen_hand_error_counts_only_the_frames_a_hand_is_not_seen():
    from humotion.canonical import JOINTS

    true = torch.zeros(4, 22, 3)
    pred = true.clone()
    pred[:, JOINTS.index("left_wrist"), 0] = 0.03       # 3 cm off on every frame
    pred[:, JOINTS.index("right_wrist"), 1] = 0.01      # 1 cm off on every frame
    visible = torch.tensor([[1, 0], [0, 1], [0, 1], [1, 1]], dtype=torch.bool)
    error, count = metrics.unseen_hand_error(pred, true, visible)
    assert count == 3 and error == pytest.approx((3 + 3 + 1) / 3, rel=1e-5)
    error, count = metrics.unseen_hand_error(pred, true, torch.ones(4, 2, dtype=torch.bool))
    assert count == 0 and math.isnan(error)


def test_body_halves_cover_every_joint_once():
    from humotion.canonical import JOINTS

    assert sorted(metrics.UPPER_BODY + metrics.LOWER_BODY) == sorted(JOINTS)


def test_reach_error_counts_only_seen_hands_within_the_arms_length():
    from humotion.canonical import JOINTS

    pred = torch.zeros(3, 22, 3)
    pred[:, JOINTS.index("right_shoulder")] = torch.tensor([1.0, 0.0, 0.0])
    hands = torch.zeros(3, 2, 3)
    hands[:, 0, 0] = torch.tensor([0.4, 0.5, 0.8])           # left hand from its shoulder (at 0): in, at, beyond reach
    hands[:, 1] = torch.tensor([1.0, 0.3, 0.0])              # right: 0.3 m away, always in reach
    pred[:, JOINTS.index("left_wrist")] = hands[:, 0] - torch.tensor([0.02, 0.0, 0.0])   # 2 cm short
    pred[:, JOINTS.index("right_wrist")] = hands[:, 1]
    visible = torch.tensor([[True, True], [True, False], [True, True]])
    error, count, beyond = metrics.reach_error(pred, hands, visible, [0.5, 0.5])
    assert count == 4 and error == pytest.approx((2 + 2 + 0 + 0) / 4, rel=1e-4)
    assert beyond == pytest.approx(100 / 5)                    # the left hand 0.8 m away on frame 2
    assert metrics.target_error(pred, hands, visible)[0] == pytest.approx(6 / 5, rel=1e-4)
    assert math.isnan(metrics.reach_error(pred, hands, torch.zeros(3, 2, dtype=torch.bool), [0.5, 0.5])[2])

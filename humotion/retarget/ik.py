"""Analytic two-bone inverse kinematics (hip-knee-ankle, shoulder-elbow-wrist), batched over frames.

The limb keeps its plane where it can: the middle joint bends within the plane of the three
joints, then the whole limb swings about its root onto the target. A straight limb has no plane;
then it bends towards a hint direction (forward for knees).
"""

from __future__ import annotations

import torch

from humotion import rotations as rot


def _angle(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    cos = (torch.nn.functional.normalize(u, dim=-1) * torch.nn.functional.normalize(v, dim=-1)).sum(-1)
    return torch.acos(cos.clamp(-1.0, 1.0))


def _turn(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """(T, 3, 3) rotations by angle (T,) about unit axis (T, 3)."""
    return rot.convert(axis * angle[:, None], "rotvec", "matrix")


def two_bone_ik(a: torch.Tensor, b: torch.Tensor, c: torch.Tensor, target: torch.Tensor,
                hint: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """World-space turns that bring the end joint c onto the target.

    a, b, c: (T, 3) world positions of the root, middle and end joints (metres).
    target: (T, 3) where c should go; out of reach, the limb points at it, straight.
    hint: (T, 3) direction the middle joint bends towards when the limb is straight.
    Returns (turn_root, turn_mid), both (T, 3, 3): the new world rotation of the root joint (and
    of every joint between root and middle) is turn_root @ old; that of the middle joint (and of
    every joint between middle and end) is turn_mid @ old.
    """
    eps = 1e-6
    upper, lower = (b - a).norm(dim=-1), (c - b).norm(dim=-1)
    reach = (target - a).norm(dim=-1).clamp(min=eps + (upper - lower).abs(), max=(upper + lower) * (1 - 1e-4))
    now_root, now_mid = _angle(c - a, b - a), _angle(a - b, c - b)
    swing = _angle(c - a, target - a)
    want_root = torch.acos(((lower**2 - upper**2 - reach**2) / (-2 * upper * reach)).clamp(-1, 1))
    want_mid = torch.acos(((reach**2 - upper**2 - lower**2) / (-2 * upper * lower)).clamp(-1, 1))

    plane = torch.linalg.cross(c - a, b - a)
    fallback = torch.linalg.cross(c - a, hint)
    straight = plane.norm(dim=-1, keepdim=True) < 1e-3 * (upper * (c - a).norm(dim=-1))[:, None]
    bend_axis = torch.nn.functional.normalize(torch.where(straight, fallback, plane), dim=-1)
    swing_axis = torch.linalg.cross(c - a, target - a)
    swing = torch.where(swing_axis.norm(dim=-1) > eps, swing, torch.zeros_like(swing))
    swing_axis = torch.nn.functional.normalize(swing_axis, dim=-1)

    bend_root = _turn(bend_axis, want_root - now_root)
    bend_mid = _turn(bend_axis, want_mid - now_mid)
    to_target = _turn(swing_axis, swing)
    # Order, in world space: bend the middle joint, turn the limb back onto its old line, swing.
    turn_root = to_target @ bend_root
    return turn_root, turn_root @ bend_mid

"""Anatomical joint limits checked on 3D joint positions of the canonical skeleton: how often a
network or a fit bends a joint in a way no body can.

Measured from positions alone, so it applies to a lifter's raw output as well as to a fitted
motion (a twist about a bone cannot be seen in positions and is not checked). The trunk frame:
left = left hip - right hip, up = pelvis -> spine3 made perpendicular to it, forward = left x up.

Limits (degrees), generous: ground-truth CMU motion of the test subjects stays inside all of them
(largest values on 3,222 frames, 20 s per clip: knee flexion 125, elbow flexion 141, hip flexion 125,
hip extension 26, neck bend 40):
- knee: bent the wrong way (against the hips' left axis) by more than 10, or flexed past 160;
- elbow: flexed past 160 (the upper arm's twist decides the bending direction, so hyperextension
  is not visible in positions);
- hip: the thigh flexed forward past 150 or extended backward past 45 from the trunk axis, in
  the trunk's sagittal plane;
- neck: the head (neck -> head) bent more than 75 from the upper spine (spine3 -> neck).
"""

from __future__ import annotations

import torch

from humotion.canonical import JOINTS

LIMITS_DEG = {"knee_hyperextension": 10.0, "knee_flexion": 160.0, "elbow_flexion": 160.0,
              "hip_flexion": 150.0, "hip_extension": 45.0, "neck_bend": 75.0}
_J = {name: index for index, name in enumerate(JOINTS)}


def _unit(v: torch.Tensor) -> torch.Tensor:
    return v / v.norm(dim=-1, keepdim=True).clamp_min(1e-9)


def _angle(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Angle (degrees) between vectors a and b (..., 3)."""
    return torch.rad2deg(torch.arccos((_unit(a) * _unit(b)).sum(-1).clamp(-1.0, 1.0)))


def joint_angles_deg(joints: torch.Tensor) -> dict[str, torch.Tensor]:
    """The angles the limits apply to, (T,) degrees each per side ("left_knee_flexion", ...):
    joints (T, 22, 3) canonical-skeleton positions in any frame and unit."""
    p = joints
    left = _unit(p[:, _J["left_hip"]] - p[:, _J["right_hip"]])
    up = p[:, _J["spine3"]] - p[:, _J["pelvis"]]
    up = _unit(up - (up * left).sum(-1, keepdim=True) * left)
    forward = torch.cross(left, up, dim=-1)
    angles = {"neck_bend": _angle(p[:, _J["head"]] - p[:, _J["neck"]], p[:, _J["neck"]] - p[:, _J["spine3"]])}
    for side in ("left", "right"):
        thigh = p[:, _J[f"{side}_knee"]] - p[:, _J[f"{side}_hip"]]
        shank = p[:, _J[f"{side}_ankle"]] - p[:, _J[f"{side}_knee"]]
        knee = _angle(thigh, shank)
        backwards = (torch.cross(thigh, shank, dim=-1) * left).sum(-1) < 0
        angles[f"{side}_knee_flexion"] = knee
        angles[f"{side}_knee_hyperextension"] = torch.where(backwards, knee, torch.zeros_like(knee))
        angles[f"{side}_elbow_flexion"] = _angle(p[:, _J[f"{side}_elbow"]] - p[:, _J[f"{side}_shoulder"]],
                                                 p[:, _J[f"{side}_wrist"]] - p[:, _J[f"{side}_elbow"]])
        hip = torch.rad2deg(torch.atan2((thigh * forward).sum(-1), -(thigh * up).sum(-1)))
        angles[f"{side}_hip_flexion"], angles[f"{side}_hip_extension"] = hip, -hip
    return angles


def past_limits(joints: torch.Tensor) -> dict[str, torch.Tensor]:
    """Per limit of LIMITS_DEG, (T,) bool: frames where either side is past it. joints (T, 22, 3)."""
    angles = joint_angles_deg(joints)
    return {limit: torch.stack([value > bound for name, value in angles.items() if name.endswith(limit)]).any(0)
            for limit, bound in LIMITS_DEG.items()}


def share_past_limits(joints: torch.Tensor) -> float:
    """Share (0-1) of frames with any joint past its limit; joints (T, 22, 3)."""
    return float(torch.stack(list(past_limits(joints).values())).any(0).float().mean())

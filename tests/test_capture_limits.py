"""Anatomical limits on joint positions: real motion stays inside, broken poses are flagged."""

import torch

from humotion.canonical import JOINTS, to_canonical
from humotion.capture.limits import LIMITS_DEG, joint_angles_deg, past_limits, share_past_limits
from humotion.io import load_motion


def walk(mocap):
    """6 s of a held-out subject's walk (07) and its (T, 22, 3) joints."""
    motion = to_canonical(load_motion(mocap / "cmu_visdoom_mocapplayer" / "amc" / "07_01-walk.amc")).resample(30.0)
    return motion.world_positions()


def test_real_walk_stays_inside_every_limit(mocap):
    joints = walk(mocap)
    assert share_past_limits(joints) == 0.0
    angles = joint_angles_deg(joints)
    assert 40 < angles["left_knee_flexion"].max() < 90      # a walking swing knee
    assert angles["left_knee_hyperextension"].max() < 10


def test_known_angles_of_a_rest_pose(mocap):
    joints = walk(mocap)[:1]
    straight = joints.clone()      # upright trunk facing +Z, legs hanging straight down under the hips
    straight[0, [JOINTS.index(j) for j in ("pelvis", "spine3")]] = torch.tensor([[0.0, 1.0, 0.0], [0.0, 1.4, 0.0]])
    straight[0, [JOINTS.index(j) for j in ("left_hip", "right_hip")]] = torch.tensor([[0.1, 0.95, 0.0], [-0.1, 0.95, 0.0]])
    for side in ("left", "right"):
        hip = straight[0, JOINTS.index(f"{side}_hip")]
        straight[0, JOINTS.index(f"{side}_knee")] = hip - torch.tensor([0.0, 0.4, 0.0])
        straight[0, JOINTS.index(f"{side}_ankle")] = hip - torch.tensor([0.0, 0.8, 0.0])
    angles = joint_angles_deg(straight)
    assert abs(float(angles["left_knee_flexion"][0])) < 1e-3 and abs(float(angles["right_hip_flexion"][0])) < 1e-3
    kicked = straight.clone()        # left thigh pointing straight forward (+Z), shank down: a 90 deg hip, 90 deg knee
    hip = kicked[0, JOINTS.index("left_hip")]
    kicked[0, JOINTS.index("left_knee")] = hip + torch.tensor([0.0, 0.0, 0.4])
    kicked[0, JOINTS.index("left_ankle")] = hip + torch.tensor([0.0, -0.4, 0.4])
    angles = joint_angles_deg(kicked)
    assert torch.allclose(angles["left_hip_flexion"], torch.tensor([90.0]), atol=1e-3)
    assert torch.allclose(angles["left_knee_flexion"], torch.tensor([90.0]), atol=1e-3)
    assert float(angles["left_knee_hyperextension"][0]) == 0.0


def test_a_knee_bent_backwards_and_a_folded_elbow_are_flagged(mocap):
    joints = walk(mocap)[:40].clone()
    hip, knee, ankle = (JOINTS.index(f"left_{j}") for j in ("hip", "knee", "ankle"))
    left = joints[:, hip] - joints[:, JOINTS.index("right_hip")]
    forward = torch.nn.functional.normalize(torch.cross(left, torch.tensor([0.0, 1.0, 0.0]).expand_as(left), dim=-1), dim=-1)[10:20]
    broken = joints.clone()
    broken[10:20, ankle] = broken[10:20, knee] + 0.3 * forward          # shank kicked forward: reversed knee ...
    broken[10:20, knee] = broken[10:20, hip] - torch.tensor([0.0, 0.4, 0.0]) - 0.2 * forward   # ... thigh back
    shoulder, elbow, wrist = (JOINTS.index(f"right_{j}") for j in ("shoulder", "elbow", "wrist"))
    broken[30:35, wrist] = broken[30:35, shoulder] + 0.02 * (broken[30:35, elbow] - broken[30:35, shoulder])  # folded flat
    flags = past_limits(broken)
    assert set(flags) == set(LIMITS_DEG)
    assert flags["knee_hyperextension"][10:20].all() and not flags["knee_hyperextension"][:10].any()
    assert flags["elbow_flexion"][30:35].all() and flags["elbow_flexion"].sum() == 5
    assert share_past_limits(broken) == (10 + 5) / 40

"""Headset signals synthesised from canonical motion: eyes, hands, frames, velocities, frustum."""

import math

import pytest
import torch

from humotion import rotations as rot
from humotion.canonical import JOINTS, canonical_skeleton, to_canonical
from humotion.io import load_motion
from humotion.motion import Motion
from humotion.sparse import signals as sg
from humotion.sparse.signals import COMPONENTS, Dropout, Frustum, hand_visibility

EYE = torch.tensor([0.0, 1.6, 0.0])
I3 = torch.eye(3)


def sixd(matrix: torch.Tensor) -> torch.Tensor:
    return rot.convert(matrix, "matrix", "sixd")


def yaw(degrees: float) -> torch.Tensor:
    """Rotation about +Y; positive turns +Z (forward) towards +X (the left)."""
    return rot.quat_to_matrix(rot.euler_to_quat("Y", torch.tensor([float(degrees)])))


def seen(hand, head_rotation=I3, frustum=Frustum()) -> bool:
    hands = torch.stack([torch.as_tensor(hand, dtype=torch.float32), torch.tensor([0.0, -5.0, 0.0])])
    return bool(hand_visibility(head_rotation, EYE, hands, frustum)[0])


def at_angle(horizontal_deg=0.0, below_deg=0.0, distance=0.5) -> torch.Tensor:
    """A point at a distance from the eyes, turned left (+X) and below the head's forward axis."""
    h, v = math.radians(horizontal_deg), math.radians(below_deg)
    return EYE + distance * torch.tensor([math.cos(v) * math.sin(h), -math.sin(v), math.cos(v) * math.cos(h)])


def test_frustum_cases():
    assert seen(at_angle(0, 0, 0.5))                          # straight ahead at 0.5 m
    assert not seen(EYE + torch.tensor([0.0, 0.0, -0.5]))    # behind the head
    assert not seen(at_angle(0, 0, 1.5))                      # beyond far (1.2 m)
    assert not seen(at_angle(0, 0, 0.05))                     # nearer than near
    assert not seen(at_angle(70, 0, 0.5))                     # 70 deg to the side, fov 120
    assert not seen(at_angle(-70, 0, 0.5))
    assert seen(at_angle(50, 0, 0.5)) and seen(at_angle(-50, 0, 0.5))
    # 70 deg below the forward axis: outside a level 120 deg view, inside once tilted down 20 deg.
    assert not seen(at_angle(0, 70, 0.5), frustum=Frustum(tilt_down_deg=0.0))
    assert seen(at_angle(0, 70, 0.5))
    assert not seen(at_angle(0, -50, 0.5))                    # 50 deg above: 70 deg off the tilted axis
    # Turning the head 90 deg to the left: a hand that turned with it (now on the +X side) stays
    # visible, the one straight ahead of the old facing is now at 90 deg and is not.
    turned = yaw(90)
    assert seen(EYE + turned @ torch.tensor([0.0, -0.1, 0.5]), turned)
    assert (turned @ torch.tensor([0.0, 0.0, 1.0]))[0] > 0.99
    assert not seen(at_angle(0, 0, 0.5), turned)
    with pytest.raises(ValueError):
        Frustum(horizontal_fov_deg=180)


def test_sixd_of_identity_and_constant_motion_velocities():
    assert sixd(I3).tolist() == [1, 0, 0, 0, 1, 0]
    skeleton = canonical_skeleton()
    motion = Motion.rest(skeleton, frames=5)
    motion.rotations[:, JOINTS.index("head")] = rot.euler_to_quat("XYZ", torch.tensor([10.0, 30.0, -5.0]))
    s = sg.signals_from_motion(motion)
    rest = torch.tensor(sg.REST_VELOCITY)
    for name in COMPONENTS:
        assert s[name].shape == (5, 9) and s[f"{name}_vel"].shape == (5, 9)
        assert torch.allclose(s[f"{name}_vel"], rest.expand(5, 9), atol=1e-6), name
    # A moving, turning head: velocity = the step, first frame at rest.
    rotations = torch.stack([yaw(10 * t) for t in range(4)])
    positions = torch.stack([torch.tensor([0.0, 1.6, 0.1 * t]) for t in range(4)])
    poses_r = torch.stack([rotations, rotations, rotations], dim=-3)
    poses_p = torch.stack([positions, positions, positions], dim=-2)
    s = sg.pose_signals(poses_r, poses_p)
    assert torch.allclose(s["head_vel"][0], rest)
    assert torch.allclose(s["head_vel"][1:, 6:], torch.tensor([0.0, 0.0, 0.1]).expand(3, 3), atol=1e-6)
    assert torch.allclose(s["head_vel"][1:, :6], sixd(yaw(10)).expand(3, 6), atol=1e-6)


def test_hand_at_the_head_is_identity_in_head_frame():
    r = yaw(37).expand(2, 3, 3, 3)
    p = torch.tensor([0.3, 1.5, -0.2]).expand(2, 3, 3)
    s = sg.pose_signals(r, p)
    for side in ("left_in_head", "right_in_head"):
        assert torch.allclose(s[side], torch.tensor([1.0, 0, 0, 0, 1, 0, 0, 0, 0]).expand(2, 9), atol=1e-6)


def test_hand_in_head_frame_is_head_relative():
    head_r = yaw(90)
    r = torch.stack([head_r, head_r, I3])[None]
    p = torch.stack([torch.tensor([0.0, 1.6, 0.0]), torch.tensor([0.4, 1.3, 0.0]), torch.zeros(3)])[None]
    s = sg.pose_signals(r, p)
    # The head faces +X (its left); a hand 0.4 m along +X is 0.4 m in front of it, 0.3 m below.
    assert torch.allclose(s["left_in_head"][0, 6:], torch.tensor([0.0, -0.3, 0.4]), atol=1e-6)
    assert torch.allclose(s["left_in_head"][0, :6], sixd(I3), atol=1e-6)
    assert torch.allclose(s["right_in_head"][0, :6], sixd(head_r.T), atol=1e-6)


def test_head_signal_is_at_the_eyes():
    skeleton = canonical_skeleton(1.70)
    s = sg.signals_from_motion(Motion.rest(skeleton, 2))
    rest = dict(zip(skeleton.names, skeleton.rest_positions()))
    eyes = s["head"][0, 6:]
    above, forward = (eyes - rest["head"])[1], (eyes - rest["head"])[2]
    assert 0.03 < above < 0.08 and 0.06 < forward < 0.11, eyes - rest["head"]
    assert eyes[1] == pytest.approx(0.936 * 1.70, abs=1e-4)
    assert torch.allclose(s["left"][0, 6:], rest["left_wrist"]) and torch.allclose(s["right"][0, 6:], rest["right_wrist"])
    assert torch.allclose(s["head"][0, :6], sixd(I3))
    # Scaled body, scaled eyes.
    assert torch.allclose(sg.eye_offset(canonical_skeleton(1.87)), sg.eye_offset(skeleton) * 1.1, atol=1e-6)


def test_batched_shapes_and_gradients():
    skeleton = canonical_skeleton()
    local = rot.quat_to_matrix(rot.euler_to_quat("XYZ", torch.randn(2, 3, 7, 22, 3) * 20))
    local.requires_grad_(True)
    from humotion.skeleton import forward_kinematics
    world_r, world_p = forward_kinematics(local, torch.zeros(2, 3, 7, 3), skeleton.offsets, skeleton.parents)
    eye = sg.eye_offset(skeleton).expand(2, 3, 3)
    s = sg.headset_signals(world_r, world_p, eye)
    for name in COMPONENTS:
        assert s[name].shape == (2, 3, 7, 9) and s[f"{name}_vel"].shape == (2, 3, 7, 9)
    assert s["visible"].shape == (2, 3, 7, 2) and bool((s["visible"] == 1).all())
    assert sg.stack_components(s).shape == (2, 3, 7, 5, 18)
    same = sg.headset_signals(world_r, world_p, skeleton)
    assert torch.allclose(same["head"], s["head"])
    sum(v.sum() for v in s.values()).backward()
    assert local.grad is not None and torch.isfinite(local.grad).all()
    rotations, positions = sg.device_poses(world_r, world_p, eye)
    assert hand_visibility(rotations[..., 0, :, :], positions[..., 0, :], positions[..., 1:, :]).shape == (2, 3, 7, 2)
    centred = sg.recentre(s)
    assert torch.allclose(centred["head"][..., 0, [6, 8]], torch.zeros(2, 3, 2), atol=1e-6)
    assert torch.allclose(centred["head"][..., 7], s["head"][..., 7])
    assert torch.allclose(centred["left_in_head"], s["left_in_head"])


def test_hide_unseen_and_dropouts():
    r = torch.stack([yaw(5 * t) for t in range(6)])[:, None].expand(6, 3, 3, 3)
    p = torch.arange(6.0)[:, None, None].expand(6, 3, 3) * 0.1
    visible = torch.tensor([[1, 0], [0, 0], [1, 1], [1, 1], [0, 1], [1, 1]], dtype=torch.bool)
    s = sg.hide_unseen(sg.pose_signals(r, p, visible))
    rest = torch.tensor(sg.REST_VELOCITY)
    assert (s["left"][1] == 0).all() and (s["left_in_head_vel"][4] == 0).all() and (s["right"][0] == 0).all()
    assert torch.equal(s["left_vel"][2], rest) and torch.equal(s["right_vel"][2], rest)   # re-entry
    assert torch.allclose(s["left_vel"][3, 6:], torch.full((3,), 0.1)) and (s["left"][3] != 0).any()
    assert torch.equal(s["head"], sg.pose_signals(r, p, visible)["head"])
    # Dropouts: reproducible with a generator, only remove visibility, about the asked rate.
    g = torch.Generator().manual_seed(0)
    ones = torch.ones(50, 2000, 2, dtype=torch.bool)
    lost = ~sg.random_dropouts(ones, rate_per_s=0.5, mean_duration_s=0.4, fps=30, generator=g)
    expected = 0.5 * 0.4 / (1 + 0.5 * 0.4)   # fraction of time inside a span (renewal, approx.)
    assert abs(lost.float().mean().item() - expected) < 0.03
    assert not sg.random_dropouts(torch.zeros(3, 100, 2, dtype=torch.bool), 1.0, 0.2, 30).any()
    assert sg.random_dropouts(ones[:1], 0.0, 0.4, 30).all()


def test_frame_signals_are_the_stream_signals_of_that_frame():
    g = torch.Generator().manual_seed(3)
    r = rot.convert(torch.randn(6, 3, 3, generator=g) * 0.6, "rotvec", "matrix")
    p = torch.randn(6, 3, 3, generator=g)
    visible = torch.tensor([[1, 0], [0, 0], [1, 1], [1, 1], [0, 1], [1, 1]], dtype=torch.bool)
    stream = sg.hide_components(sg.component_signals(r, p), visible)                  # (6, 5, 18)
    seen = torch.cat([torch.ones(6, 1, dtype=torch.bool), visible[:, list(sg.HAND_OF)]], dim=1)
    for t in range(6):
        before = max(t - 1, 0)
        frame = sg.frame_signals(r[t], p[t], visible[t].float(), r[before], p[before], visible[before].float())
        assert torch.allclose(frame[seen[t]], stream[t][seen[t]], atol=1e-6), t  # unseen hands: never read


@pytest.fixture(scope="module")
def walking(mocap):
    return to_canonical(load_motion(mocap / "cmu_mocgui_s02" / "02_01.amc"))


def test_real_clip_visibility(walking, mocap):
    mc = sg.signals_from_motion(walking, "MC")
    assert bool((mc["visible"] == 1).all())
    ht = sg.signals_from_motion(walking, "HT")
    fraction = ht["visible"].mean(0)
    print(f"02_01 (walk) HT visible fraction left {fraction[0]:.2f} right {fraction[1]:.2f}")
    assert 0.0 < fraction.mean() < 0.4  # walking, arms mostly down: hands mostly below the view
    for name in COMPONENTS:
        assert torch.isfinite(ht[name]).all() and torch.allclose(ht[name], mc[name])
    # Eyes ride in front of the head joint along the head's facing and about at eye height.
    world_r, world_p = walking.world()
    head = JOINTS.index("head")
    ahead = ((ht["head"][:, 6:] - world_p[:, head])[:, None, :] @ world_r[:, head, :, 2:]).flatten()
    assert (ahead > 0.05).all()
    dropped = sg.signals_from_motion(walking, "MC", dropout=Dropout(2.0, 0.3), generator=torch.Generator().manual_seed(1))
    assert 0.2 < dropped["visible"].mean() < 0.9
    punch = to_canonical(load_motion(mocap / "cmu_mocgui_s02" / "02_05.amc"))
    fraction = sg.signals_from_motion(punch, "HT")["visible"].mean(0)
    print(f"02_05 (punch) HT visible fraction left {fraction[0]:.2f} right {fraction[1]:.2f}")
    assert fraction.mean() > 0.2

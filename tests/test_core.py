"""Skeleton, Motion and rotation forms against hand-computed answers."""

import math

import numpy as np
import pytest
import torch

from humotion import Motion, Skeleton, forward_kinematics
from humotion.skeleton import local_rotations
from humotion import rotations as rot


def arm() -> Skeleton:
    """root at (0, 1, 0); a left arm 0.3 + 0.25 m along +X; a mirrored right arm."""
    return Skeleton(
        ["root", "left_shoulder", "left_elbow", "right_shoulder", "right_elbow"],
        [-1, 0, 1, 0, 3],
        [[0, 1, 0], [0.2, 0.3, 0], [0.3, 0, 0], [-0.2, 0.3, 0], [-0.3, 0, 0]],
        end_site_parents=[2, 4],
        end_site_offsets=[[0.25, 0, 0], [-0.25, 0, 0]],
    )


def random_motion(skeleton: Skeleton, frames: int = 40, seed: int = 0) -> Motion:
    g = torch.Generator().manual_seed(seed)
    q = rot.convert(torch.randn(frames, skeleton.num_joints, 3, generator=g) * 0.6, "rotvec", "quat")
    return Motion(skeleton, q, torch.randn(frames, 3, generator=g), fps=30.0)


def test_rest_pose_and_quarter_turn():
    skeleton = arm()
    motion = Motion.rest(skeleton, frames=2)
    pos = motion.world_positions()[0]
    assert torch.allclose(pos[2], torch.tensor([0.5, 1.3, 0.0]))
    assert torch.allclose(motion.end_site_positions()[0, 0], torch.tensor([0.75, 1.3, 0.0]))
    # Turn the left shoulder 90 degrees about +Z: the arm then points up (+Y).
    q = motion.rotations.clone()
    q[:, 1] = rot.convert(torch.tensor([0, 0, math.pi / 2]), "rotvec", "quat")
    bent = Motion(skeleton, q, motion.root_positions, 30.0)
    assert torch.allclose(bent.world_positions()[0, 2], torch.tensor([0.2, 1.6, 0.0]), atol=1e-6)
    assert torch.allclose(bent.end_site_positions()[0, 0], torch.tensor([0.2, 1.85, 0.0]), atol=1e-6)
    transforms = bent.world_transforms()
    assert transforms.shape == (2, 5, 4, 4)
    assert torch.allclose(transforms[0, 2, :3, 3], bent.world_positions()[0, 2])


def test_forward_kinematics_takes_numpy_returns_torch_batched_and_differentiable():
    skeleton = arm()
    motion = random_motion(skeleton)
    _, pos = forward_kinematics(motion.rotations.numpy(), motion.root_positions.numpy(), skeleton.offsets, skeleton.parents)
    assert isinstance(pos, torch.Tensor) and pos.dtype == torch.float32       # one return type, whatever came in
    np.testing.assert_allclose(pos, motion.world_positions().numpy(), atol=1e-6)
    batch = motion.rotations.view(4, 10, 5, 4)
    _, pos_b = forward_kinematics(batch, motion.root_positions.view(4, 10, 3), skeleton.offsets, skeleton.parents)
    assert torch.allclose(pos_b.reshape(40, 5, 3), motion.world_positions(), atol=1e-6)
    rotvec = torch.zeros(5, 3, requires_grad=True)
    _, p = forward_kinematics(rot.convert(rotvec, "rotvec", "matrix"), torch.zeros(3), skeleton.offsets, skeleton.parents)
    p[2, 1].backward()
    assert rotvec.grad[1].abs().sum() > 0  # the shoulder angle moves the elbow


def test_local_rotations_undo_forward_kinematics():
    skeleton = arm()
    motion = random_motion(skeleton)
    world, _ = motion.world()
    local = local_rotations(world, skeleton.parents)
    torch.testing.assert_close(local, rot.quat_to_matrix(motion.rotations), rtol=0, atol=1e-5)


def test_rotation_forms_round_trip():
    q = rot.convert(torch.randn(100, 3), "rotvec", "quat")
    for form in ("matrix", "rotvec", "sixd"):
        back = rot.convert(rot.convert(q, "quat", form), form, "quat")
        assert torch.allclose(back, q, atol=1e-5), form
    euler = rot.quat_to_euler("ZYX", q)
    assert torch.allclose(rot.euler_to_quat("ZYX", euler), q, atol=1e-5)
    # intrinsic ZYX is Rz @ Ry @ Rx
    angles = torch.tensor([30.0, 20.0, 10.0])
    rz, ry, rx = (rot.convert(torch.tensor(v) * math.pi / 180, "rotvec", "matrix") for v in ([0, 0, 30.0], [0, 20.0, 0], [10.0, 0, 0]))
    assert torch.allclose(rot.quat_to_matrix(rot.euler_to_quat("ZYX", angles)), rz @ ry @ rx, atol=1e-6)
    with pytest.raises(ValueError, match="unknown rotation form"):
        rot.convert(q, "quat", "euler")


def test_the_matrix_between_two_directions_is_the_smallest_turn():
    a, b = torch.randn(200, 3), torch.randn(200, 3)
    turn = rot.rotation_matrix_between(a, b)
    unit = torch.nn.functional.normalize
    assert torch.allclose((turn @ unit(a, dim=-1)[..., None])[..., 0], unit(b, dim=-1), atol=1e-5)
    assert torch.allclose(turn, rot.quat_to_matrix(rot.rotation_between(a, b)), atol=1e-5)   # the quaternion form's
    half = rot.rotation_matrix_between(torch.tensor([1.0, 0, 0]), torch.tensor([-1.0, 0, 0]))  # opposite: a half turn
    assert torch.allclose(half @ torch.tensor([1.0, 0, 0]), torch.tensor([-1.0, 0, 0]), atol=1e-6)
    assert torch.allclose(torch.det(half), torch.tensor(1.0), atol=1e-6)


def test_slicing_and_resampling_keep_the_path():
    motion = random_motion(arm(), frames=41)
    assert len(motion[10:20]) == 10 and motion[::2].fps == 15.0
    up = motion.resample(60.0)
    assert up.num_frames == 81 and up.fps == 60.0
    assert torch.allclose(up.world_positions()[::2], motion.world_positions(), atol=1e-5)
    # A halfway frame is the slerp midpoint: its rotation is equally far from both neighbours.
    a, b, mid = motion.rotations[3], motion.rotations[4], up.rotations[7]
    angle = lambda x, y: 2 * torch.arccos((x * y).sum(-1).abs().clamp(max=1))
    assert torch.allclose(angle(a, mid), angle(mid, b), atol=1e-3)
    down = motion.resample(10.0)
    assert down.num_frames == 14
    assert torch.allclose(down.world_positions(), motion.world_positions()[::3], atol=1e-5)


def test_mirror_swaps_sides_and_reflects():
    skeleton = arm()
    assert list(skeleton.mirror_indices()) == [0, 3, 4, 1, 2]
    motion = random_motion(skeleton)
    mirrored = motion.mirrored()
    expected = motion.world_positions()[:, skeleton.mirror_indices()] * torch.tensor([-1.0, 1, 1])
    assert torch.allclose(mirrored.world_positions(), expected, atol=1e-5)
    assert torch.allclose(mirrored.mirrored().world_positions(), motion.world_positions(), atol=1e-5)


def test_side_names_are_recognised():
    names = ["Hips", "lfemur", "rfemur", "lowerback", "CC_Base_L_Thigh", "CC_Base_R_Thigh", "LeftArm", "RightArm", "lShldr", "rShldr"]
    skeleton = Skeleton(names, [-1] + [0] * 9, np.zeros((10, 3)))
    assert list(skeleton.mirror_indices()) == [0, 2, 1, 3, 5, 4, 7, 6, 9, 8]


def test_bad_input_is_named():
    skeleton = arm()
    with pytest.raises(ValueError, match=r"rotations have shape \(3, 4, 4\), expected \(3, 5, 4\)"):
        Motion(skeleton, torch.zeros(3, 4, 4), torch.zeros(3, 3), 30.0)
    q = rot.quat_identity(3, 5)
    q[2, 1, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN or infinity \\(first at frame 2\\)"):
        Motion(skeleton, q, torch.zeros(3, 3), 30.0)
    with pytest.raises(ValueError, match="fps"):
        Motion(skeleton, rot.quat_identity(3, 5), torch.zeros(3, 3), 0.0)
    far = torch.tensor([[0.0, 0, 0], [3e38, 0, 0], [3e38, 0, 0]])   # finite values whose sum overflows
    assert Motion(skeleton, rot.quat_identity(3, 5), far, 30.0).num_frames == 3
    with pytest.raises(ValueError, match="parents"):
        Skeleton(["a", "b"], [-1, 1], np.zeros((2, 3)))
    with pytest.raises(ValueError, match="duplicate joint names"):
        Skeleton(["a", "a"], [-1, 0], np.zeros((2, 3)))
    with pytest.raises(KeyError, match="no joint 'knee'"):
        skeleton.index("knee")

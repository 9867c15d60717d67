"""Augmentations against known answers: yaw rotates FK positions, mirror is an involution,
speed changes keep the path."""

import math

import pytest
import torch

from humotion import rotations as rot
from humotion.data.augment import RandomAugment, change_speed, mirror, rotate_yaw, yaw_quaternion
from humotion.motion import Motion
from humotion.skeleton import Skeleton


def _skeleton() -> Skeleton:
    names = ("Hips", "Spine", "Head", "LeftUpLeg", "LeftLeg", "RightUpLeg", "RightLeg", "LeftArm", "RightArm")
    parents = (-1, 0, 1, 0, 3, 0, 5, 1, 1)
    offsets = [[0, 0.9, 0], [0, 0.2, 0.01], [0, 0.3, 0], [0.1, 0, 0], [0, -0.45, 0],
               [-0.1, 0, 0], [0, -0.45, 0], [0.2, 0.25, 0], [-0.2, 0.25, 0]]
    return Skeleton(names, parents, offsets, end_site_parents=(2,), end_site_offsets=[[0, 0.15, 0.02]])


def _motion(frames: int = 25, seed: int = 0) -> Motion:
    g = torch.Generator().manual_seed(seed)
    skeleton = _skeleton()
    rotvec = 0.6 * torch.randn(frames, skeleton.num_joints, 3, generator=g)
    rotations = rot.convert(rotvec, "rotvec", "quat")
    root = torch.cumsum(0.05 * torch.randn(frames, 3, generator=g), 0) + torch.tensor([0.3, 0.9, -0.2])
    return Motion(skeleton, rotations, root, fps=30.0)


def _rot_y(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def test_yaw_quaternion_turns_forward_to_left_side():
    q = yaw_quaternion(math.pi / 2)
    assert torch.allclose(rot.quat_apply(q, torch.tensor([0.0, 0.0, 1.0])), torch.tensor([1.0, 0.0, 0.0]), atol=1e-6)
    assert torch.allclose(rot.quat_apply(q, torch.tensor([1.0, 0.0, 0.0])), torch.tensor([0.0, 0.0, -1.0]), atol=1e-6)


def test_yaw_90_rotates_world_positions_exactly():
    motion = _motion()
    turned = rotate_yaw(motion, math.pi / 2)
    p, p_turned = motion.world_positions(), turned.world_positions()
    # (x, y, z) -> (z, y, -x) for a quarter turn about +Y.
    expected = torch.stack([p[..., 2], p[..., 1], -p[..., 0]], dim=-1)
    assert torch.allclose(p_turned, expected, atol=1e-5)
    assert torch.allclose(turned.end_site_positions(), motion.end_site_positions() @ _rot_y(math.pi / 2).T, atol=1e-5)
    # Only the root orientation changes.
    assert torch.equal(turned.rotations[:, 1:], motion.rotations[:, 1:])


@pytest.mark.parametrize("angle", [-2.5, -0.3, 0.7, math.pi])
def test_yaw_matches_rotation_matrix_on_fk(angle):
    motion = _motion(seed=1)
    expected = motion.world_positions() @ _rot_y(angle).T
    assert torch.allclose(rotate_yaw(motion, angle).world_positions(), expected, atol=1e-5)


def test_yaw_composes_and_inverts():
    motion = _motion(seed=2)
    twice = rotate_yaw(rotate_yaw(motion, 0.4), 0.9)
    assert torch.allclose(twice.world_positions(), rotate_yaw(motion, 1.3).world_positions(), atol=1e-5)
    back = rotate_yaw(rotate_yaw(motion, 1.1), -1.1)
    assert torch.allclose(back.world_positions(), motion.world_positions(), atol=1e-5)


def test_mirror_twice_is_identity():
    motion = _motion(seed=3)
    twice = mirror(mirror(motion))
    assert torch.equal(twice.rotations, motion.rotations)
    assert torch.equal(twice.root_positions, motion.root_positions)
    assert torch.equal(twice.skeleton.offsets, motion.skeleton.offsets)
    assert torch.allclose(twice.world_positions(), motion.world_positions(), atol=1e-6)


def test_mirror_reflects_and_swaps_sides():
    motion = _motion(seed=4)
    mirrored = mirror(motion)
    swap = motion.skeleton.mirror_indices()
    assert list(swap[[3, 4, 5, 6, 7, 8]]) == [5, 6, 3, 4, 8, 7]
    expected = motion.world_positions()[:, swap] * torch.tensor([-1.0, 1.0, 1.0])
    assert torch.allclose(mirrored.world_positions(), expected, atol=1e-5)


def test_speed_2_halves_frames_and_keeps_path():
    motion = _motion(frames=41)
    fast = change_speed(motion, 2.0)
    assert fast.fps == motion.fps
    assert fast.num_frames == 21
    assert fast.duration == pytest.approx(motion.duration / 2, abs=1 / motion.fps)
    assert torch.allclose(fast.root_positions, motion.root_positions[::2], atol=1e-6)
    assert torch.allclose(fast.world_positions(), motion.world_positions()[::2], atol=1e-5)


def test_speed_half_doubles_frames_through_the_same_poses():
    motion = _motion(frames=20)
    slow = change_speed(motion, 0.5)
    assert slow.num_frames == 39
    assert torch.allclose(slow.world_positions()[::2], motion.world_positions(), atol=1e-5)
    midway = (motion.root_positions[:-1] + motion.root_positions[1:]) / 2
    assert torch.allclose(slow.root_positions[1::2], midway, atol=1e-6)


def test_speed_rejects_non_positive_factor():
    with pytest.raises(ValueError, match="speed factor"):
        change_speed(_motion(), 0.0)


def test_random_augment_is_reproducible_from_seed():
    motion = _motion(seed=5)
    a = [RandomAugment(seed=7)(motion) for _ in range(2)]
    assert torch.equal(a[0].rotations, a[1].rotations) and torch.equal(a[0].root_positions, a[1].root_positions)
    augment = RandomAugment(seed=7)
    first, second = augment(motion), augment(motion)
    assert not torch.equal(first.root_positions, second.root_positions)  # the generator moves on
    assert not torch.equal(RandomAugment(seed=8)(motion).root_positions, a[0].root_positions)


def test_random_augment_keeps_shape_and_bone_lengths():
    motion = _motion(seed=6)
    augment = RandomAugment(mirror=0.5, yaw=True, generator=torch.Generator().manual_seed(0))
    for _ in range(6):
        out = augment(motion)
        assert out.num_frames == motion.num_frames
        p, q = out.world_positions(), motion.world_positions()
        bones = lambda x: (x[:, 1:] - x[:, list(motion.skeleton.parents[1:])]).norm(dim=-1)  # noqa: E731
        assert torch.allclose(bones(p), bones(q), atol=1e-5)
        # height above the ground plane is unchanged by mirror and yaw
        assert torch.allclose(torch.sort(p[..., 1], dim=-1).values, torch.sort(q[..., 1], dim=-1).values, atol=1e-5)


def test_random_augment_speed_range_changes_length_within_bounds():
    motion = _motion(frames=61)
    augment = RandomAugment(mirror=0.0, yaw=False, speed=(0.5, 2.0), seed=3)
    lengths = {augment(motion).num_frames for _ in range(8)}
    assert all(31 <= n <= 121 for n in lengths) and len(lengths) > 1

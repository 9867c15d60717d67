"""Training batches for the lifting network: mocap windows filmed by random virtual cameras.

    frames = LiftFrames(load_windows(config, "train", stride=8))     # 3D joints + keypoints per frame
    inputs, target = make_lift_batch(*frames.window_points(indices), generator)

Each window: arms raised sideways at random (:func:`raise_arms`; mocap rarely holds arms level,
so without it a T-pose is lifted with drooping arms), mirrored (left and right swapped, x
negated) with probability `mirror`, filmed by
its own random static camera (humotion.capture.keypoints.random_camera: any yaw, so no separate
yaw augmentation is needed), its keypoints spoilt by the detector noise model (corrupt), then
normalised per frame (humotion.capture.lifting.lifting_inputs). Targets: the 22 canonical joints
in the camera frame, relative to the pelvis, divided by the skeleton's standing height.
"""

from __future__ import annotations

import torch

from humotion import rotations as rot
from humotion.canonical import JOINTS, canonical_skeleton
from humotion.capture.detection import KEYPOINTS
from humotion.capture.keypoints import (KEYPOINT_MIRROR, CameraRanges, DetectorNoise, body_keypoints_3d, corrupt,
                                        random_camera)
from humotion.capture.lifting import lifting_inputs
from humotion.data import MotionWindows

JOINT_MIRROR = tuple(int(i) for i in canonical_skeleton().mirror_indices())
_FLIP_X = torch.tensor([-1.0, 1.0, 1.0])
_HIPS = (JOINTS.index("left_hip"), JOINTS.index("right_hip"))


def raise_arms(joints: torch.Tensor, keypoints: torch.Tensor, generator: torch.Generator, share: float = 0.3,
               max_degrees: float = 80.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Windows where each arm, with probability share, is turned about its shoulder towards the
    side (about the body's forward axis, from the hips line, frame by frame) by one angle drawn
    uniformly up to max_degrees for the window. joints (B, L, 22, 3), keypoints (B, L, 21, 3)
    metres, Y up; returns new tensors (elbows and wrists moved, joints and keypoints alike)."""
    joints, keypoints = joints.clone(), keypoints.clone()
    left_axis = joints[..., _HIPS[0], :] - joints[..., _HIPS[1], :]
    forward = torch.nn.functional.normalize(torch.cross(left_axis, torch.tensor([0.0, 1.0, 0.0]).expand_as(left_axis),
                                                        dim=-1), dim=-1)                  # (B, L, 3)
    batch = joints.shape[0]
    for side, sign in (("left", 1.0), ("right", -1.0)):
        chosen = torch.rand(batch, generator=generator) < share
        angle = torch.rand(batch, generator=generator) * torch.deg2rad(torch.tensor(max_degrees)) * chosen * sign
        turn = rot.convert(forward * angle[:, None, None], "rotvec", "matrix")[..., None, :, :]   # (B, L, 1, 3, 3)
        shoulder = joints[..., JOINTS.index(f"{side}_shoulder"), :][..., None, :]
        for points, names in ((joints, JOINTS), (keypoints, KEYPOINTS)):
            arm = [names.index(f"{side}_elbow"), names.index(f"{side}_wrist")]
            points[..., arm, :] = shoulder + (turn @ (points[..., arm, :] - shoulder)[..., None])[..., 0]
    return joints, keypoints


class LiftFrames:
    """World joints and keypoints of every frame of the clips of canonical MotionWindows, from
    which its windows are cut.

    joints: (N, 22, 3) and keypoints: (N, 21, 3) metres (Y up); height: (N,) standing height of
    each frame's skeleton, metres; starts: (len(windows),) row of each window's first frame;
    length: frames per window.
    """

    def __init__(self, windows: MotionWindows):
        joints, keypoints, heights, first_rows = [], [], [], [0]
        for motion in windows.motions:
            rotations, positions = motion.world()
            joints.append(positions)
            keypoints.append(body_keypoints_3d(rotations, positions, motion.skeleton))
            heights.append(torch.full((motion.num_frames,), motion.skeleton.height()))
            first_rows.append(first_rows[-1] + motion.num_frames)
        self.joints, self.keypoints, self.height = torch.cat(joints), torch.cat(keypoints), torch.cat(heights)
        self.starts = torch.tensor([first_rows[clip] + start for clip, start in windows.index], dtype=torch.long)
        self.length = windows.length

    def __len__(self) -> int:
        return len(self.starts)

    def window_points(self, indices) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(joints (B, L, 22, 3), keypoints (B, L, 21, 3), height (B,)) of windows `indices`."""
        rows = self.starts[torch.as_tensor(indices, dtype=torch.long)][:, None] + torch.arange(self.length)
        return self.joints[rows], self.keypoints[rows], self.height[rows[:, 0]]


def make_lift_batch(joints: torch.Tensor, keypoints: torch.Tensor, height: torch.Tensor, generator: torch.Generator,
                    noise: DetectorNoise = DetectorNoise(), cameras: CameraRanges = CameraRanges(),
                    mirror: float = 0.5, arm_raise: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """(inputs (B, L, 21, 3), target (B, L, 22, 3)) for windows of world joints (B, L, 22, 3) and
    keypoints (B, L, 21, 3) in metres and standing heights (B,) in metres. All random draws
    (arm raising with share arm_raise, mirror, camera, noise) come from `generator`."""
    if arm_raise:
        joints, keypoints = raise_arms(joints, keypoints, generator, arm_raise)
    flip = (torch.rand(joints.shape[0], generator=generator) < mirror)[:, None, None, None]
    joints = torch.where(flip, joints[..., JOINT_MIRROR, :] * _FLIP_X, joints)
    keypoints = torch.where(flip, keypoints[..., KEYPOINT_MIRROR, :] * _FLIP_X, keypoints)
    camera = random_camera(generator, torch.cat([joints, keypoints], dim=-2).flatten(1, 2), cameras)
    pixels, depth = camera.project(keypoints)
    seen, confidence = corrupt(pixels, generator, noise, image_size=camera.size, depth=depth)
    local = camera.to_camera(joints)
    target = (local - local[..., :1, :]) / height[:, None, None, None]
    return lifting_inputs(seen, confidence), target

"""Motion augmentation: mirror, yaw rotation, speed change, and a seeded random composition.

Every function takes a Motion and returns a new one (the input is not modified). World frame
conventions as in DESIGN.md: Y up, so a yaw is a rotation about +Y through the world origin.
"""

from __future__ import annotations

import math
from dataclasses import replace

import torch

from humotion import rotations as rot
from humotion.motion import Motion


def mirror(motion: Motion) -> Motion:
    """Left and right swapped, reflected through the X = 0 plane (Motion.mirrored)."""
    return motion.mirrored()


def yaw_quaternion(angle: float | torch.Tensor) -> torch.Tensor:
    """(..., 4) wxyz quaternion of a rotation by `angle` radians about +Y (counter-clockwise
    seen from above: +Z turns towards +X)."""
    angle = torch.as_tensor(angle, dtype=torch.float64)
    rotvec = torch.stack([torch.zeros_like(angle), angle, torch.zeros_like(angle)], dim=-1)
    return rot.convert(rotvec, "rotvec", "quat").float()


def rotate_yaw(motion: Motion, angle: float) -> Motion:
    """The motion turned by `angle` radians about the vertical axis through the world origin.

    The root orientation is pre-multiplied by the yaw and the root trajectory (T, 3) is rotated,
    so every world joint position p becomes R_y(angle) @ p.
    """
    q = yaw_quaternion(angle).expand(motion.num_frames, 4)
    rotations = motion.rotations.clone()
    rotations[:, 0] = rot.quat_mul(q, motion.rotations[:, 0])
    return replace(motion, rotations=rotations, root_positions=rot.quat_apply(q, motion.root_positions))


def change_speed(motion: Motion, factor: float) -> Motion:
    """The motion played `factor` times as fast at the same fps (factor 2: half the frames,
    same path; factor 0.5: twice the frames, in-between frames interpolated by slerp/lerp)."""
    if not (factor > 0 and math.isfinite(factor)):
        raise ValueError(f"speed factor must be a positive number, got {factor}")
    return replace(motion, fps=motion.fps * factor).resample(motion.fps)


class RandomAugment:
    """A random composition of speed change, mirror and yaw, reproducible from a seed.

    mirror: probability of mirroring. yaw: rotate by an angle uniform in [-pi, pi) when True
        (or within +-yaw radians when a number). speed: (low, high) factor range, uniform in
        log space, or None for no speed change (speed changes the frame count: use it on whole
        clips, e.g. as a windows transform, not on fixed-length windows).
    generator / seed: the torch.Generator drawing the choices (a new one from seed when given).
    Call it on a Motion: augment(motion) -> Motion.
    """

    def __init__(self, mirror: float = 0.5, yaw: bool | float = True, speed: tuple[float, float] | None = None,
                 *, seed: int | None = None, generator: torch.Generator | None = None):
        if generator is None:
            generator = torch.Generator()
            generator.manual_seed(0 if seed is None else seed)
        self.mirror, self.yaw, self.speed, self.generator = mirror, yaw, speed, generator

    def _uniform(self, low: float, high: float) -> float:
        return low + (high - low) * float(torch.rand((), generator=self.generator, dtype=torch.float64))

    def __call__(self, motion: Motion) -> Motion:
        if self.speed is not None:
            low, high = self.speed
            motion = change_speed(motion, math.exp(self._uniform(math.log(low), math.log(high))))
        if self.mirror and self._uniform(0.0, 1.0) < self.mirror:
            motion = mirror(motion)
        if self.yaw is not False:
            limit = math.pi if self.yaw is True else float(self.yaw)
            motion = rotate_yaw(motion, self._uniform(-limit, limit))
        return motion

    def __repr__(self) -> str:
        return f"RandomAugment(mirror={self.mirror}, yaw={self.yaw}, speed={self.speed})"

"""Joint-angle limits of the body rig as boxes on rotation vectors, and the smooth
box-constrained parameterisation that pose optimisation (L-BFGS) works in.

Limits come from data: per joint and rotation-vector component, the range seen in the training
poses widened by a margin. Joints that never move in the data (Anny's twist bones, which follow
their parents there) are frozen at the identity; the root (the body's global orientation) is
left free within +-pi. A box on the rotation vector is a stand-in for anatomical limits (a knee
gets a thin slab around its flexion arc, not an exact hinge).

    limits = JointLimits(J)
    limits.set_from(rotvecs)                                  # rotvecs (M, J, 3) of training poses
    free = limits.to_free(rotvec)                             # (B, J, 3) unconstrained parameters
    rotvec = limits.to_rotvec(free)                           # centre + half * tanh(free): inside the box
"""

from __future__ import annotations

import math

import torch
from torch import nn

from humotion import rotations as rot


class JointLimits(nn.Module):
    """Boxes lower <= rotvec <= upper per joint (buffers centre, half_range (J, 3); 0 freezes)."""

    def __init__(self, num_joints: int):
        super().__init__()
        self.register_buffer("centre", torch.zeros(num_joints, 3))
        self.register_buffer("half_range", torch.full((num_joints, 3), math.pi))

    @torch.no_grad()
    def set_from(self, rotvecs: torch.Tensor, margin: float = 0.1, frozen_below: float = 1e-3,
                 free_root: bool = True) -> None:
        """Limits from rotation vectors (M, J, 3): the seen range +- margin radians, frozen where
        a joint's largest rotation angle is below frozen_below radians; the root free (+-pi)."""
        lower, upper = rotvecs.amin(0) - margin, rotvecs.amax(0) + margin
        frozen = rotvecs.norm(dim=-1).amax(0) < frozen_below
        lower = lower.clamp_min(-math.pi)
        upper = upper.clamp_max(math.pi)
        centre, half = (lower + upper) / 2, (upper - lower) / 2
        centre[frozen], half[frozen] = 0.0, 0.0
        if free_root:
            centre[0], half[0] = 0.0, math.pi
        self.centre.copy_(centre)
        self.half_range.copy_(half)

    @property
    def frozen(self) -> torch.Tensor:
        """(J,) bool: joints held at their box centre."""
        return (self.half_range == 0).all(-1)

    def to_rotvec(self, free: torch.Tensor) -> torch.Tensor:
        """Unconstrained (..., J, 3) -> rotation vectors inside the boxes."""
        return self.centre + self.half_range * torch.tanh(free)

    def to_free(self, rotvec: torch.Tensor, eps: float = 1e-4) -> torch.Tensor:
        """Rotation vectors (..., J, 3) -> unconstrained parameters (clamped into the boxes)."""
        ratio = (rotvec - self.centre) / self.half_range.clamp_min(1e-12)
        return torch.atanh(ratio.clamp(-1 + eps, 1 - eps)) * (self.half_range > 0)

    def violation(self, rotvec: torch.Tensor) -> torch.Tensor:
        """(..., J) largest distance (radians) of each joint's rotation vector outside its box."""
        excess = (rotvec - self.centre).abs() - self.half_range
        return excess.clamp_min(0).amax(-1)

    def to_matrix(self, free: torch.Tensor) -> torch.Tensor:
        """Unconstrained (..., J, 3) -> rotation matrices (..., J, 3, 3)."""
        return rot.convert(self.to_rotvec(free), "rotvec", "matrix")

"""The template skeleton of a filmed person: the canonical body at their standing height.

Step 5 of the video-capture pipeline (specs/video-capture.md). Bone lengths come from classic
anthropometric proportions of standing height (Drillis & Contini, as tabulated by Winter),
already laid out on the canonical joints by :func:`humotion.canonical.canonical_skeleton`;
this module picks the height (a default, the user's, or one estimated from measured bones).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from humotion.canonical import JOINTS, PARENTS, canonical_skeleton
from humotion.skeleton import Skeleton

DEFAULT_HEIGHT = 1.65  # metres: the spec's adult average when nothing else is known

# Bones whose lengths estimate height: thighs, shanks, upper arms and forearms (named by their
# child joint). They run between well-defined joint centres, so every rig agrees on them best;
# pelvis, spine, collar and head bones differ between rigs by 20-150 % (see the tests).
HEIGHT_BONES = ("left_knee", "right_knee", "left_ankle", "right_ankle",
                "left_elbow", "right_elbow", "left_wrist", "right_wrist")

_LENGTH_PER_METRE = torch.as_tensor(np.linalg.norm(canonical_skeleton(1.0).offsets, axis=1))
_LENGTH_PER_METRE[0] = 0.0  # the root's offset is a position, not a bone


def template_skeleton(height_m: float = DEFAULT_HEIGHT) -> Skeleton:
    """The canonical skeleton (22 joints, T-pose facing +Z, Y up) for a standing height in metres."""
    if not (math.isfinite(height_m) and 0.5 <= height_m <= 2.5):
        raise ValueError(f"height_m must be a standing height in metres between 0.5 and 2.5, got {height_m}")
    return canonical_skeleton(height_m)


def bone_lengths(positions: torch.Tensor, parents: tuple[int, ...] = PARENTS) -> torch.Tensor:
    """(..., J) distance of each joint from its parent (0 for the root), metres.

    positions: (..., J, 3) joint positions in metres; parents: J parent indices (-1 for the root),
    the canonical body's by default.
    """
    positions = torch.as_tensor(positions)
    parent_index = [max(p, 0) for p in parents]
    return (positions - positions[..., parent_index, :]).norm(dim=-1)


def estimate_height(bones: Skeleton | torch.Tensor) -> float | torch.Tensor:
    """Standing height (metres) whose template best matches measured limb bones.

    bones: a Skeleton with the canonical joints, or (..., 22) bone lengths in metres as given by
    :func:`bone_lengths` (for a network's per-frame output, take the median over frames first).
    Least squares over :data:`HEIGHT_BONES`: the height H minimising
    sum_b (length_b - H * template_length_per_metre_b)^2. Returns a float for a Skeleton, else a
    (...) tensor.
    """
    if isinstance(bones, Skeleton):
        if bones.names != JOINTS:
            raise ValueError("estimate_height needs a skeleton with the canonical joints (humotion.canonical.JOINTS)")
        return float(estimate_height(torch.as_tensor(np.linalg.norm(bones.offsets, axis=1))))
    lengths = torch.as_tensor(bones)
    if lengths.shape[-1:] != (len(JOINTS),):
        raise ValueError(f"bone lengths must have shape (..., {len(JOINTS)}), got {tuple(lengths.shape)}")
    index = [JOINTS.index(name) for name in HEIGHT_BONES]
    per_metre = _LENGTH_PER_METRE[index].to(lengths.dtype)
    return (lengths[..., index] * per_metre).sum(-1) / per_metre.square().sum()

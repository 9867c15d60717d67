"""The template skeleton of a filmed person: the canonical body at their standing height.

Step 5 of the video-capture pipeline (specs/video-capture.md). Bone lengths come from classic
anthropometric proportions of standing height (Drillis & Contini, as tabulated by Winter),
already laid out on the canonical joints by :func:`humotion.canonical.canonical_skeleton`;
this module gives it at a height (the spec's default 1.65 m, or the user's).
"""

from __future__ import annotations

import math

import torch

from humotion.canonical import PARENTS, canonical_skeleton
from humotion.skeleton import Skeleton

DEFAULT_HEIGHT = 1.65  # metres: the spec's adult average when nothing else is known


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


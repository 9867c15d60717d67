"""The template skeleton of a filmed person: the canonical body at their standing height.

Step 5 of the video-capture pipeline (specs/video-capture.md). Bone lengths come from classic
anthropometric proportions of standing height (Drillis & Contini, as tabulated by Winter),
already laid out on the canonical joints by :func:`humotion.canonical.canonical_skeleton`;
this module gives it at a height (the spec's default 1.65 m, the user's, or one typical of a
sex and age: :func:`typical_height`).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from humotion.canonical import PARENTS, canonical_skeleton
from humotion.skeleton import Skeleton

DEFAULT_HEIGHT = 1.65  # metres: the spec's adult average when nothing else is known

GROWTH_AGES = tuple(range(2, 21))
"""Years of GROWTH_MEDIANS_CM: median standing height (stature) by age and sex, CDC 2000 growth
charts (stature-for-age, 50th percentile; Kuczmarski et al. 2002), rounded to 0.5 cm."""
GROWTH_MEDIANS_CM = {
    "male": (86.5, 95.5, 102.5, 109.0, 115.5, 121.5, 127.5, 133.0, 138.5, 143.5, 149.0, 156.0, 163.0, 169.0,
             173.0, 175.0, 176.0, 176.5, 177.0),
    "female": (85.0, 94.0, 101.5, 108.5, 115.0, 121.0, 127.0, 133.0, 138.5, 145.0, 151.0, 156.5, 160.0, 161.5,
               162.5, 163.0, 163.0, 163.5, 163.5),
}

GROWTH_WEIGHT_MEDIANS_KG = {
    "male": (12.7, 14.3, 16.2, 18.4, 20.7, 23.1, 25.6, 28.6, 31.9, 35.9, 40.5, 45.6, 51.0, 56.3, 60.9, 64.6,
             67.2, 69.1, 70.6),
    "female": (12.1, 13.9, 15.8, 17.9, 20.2, 22.8, 25.6, 29.0, 32.9, 37.2, 41.6, 45.8, 49.4, 52.0, 53.9, 55.1,
               56.2, 57.3, 58.2),
}
"""Median body weight (kg) at the ages GROWTH_AGES (2..20 years) by sex: the CDC 2000 growth
charts, weight-for-age, 50th percentile (the LMS tables' M; Kuczmarski et al. 2002, "2000 CDC
Growth Charts for the United States", Vital Health Stat 11(246)), interpolated to whole years
and rounded to 0.1 kg; the partner of GROWTH_MEDIANS_CM (stature).
Adults keep the 20-year medians (US adults' medians rise with age: a typical build, not a census)."""


def typical_height(sex: str | None = None, age: float | None = None) -> float:
    """A standing height in metres typical of a sex ("male", "female", or None: the mean of both)
    and an age in years (2 or more; None: an adult), from GROWTH_MEDIANS_CM (adults keep the
    20-year median). Neither given: DEFAULT_HEIGHT."""
    if sex is None and age is None:
        return DEFAULT_HEIGHT
    return _growth_median(lambda s, a: _median(GROWTH_MEDIANS_CM, s, a) / 100, sex, age)


def typical_bmi(sex: str | None = None, age: float | None = None) -> float:
    """A body-mass index (kg / m^2) typical of a sex and an age as for :func:`typical_height`:
    the median weight (GROWTH_WEIGHT_MEDIANS_KG) over the median height squared."""
    return _growth_median(lambda s, a: _median(GROWTH_WEIGHT_MEDIANS_KG, s, a)
                          / (_median(GROWTH_MEDIANS_CM, s, a) / 100) ** 2, sex, age)


def _median(table: dict, sex: str, age: float) -> float:
    return float(np.interp(age, GROWTH_AGES, table[sex]))


def _growth_median(value, sex: str | None, age: float | None) -> float:
    """value(sex, age) for a checked sex and age (None: adult; adults take the 20-year figures),
    averaged over both sexes when sex is None. ValueError for an unknown sex or an age outside
    2-120 years."""
    if sex not in (None, *GROWTH_MEDIANS_CM):
        raise ValueError(f"sex must be one of {sorted(GROWTH_MEDIANS_CM)} (or left out), got {sex!r}")
    if age is not None and not (math.isfinite(age) and age >= GROWTH_AGES[0]):
        raise ValueError(f"age must be at least {GROWTH_AGES[0]} years (the growth charts' range starts there), got {age}")
    if age is not None and age > 120:
        raise ValueError(f"age must be at most 120 years, got {age:g}")
    age = GROWTH_AGES[-1] if age is None else min(age, GROWTH_AGES[-1])
    sexes = [sex] if sex else list(GROWTH_MEDIANS_CM)
    return sum(value(s, age) for s in sexes) / len(sexes)


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


"""Subject splits: every person in exactly one of train / val / test, balanced by minutes of motion.

    splits = split_subjects({"cmu-01": 12.5, "cmu-02": 3.0, ...}, (0.8, 0.1, 0.1), seed=0)

Splits are made by subject, never by clip, so one person's takes never sit on both sides of an
evaluation; TOGETHER lists subjects whose data is not independent, and EVALUATION_ONLY the
sources that MotionCollection.split keeps out of training.
"""

from __future__ import annotations

import hashlib
from collections import defaultdict
from typing import Iterable, Sequence

TOGETHER = (
    ("cmu-60", "cmu-61"),
    ("cmu-expmap-unknown", "cmu-02", "cmu-07", "cmu-10", "cmu-11", "cmu-16"),
)
"""Subjects kept in the same split by default.

- CMU 60 and 61 are the two partners of the same salsa recordings: distinct people, but their
  motion is coupled frame for frame, so not independent data.
- cmu_expmap_li2018 holds copies of takes found elsewhere in ../shared/data/mocap. Matching
  per-joint rotation-angle curves (hips, knees, shoulders, elbows; 30 Hz, 1 s windows, mean
  difference 0.004-0.015 rad against >= 0.03 rad for any other pair) identified 14 of its 96
  clips: test/soccer/soccer_1 = 11_01; train/soccer/soccer_4, soccer_5 = 10_05, 10_06;
  train/walking_extra/walking_18 = 10_04; walking_27..33 = 16_15, 16_16, 16_21, 16_22, 16_31,
  16_32, 16_47; train/running/running_2 = 16_36; train/walking/walking_1 = 02_01;
  train/walking/walking_4 = 07_01 (also confirming its rows are 120 Hz). The source therefore
  shares a split with subjects 02, 07, 10, 11 and 16. Its other 82 clips matched nothing held
  here but may still be takes of CMU subjects that other copies of the database hold: exclude
  the source when that matters for a reported number.
"""

EVALUATION_ONLY = ("hdm05_jointlearning",)
"""Sources that may evaluate but not train shipped weights (HDM05: CC BY-SA 3.0, share-alike):
MotionCollection.split puts their subjects in the test split by default."""

SPLIT_NAMES = ("train", "val", "test")


def _stable_rank(seed: int, attempt: int, key: str) -> str:
    return hashlib.sha256(f"{seed}:{attempt}:{key}".encode()).hexdigest()


def split_subjects(minutes: dict[str, float], fractions: Sequence[float] = (0.8, 0.1, 0.1), seed: int = 0, *,
                   names: Sequence[str] = SPLIT_NAMES, pin: dict[str, str] | None = None,
                   together: Iterable[Sequence[str]] = TOGETHER, attempts: int = 4) -> dict[str, list[str]]:
    """Assign every subject to one split, balancing minutes of motion; deterministic in (minutes, seed).

    minutes: subject id -> minutes. fractions: share of the minutes per split (same order as names).
    pin: subject id -> split name, placed there first. together: groups of subject ids kept in one
        split (ids not in `minutes` are ignored).
    Groups (a subject, or a `together` group) are visited in the order of sha256(seed, attempt,
    group) and each is put where it brings the splits' minutes closest to their targets (least
    sum of squared relative deviations); of `attempts` such orders the best-balanced one wins.
    Returns split name -> sorted subject ids; every subject in exactly one split.
    """
    _check_split_arguments(fractions, names, pin or {})
    total = sum(minutes.values())
    targets = [total * f / sum(fractions) for f in fractions]
    pinned_groups, free = _pinned_and_free(_groups(minutes, together), dict(pin or {}), names)
    best = None
    for attempt in range(max(1, attempts)):
        assignment, cost = _assign(minutes, targets, pinned_groups, free, seed, attempt)
        if best is None or cost < best[0]:
            best = (cost, assignment)
    result: dict[str, list[str]] = {n: [] for n in names}
    for members, index in best[1]:
        result[names[index]] += members
    return {n: sorted(v) for n, v in result.items()}


def _check_split_arguments(fractions: Sequence[float], names: Sequence[str], pin: dict[str, str]) -> None:
    if len(fractions) != len(names):
        raise ValueError(f"{len(fractions)} fractions for {len(names)} split names {tuple(names)}")
    if any(f < 0 for f in fractions) or sum(fractions) <= 0:
        raise ValueError(f"fractions must be non-negative with a positive sum, got {tuple(fractions)}")
    for subject, name in pin.items():
        if name not in names:
            raise ValueError(f"subject {subject!r} pinned to unknown split {name!r}; splits: {', '.join(names)}")


def _groups(minutes: dict[str, float], together: Iterable[Sequence[str]]) -> dict[str, list[str]]:
    """Group key -> subjects: the `together` groups united (transitively) over the subjects present,
    every other subject a group of its own."""
    group_of = {s: s for s in minutes}
    for group in together:
        present = sorted(s for s in group if s in minutes)
        for s in present[1:]:
            old, new = group_of[s], group_of[present[0]]
            group_of = {k: (new if v == old else v) for k, v in group_of.items()}
    groups: dict[str, list[str]] = defaultdict(list)
    for s, g in group_of.items():
        groups[g].append(s)
    return groups


def _pinned_and_free(groups: dict[str, list[str]], pin: dict[str, str], names: Sequence[str]):
    """([(members, split index)] for groups with a pinned member, [members] for the others)."""
    pinned_groups, free = [], []
    for key in sorted(groups):
        members = sorted(groups[key])
        pinned = {pin[s] for s in members if s in pin}
        if len(pinned) > 1:
            raise ValueError(f"subjects {members} must share a split but are pinned to {sorted(pinned)}")
        if pinned:
            pinned_groups.append((members, list(names).index(pinned.pop())))
        else:
            free.append(members)
    return pinned_groups, free


def _assign(minutes: dict[str, float], targets: list[float], pinned_groups: list, free: list[list[str]],
            seed: int, attempt: int) -> tuple[list[tuple[list[str], int]], float]:
    """One greedy pass: the pinned groups, then the free ones in this attempt's order, each where
    it brings the splits' minutes closest to their targets. Returns (assignment, its cost)."""
    open_splits = [i for i, t in enumerate(targets) if t > 0]

    def cost(filled: list[float]) -> float:
        return sum(((filled[i] - targets[i]) / targets[i]) ** 2 for i in open_splits)

    assignment = list(pinned_groups)
    filled = [0.0] * len(targets)
    for members, index in assignment:
        filled[index] += sum(minutes[s] for s in members)
    for members in sorted(free, key=lambda m: _stable_rank(seed, attempt, ",".join(m))):
        amount = sum(minutes[s] for s in members)

        def after(i: int) -> list[float]:
            return [f + amount if j == i else f for j, f in enumerate(filled)]

        index = min(open_splits, key=lambda i: (cost(after(i)), i))
        assignment.append((members, index))
        filled = after(index)
    return assignment, cost(filled)

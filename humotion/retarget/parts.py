"""Body parts of a rig: every joint labelled with one of six parts, and the membership matrix.

The parts, in one fixed order for every skeleton (so they correspond across skeletons even
when joints do not): left arm, right arm, left leg, right leg, torso, head. A limb is the
subtree of its first joint (collar, or upper arm without one; upper leg) plus the side's own
joints between it and the trunk (CMU's hip-socket bone); the head is the subtree of the neck;
everything else (root, pelvis, spine, chest helpers) is torso. A rig without legs has no leg parts.

Overrides come from a small JSON or TOML file, for rigs the automatic search gets wrong:

    {"joints": {"left_knee": "Knee_L"},         key point -> joint name (see KEY_POINTS)
     "parts": {"Tail1": "torso"}}               joint -> part, for it and every joint below it
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import torch

from humotion.retarget.keyjoints import KEY_POINTS, SIDES, Tree, has_legs
from humotion.skeleton import Skeleton

PARTS: tuple[str, ...] = ("left_arm", "right_arm", "left_leg", "right_leg", "torso", "head")


def label_parts(skeleton: Skeleton, key_joints: dict[str, str | None],
                overrides: dict[str, str] | None = None) -> torch.Tensor:
    """(J,) int64 index into PARTS of every joint.

    key_joints: as from find_key_joints (hips, collars and neck are used).
    overrides: joint name -> part name, applied to the joint and its subtree (deeper overrides
        win over shallower ones).
    """
    tree = Tree(skeleton)
    index = {n: i for i, n in enumerate(skeleton.names)}
    labels = torch.full((skeleton.num_joints,), PARTS.index("torso"), dtype=torch.int64)
    pelvis, chest = index[key_joints["pelvis"]], index[key_joints["spine3"]]
    limbs = (("leg", "hip", pelvis), ("arm", "collar", chest))
    for side in SIDES:
        for kind, first, trunk in limbs if has_legs(key_joints) else limbs[1:]:
            top = index[key_joints[f"{side}_{first}"]]
            other = index[key_joints[f"{'right' if side == 'left' else 'left'}_{first}"]]
            shared = set(tree.ancestors(other))
            own = [j for j in tree.path(trunk, top) if j not in shared] if top in tree.subtree(trunk) else [top]
            labels[own + tree.subtree(top)] = PARTS.index(f"{side}_{kind}")
    labels[tree.subtree(index[key_joints["neck"]])] = PARTS.index("head")
    for name in sorted(overrides or {}, key=lambda n: tree.depth[index[n]] if n in index else 0):
        if name not in index:
            raise ValueError(f"part override names joint {name!r}, which the skeleton does not have")
        part = overrides[name]
        if part not in PARTS:
            raise ValueError(f"part override {name!r}: {part!r} is no part; parts are {', '.join(PARTS)}")
        labels[tree.subtree(index[name])] = PARTS.index(part)
    return labels


def membership_matrix(labels: torch.Tensor) -> torch.Tensor:
    """P (6, J + 1) float32 from part labels (J,) int64 (label_parts): P[i, j] = 1 when joint j
    is in part i; the last column, the root's velocity, is 1 for every part."""
    p = torch.zeros((len(PARTS), len(labels) + 1), dtype=torch.float32)
    p[labels, torch.arange(len(labels))] = 1.0
    p[:, -1] = 1.0
    return p


def load_overrides(path: str | Path) -> dict[str, dict[str, str]]:
    """{"joints": key point -> joint, "parts": joint -> part} from a JSON or TOML file."""
    path = Path(path)
    try:
        text = path.read_text()
        data = tomllib.loads(text) if path.suffix.lower() == ".toml" else json.loads(text)
    except (OSError, ValueError) as error:
        raise ValueError(f"{path}: cannot read the override file ({error})") from None
    if not isinstance(data, dict) or set(data) - {"joints", "parts"}:
        raise ValueError(f"{path}: an override file holds 'joints' (key point -> joint name) and/or "
                         f"'parts' (joint name -> part), found {sorted(data) if isinstance(data, dict) else data!r}")
    out = {"joints": dict(data.get("joints", {})), "parts": dict(data.get("parts", {}))}
    unknown = sorted(set(out["joints"]) - set(KEY_POINTS))
    if unknown:
        raise ValueError(f"{path}: unknown key joint(s) {', '.join(unknown)}; key joints are {', '.join(KEY_POINTS)}")
    bad = sorted(p for p in out["parts"].values() if p not in PARTS)
    if bad:
        raise ValueError(f"{path}: unknown part(s) {', '.join(bad)}; parts are {', '.join(PARTS)}")
    return out

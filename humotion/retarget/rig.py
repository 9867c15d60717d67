"""A rig understood for retargeting: key joints, body parts and rest-pose alignment of a skeleton.

The alignment is humotion.canonical's: per canonical joint, the rotation taking the canonical
T-pose's bone directions onto the rig's rest bones (the root's facing by yaw alone; every other
joint its parent's plus the smallest turn onto its own bone). A world rotation W of a rig's
driving joint times that alignment A is the joint's rotation away from the T-pose, the same
quantity on every rig; so pose transfer is W_target = W_source @ A_source @ A_target^T, whatever
each rig's zero pose (T-pose, A-pose, or the game rig's legs-up zero pose).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import torch

from humotion import canonical
from humotion.canonical import END_SITE_PARENTS, END_SITES, JOINTS, PARENTS
from humotion.retarget.keyjoints import find_key_joints
from humotion.retarget.parts import PARTS, label_parts, membership_matrix
from humotion.skeleton import Skeleton

_CANONICAL_DEPTH = Skeleton(JOINTS, PARENTS, np.zeros((len(JOINTS), 3))).depth()


@dataclass(frozen=True, eq=False)
class Rig:
    """A skeleton with its key joints (canonical names -> its joint or end-site names, see
    humotion.retarget.keyjoints), part labels (J,) into PARTS, and per canonical joint the
    driving joint index (22,), the alignment (22, 3, 3) and the bone between key points in the
    canonical frame (22, 3) and (5, 3) for end points, metres."""

    skeleton: Skeleton
    key_joints: dict[str, str | None]
    parts: np.ndarray
    drivers: np.ndarray
    alignment: np.ndarray
    bones: np.ndarray
    end_bones: np.ndarray
    label: str = ""

    @classmethod
    def of(cls, skeleton: Skeleton, overrides: dict | None = None, label: str = "") -> "Rig":
        """Understand a skeleton. overrides: {"joints": key point -> joint, "parts": joint -> part}
        (humotion.retarget.parts.load_overrides). Raises MissingKeyJoints naming what is missing."""
        overrides = overrides or {}
        keys = find_key_joints(skeleton, overrides.get("joints"), label)
        parts = label_parts(skeleton, keys, overrides.get("parts"))
        drivers, alignment, bones, end_bones = canonical.rest_alignments(skeleton, keys)
        return cls(skeleton, keys, parts, np.asarray(drivers), alignment, bones, end_bones, label)

    @property
    def membership(self) -> np.ndarray:
        """P (6, J + 1): part membership of every joint, last column the root velocity (all 1)."""
        return membership_matrix(self.parts)

    def part_of(self, joint: str) -> str:
        return PARTS[self.parts[self.skeleton.index(joint)]]

    @cached_property
    def owners(self) -> np.ndarray:
        """(J,) canonical joint whose rotation sets each joint's world rotation, -1 for none.
        Where several canonical joints share one driving joint (a rig without a collar or with
        two spine joints), the deepest wins: the others are bones of no length."""
        owners = np.full(self.skeleton.num_joints, -1)
        for k in sorted(range(len(JOINTS)), key=lambda k: _CANONICAL_DEPTH[k]):
            owners[self.drivers[k]] = k
        return owners

    def joint(self, key: str) -> int:
        """Index of the joint driving a canonical joint ('left_knee')."""
        return int(self.drivers[JOINTS.index(key)])

    @cached_property
    def t_pose(self) -> Skeleton:
        """The rig's key points as a canonical skeleton in the T-pose, with the rig's bones."""
        return Skeleton(JOINTS, PARENTS, self.bones, END_SITE_PARENTS, self.end_bones, END_SITES)

    def standing_height(self) -> float:
        """Height of the rig stood in the T-pose, metres (its zero pose may not stand)."""
        return self.t_pose.height()

    def hip_height(self) -> float:
        """Height of the pelvis above the soles (lowest point) in the T-pose, metres: the leg
        length that root motion scales with."""
        points = np.concatenate([self.t_pose.rest_positions(), self.t_pose.rest_end_site_positions()])
        return float(points[0, 1] - points[:, 1].min())

    def points(self, world_rotations: torch.Tensor, world_positions: torch.Tensor, keys) -> torch.Tensor:
        """(F, K, 3) world positions of key points (joints or end sites) from forward kinematics
        results (F, J, 3, 3) and (F, J, 3)."""
        sk = self.skeleton
        out = []
        for key in keys:
            name = self.key_joints[key]
            if name in sk.names:
                out.append(world_positions[:, sk.index(name)])
            else:
                e = sk.end_site_names.index(name)
                p = sk.end_site_parents[e]
                offset = torch.as_tensor(sk.end_site_offsets[e], dtype=world_positions.dtype)
                out.append(world_positions[:, p] + world_rotations[:, p] @ offset)
        return torch.stack(out, dim=1)

    def rest_directions(self) -> np.ndarray:
        """(22, 3) unit rest direction of each canonical joint's bone from its parent, in the
        rig's facing frame (rows of zeros for the root and bones of no length)."""
        rest = np.concatenate([self.skeleton.rest_positions(), self.skeleton.rest_end_site_positions()])
        names = list(self.skeleton.names) + list(self.skeleton.end_site_names)
        at = rest[[names.index(self.key_joints[k]) for k in JOINTS]]
        vectors = np.array([at[j] - at[p] if p >= 0 else np.zeros(3) for j, p in enumerate(PARENTS)])
        vectors = vectors @ self.alignment[0]  # undo the rig's facing (yaw)
        length = np.linalg.norm(vectors, axis=1, keepdims=True)
        return np.where(length > 1e-6, vectors / np.maximum(length, 1e-12), 0.0)


def correspondence(a: Rig, b: Rig) -> dict[str, str]:
    """Joint of a -> joint of b: key joints driving the same canonical joint, then joints of the
    same name."""
    pairs = {a.skeleton.names[a.drivers[k]]: b.skeleton.names[b.drivers[k]]
             for k in range(len(JOINTS)) if a.owners[a.drivers[k]] == k and b.owners[b.drivers[k]] == k}
    same = set(a.skeleton.names) & set(b.skeleton.names)
    return pairs | {n: n for n in same if n not in pairs and n not in pairs.values()}


def rest_difference(a: Rig, b: Rig) -> dict[str, float]:
    """Angle in degrees between the rest directions of each key bone on two rigs (facing
    removed): what a T-pose and an A-pose rig differ by (about 45 at the shoulders)."""
    da, db = a.rest_directions(), b.rest_directions()
    both = (np.abs(da).sum(1) > 0) & (np.abs(db).sum(1) > 0)
    angles = np.degrees(np.arccos(np.clip((da * db).sum(1), -1.0, 1.0)))
    return {JOINTS[k]: float(angles[k]) for k in range(len(JOINTS)) if both[k]}

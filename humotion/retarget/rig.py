"""A rig understood for retargeting: key joints, body parts and rest-pose alignment of a skeleton.

The alignment is humotion.canonical's: per canonical joint, the rotation taking the canonical
T-pose's bone directions onto the rig's rest bones (the root's facing by yaw alone; every other
joint its parent's plus the smallest turn onto its own bone). A world rotation W of a rig's
driving joint times that alignment A is the joint's rotation away from the T-pose, the same
quantity on every rig; so pose transfer is W_target = W_source @ A_source @ A_target^T, whatever
each rig's zero pose (T-pose, A-pose, or the game rig's legs-up zero pose).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from functools import cached_property

import torch

from humotion import canonical, rotations as rot
from humotion.canonical import END_SITE_PARENTS, END_SITES, JOINTS, PARENTS
from humotion.retarget.contacts import floor_height
from humotion.retarget.keyjoints import KEY_POINTS, LEG_JOINTS, SIDES, Tree, find_key_joints, has_legs
from humotion.retarget.parts import PARTS, label_parts, membership_matrix
from humotion.skeleton import Skeleton

_CANONICAL_DEPTH = Skeleton(JOINTS, PARENTS, torch.zeros(len(JOINTS), 3)).depth().tolist()
_LEFT, _UP, _FORWARD = torch.eye(3, dtype=torch.float64)  # +X, +Y, +Z
_LEGS = {f"{side}_{k}" for side in SIDES for k in LEG_JOINTS}
# Finger names: thumb, index, middle, ring, little; 3ds Max's biped numbers them Finger0-4.
_FINGERS = [re.compile(p, re.I) for p in (r"thumb|finger0", r"index|finger1", r"mid|finger2", r"ring|finger3",
                                               r"pinky|little|finger4")]
_TWIST = re.compile(r"twist|roll", re.I)


@dataclass(frozen=True, eq=False)
class Rig:
    """A skeleton with its key joints (canonical names -> its joint or end-site names, see
    humotion.retarget.keyjoints), part labels (J,) int64 into PARTS, and per canonical joint the
    driving joint (22,) int64, the alignment (22, 3, 3) float64 (as the retargeter's rotations)
    and the bone between key points in the canonical frame (22, 3), and (5, 3) for end points,
    float32 metres."""

    skeleton: Skeleton
    key_joints: dict[str, str | None]
    parts: torch.Tensor
    drivers: torch.Tensor
    alignment: torch.Tensor
    bones: torch.Tensor
    end_bones: torch.Tensor
    label: str = ""

    @classmethod
    def of(cls, skeleton: Skeleton, overrides: dict | None = None, label: str = "") -> "Rig":
        """Understand a skeleton. overrides: {"joints": key point -> joint, "parts": joint -> part}
        (humotion.retarget.parts.load_overrides). Raises MissingKeyJoints naming what is missing."""
        overrides = overrides or {}
        keys = find_key_joints(skeleton, overrides.get("joints"), label)
        parts = label_parts(skeleton, keys, overrides.get("parts"))
        drivers, alignment, bones, end_bones = canonical.rest_alignments(skeleton, keys)
        return cls(skeleton, keys, parts, drivers, alignment, bones, end_bones, label)

    @property
    def membership(self) -> torch.Tensor:
        """P (6, J + 1) float32: part membership of every joint, last column the root velocity (all 1)."""
        return membership_matrix(self.parts)

    def part_of(self, joint: str) -> str:
        return PARTS[self.parts[self.skeleton.index(joint)]]

    @cached_property
    def owners(self) -> torch.Tensor:
        """(J,) int64 canonical joint whose rotation sets each joint's world rotation, -1 for none.
        Where several canonical joints share one driving joint (a rig without a collar or with
        two spine joints), the deepest wins: the others are bones of no length. A rig without
        legs has its leg key points on the pelvis; they own nothing."""
        owners = torch.full((self.skeleton.num_joints,), -1, dtype=torch.int64)
        for k in sorted(range(len(JOINTS)), key=lambda k: _CANONICAL_DEPTH[k]):
            if self.legs or JOINTS[k] not in _LEGS:
                owners[self.drivers[k]] = k
        return owners

    @property
    def legs(self) -> bool:
        """False for an upper-body rig (no legs: no feet to plant, no leg IK)."""
        return has_legs(self.key_joints)

    @cached_property
    def ground(self) -> list[int]:
        """Joints above the pelvis (a root bone such as iClone's RL_BoneRoot), root first: they
        stand on the floor under the hips (see standing)."""
        chain, j = [], self.skeleton.parents[self.joint("pelvis")]
        while j >= 0:
            chain.append(j)
            j = self.skeleton.parents[j]
        return chain[::-1]

    @cached_property
    def standing(self) -> torch.Tensor:
        """(3, 3) float64 world rotation of the ground joints (all at rest between them) when the
        rig stands facing +Z: their chain to the pelvis turned upright (the smallest turn), then
        turned about the vertical so that the hips' left points along +X. A ground joint at the
        pelvis itself only faces +Z."""
        rest = self.skeleton.rest_positions(torch.float64)
        up = rest[self.joint("pelvis")] - rest[self.ground[0]] if self.ground else torch.zeros(3, dtype=torch.float64)
        turn = canonical.turn_between(up, _UP, _FORWARD) if up.norm() > 1e-6 else torch.eye(3, dtype=torch.float64)
        side = turn @ (self.alignment[0] @ _LEFT)
        yaw = rot.convert(torch.tensor([0.0, -math.atan2(-side[2], side[0]), 0.0], dtype=torch.float64),
                          "rotvec", "matrix")
        return yaw @ turn

    def ground_height(self) -> float:
        """Height of the pelvis above the ground joints when standing (0 without), metres."""
        rest = self.skeleton.rest_positions(torch.float64)
        return float((rest[self.joint("pelvis")] - rest[self.ground[0]]).norm()) if self.ground else 0.0

    @property
    def on_floor(self) -> bool:
        """Whether the rig has a root bone on the floor (ground joints well below the hips)."""
        return self.ground_height() > max(0.5 * self.hip_height(), 0.1)

    def clearance(self) -> float:
        """Height of the rig's lowest key point above the floor when it stands, metres: for a rig
        modelled standing at or above y = 0 (a character), that point's rest height; else 0."""
        t_pose = float(self.t_pose.rest_points(torch.float64)[:, 1].min())
        rest = float(self.skeleton.rest_positions(torch.float64)[:, 1].min())
        upright = abs(rest - t_pose) < 0.1 * self.hip_height()  # its zero pose's legs point down too
        return float(max(t_pose, 0.0)) if upright and self.legs and not self.on_floor else 0.0

    def key_points(self, world_rotations: torch.Tensor, world_positions: torch.Tensor) -> torch.Tensor:
        """(T, K, 3) world positions of every key point the rig has, from forward kinematics."""
        return self.points(world_rotations, world_positions, [k for k in KEY_POINTS if self.key_joints[k] is not None])

    def floor_of(self, motion) -> float:
        """Height of the floor a motion on this rig stands on, metres: its root bone's median
        height (on_floor), else its key points' floor (contacts.floor_height) less the
        clearance. retarget(..., floor=rig.floor_of(its_own_clip)) stands where its clips do."""
        world = motion.world()
        if self.on_floor:
            return float(world[1][:, self.ground[0], 1].double().median())
        return floor_height(self.key_points(*world)) - self.clearance()

    def trunk_length(self) -> float:
        """Pelvis to head in the T-pose, metres: what root motion scales with when a rig has no legs."""
        rest = self.t_pose.rest_positions(torch.float64)
        return float((rest[JOINTS.index("head")] - rest[0]).norm())

    @cached_property
    def fingers(self) -> dict[int, tuple[str, int, int]]:
        """Finger joints: joint -> (side, finger 0-4 from the thumb, segment from the hand)."""
        tree, out = Tree(self.skeleton), {}
        for side in SIDES:
            wrist = self.joint(f"{side}_wrist")
            for j in tree.subtree(wrist)[1:]:
                finger = next((f for f, p in enumerate(_FINGERS) if p.search(self.skeleton.names[j])), None)
                if finger is not None:  # (subtree lists a joint after its ancestors)
                    above = tree.ancestors(j)
                    out[j] = (side, finger, sum(out[a][1] == finger for a in above[1:above.index(wrist)] if a in out))
        return out

    @cached_property
    def finger_alignment(self) -> dict[int, torch.Tensor]:
        """Finger joint -> (3, 3) float64 alignment, made as the key joints' are
        (canonical.rest_alignments): its parent's (the hand's for a first segment) turned by the
        smallest turn from the hand's direction onto its own bone (to its next segment, else its
        end site; none: the parent's).
        A finger's world rotation times it is the same on every rig for the same finger pose."""
        rest = self.skeleton.rest_positions(torch.float64)
        ends = self.skeleton.rest_end_site_positions(torch.float64)
        out: dict[int, torch.Tensor] = {}
        for j in sorted(self.fingers):  # parents first
            side, finger, _ = self.fingers[j]
            inherited = out.get(self.skeleton.parents[j], self.alignment[JOINTS.index(f"{side}_wrist")])
            along = [rest[c] for c in self.skeleton.children(j) if self.fingers.get(c, (side, -1, 0))[1] == finger]
            along += [ends[e] for e, p in enumerate(self.skeleton.end_site_parents) if p == j]
            bone = along[0] - rest[j] if along else torch.zeros(3, dtype=torch.float64)
            hand = inherited @ (_LEFT if side == "left" else -_LEFT)
            out[j] = (canonical.turn_between(hand, bone, inherited[:, 2]) @ inherited if bone.norm() > 1e-6
                      else inherited)
        return out

    @cached_property
    def twists(self) -> dict[int, tuple[int, float]]:
        """Twist bones between two key joints: joint -> (the key joint b ending its segment, its
        share t in [0, 1] of the way there): it turns about the segment by t times b's twist."""
        rest, out = self.skeleton.rest_positions(torch.float64), {}
        for j, name in enumerate(self.skeleton.names):
            a = self.skeleton.parents[j]
            if not _TWIST.search(name) or a < 0 or self.owners[j] >= 0 or self.owners[a] < 0:
                continue
            below = [c for c in self.skeleton.children(a) + self.skeleton.children(j) if self.owners[c] >= 0]
            if below:  # on the segment's line (not a rib or breast helper beside it)
                b = below[0]
                segment = rest[b] - rest[a]
                share = float((rest[j] - rest[a]) @ segment) / max(float(segment @ segment), 1e-12)
                if (rest[j] - rest[a] - share * segment).norm() < 0.2 * segment.norm():
                    out[j] = (b, min(max(share, 0.0), 1.0))
        return out

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
        points = self.t_pose.rest_points(torch.float64)
        return float(points[0, 1] - points[:, 1].min())

    def points(self, world_rotations: torch.Tensor, world_positions: torch.Tensor, keys) -> torch.Tensor:
        """(T, K, 3) world positions of key points (joints or end sites) from forward kinematics
        results (T, J, 3, 3) and (T, J, 3)."""
        sk = self.skeleton
        out = []
        for key in keys:
            name = self.key_joints[key]
            if name in sk.names:
                out.append(world_positions[:, sk.index(name)])
            else:
                e = sk.end_site_names.index(name)
                p = sk.end_site_parents[e]
                offset = sk.end_site_offsets[e].to(world_positions.dtype)
                out.append(world_positions[:, p] + world_rotations[:, p] @ offset)
        return torch.stack(out, dim=1)

    def rest_directions(self) -> torch.Tensor:
        """(22, 3) float64 unit rest direction of each canonical joint's bone from its parent, in
        the rig's facing frame (rows of zeros for the root and bones of no length)."""
        rest = self.skeleton.rest_points(torch.float64)
        names = list(self.skeleton.names) + list(self.skeleton.end_site_names)
        at = rest[[names.index(self.key_joints[k]) for k in JOINTS]]
        vectors = torch.cat([torch.zeros(1, 3, dtype=torch.float64), at[1:] - at[list(PARENTS[1:])]])
        vectors = vectors @ self.alignment[0]  # undo the rig's facing (yaw)
        length = vectors.norm(dim=1, keepdim=True)
        return torch.where(length > 1e-6, vectors / length.clamp_min(1e-12), 0.0)


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
    both = (da.abs().sum(1) > 0) & (db.abs().sum(1) > 0)
    angles = torch.rad2deg(torch.arccos((da * db).sum(1).clamp(-1.0, 1.0)))
    return {JOINTS[k]: float(angles[k]) for k in range(len(JOINTS)) if both[k]}

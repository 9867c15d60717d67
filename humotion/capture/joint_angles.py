"""From estimated 3D joint positions to a skeleton's joint angles (video capture, steps 6 and 7).

A lifting network gives positions of the 22 canonical joints whose bones have the wrong lengths,
changing from frame to frame. :func:`correct_bone_lengths` gives every bone the template's length
and keeps its direction; :func:`positions_to_rotations` turns the positions into local joint
rotations plus the root position, so that forward kinematics on the skeleton gives them back.

How a joint's rotation is chosen. Each joint with a child aims one bone (its own child bone, the
hips line for the pelvis) exactly along the observed one by the smallest turn from its parent's
frame. The turn about that bone (the twist) then comes from references, taken in order of
preference, each trusted only as far as it is well defined:

- pelvis: the line from the hips' midpoint up to spine1;
- spine1: the mean of the hips and shoulders lines; spine2: the shoulders line; spine3: the
  collars line, else (collars on one point, as in CMU rigs) the shoulders line;
- hips and shoulders: the plane of the limb (its knee or elbow flexion axis), ankles: the plane of
  shank and foot. A straight limb has no plane, so its twist fades to the stable fallback; a knee
  or elbow bent the wrong way (a network's error) shows as a half-turn twist of the hip or
  shoulder, left for the refinement's pose prior to penalise;
- neck, collars, knees, elbows: no reference; the smallest turn from the parent's frame, which
  for a knee or elbow whose hip or shoulder followed the limb plane is a pure hinge.

Joints without a child among the 22 (head, wrists, feet) keep their parent's orientation.
Forward kinematics reproduces positions exactly when the pose is reachable by the skeleton: its
bones have the skeleton's lengths and the rigid fans at the pelvis (hips, spine1) and at spine3
(neck, collars) have the skeleton's shape. Otherwise it gives the nearest such pose, bone by bone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch.nn.functional import normalize

from humotion import rotations as rot
from humotion.canonical import JOINTS, PARENTS
from humotion.skeleton import Skeleton, local_rotations

# A bone whose observed length is below this share of its length in the skeleton points nowhere
# reliable: its direction is taken from further along the chain (see correct_bone_lengths).
DEGENERATE_SHARE = 0.25
# A twist reference is ignored below the first strength and fully trusted above the second. For a
# limb plane the strength is the sine of the bend angle (0.1: 6 degrees, 0.3: 17 degrees); for a
# line, its length across the aimed bone relative to the skeleton's.
TWIST_UNSURE, TWIST_SURE = 0.1, 0.3


def _checked_positions(positions, names: tuple[str, ...]) -> torch.Tensor:
    """positions as a floating tensor of shape (..., len(names), 3), all finite; ValueError otherwise."""
    positions = torch.as_tensor(positions)
    if not positions.is_floating_point():
        positions = positions.float()
    if positions.dim() < 2 or positions.shape[-2:] != (len(names), 3):
        raise ValueError(f"positions must have shape (..., {len(names)}, 3) (joints, xyz in metres), "
                         f"got {tuple(positions.shape)}")
    finite = torch.isfinite(positions).all(-1)
    if not finite.all():
        where = [int(i) for i in torch.nonzero(~finite)[0]]
        raise ValueError(f"positions contain NaN or infinity (first at leading index {tuple(where[:-1])}, "
                         f"joint {names[where[-1]]!r})")
    return positions


def correct_bone_lengths(positions, skeleton: Skeleton) -> torch.Tensor:
    """Positions whose every bone has the skeleton's length and keeps its observed direction.

    positions: (..., J, 3) joint positions in metres, J = skeleton.num_joints (leading dimensions:
    frames, people, ...). Returns (..., J, 3): the root where it was, then, parents before children,
    corrected child = corrected parent + length * unit(observed child - observed parent).
    A bone shorter than DEGENERATE_SHARE of its length in the skeleton has no reliable direction:
    it takes the direction from its parent to the first joint down its first-child chain that is
    far enough (spine1 lying on the pelvis follows the pelvis-to-spine2 line), else the skeleton's
    rest direction. Differentiable.
    """
    positions = _checked_positions(positions, skeleton.names)
    points, parents, shortest, rest_directions, lengths, paths = (
        torch.as_tensor(a, device=positions.device) for a in _bone_plan(skeleton))
    vectors = positions[..., points, :] - positions[..., parents, None, :]        # (..., J-1, L, 3)
    usable = vectors.norm(dim=-1) > shortest.to(positions.dtype)
    first = usable.to(torch.uint8).argmax(-1, keepdim=True)                      # nearest usable point
    chosen = torch.take_along_dim(vectors, first[..., None], dim=-2)[..., 0, :]
    directions = torch.where(usable.any(-1, keepdim=True), normalize(chosen, dim=-1), rest_directions.to(positions.dtype))
    bones = lengths.to(positions.dtype)[:, None] * directions                    # (..., J-1, 3)
    root = positions[..., :1, :]
    return root + torch.einsum("jk,...kd->...jd", paths.to(positions.dtype), bones)


def _bone_plan(skeleton: Skeleton) -> tuple[np.ndarray, ...]:
    """correct_bone_lengths' tables for bones 1..J-1: points (J-1, L), each bone's first-child
    chain padded with its joint; parents (J-1,); shortest (J-1, L) usable length of the vector
    parent -> point (inf on padding); rest_directions (J-1, 3); lengths (J-1,); paths (J, J-1),
    1 where bone k lies between the root and joint j."""
    rest = skeleton.rest_positions(torch.float64).numpy()
    chains = [_first_child_chain(skeleton, joint) for joint in range(1, skeleton.num_joints)]
    width = max(len(c) for c in chains)
    points = np.array([c + [c[0]] * (width - len(c)) for c in chains])
    parents = np.array(skeleton.parents[1:])
    shortest = np.maximum(DEGENERATE_SHARE * np.linalg.norm(rest[points] - rest[parents, None], axis=-1), 1e-6)
    shortest[np.arange(width)[None] >= np.array([len(c) for c in chains])[:, None]] = np.inf
    offsets = skeleton.offsets[1:].double().numpy()
    lengths = np.linalg.norm(offsets, axis=1)
    rest_directions = offsets / np.maximum(lengths, 1e-12)[:, None]
    paths = np.zeros((skeleton.num_joints, skeleton.num_joints - 1))
    for joint in range(1, skeleton.num_joints):
        paths[joint] = paths[skeleton.parents[joint]]
        paths[joint, joint - 1] = 1.0
    return points, parents, shortest, rest_directions, lengths, paths


def _first_child_chain(skeleton: Skeleton, joint: int) -> list[int]:
    """joint, its first child, that child's first child, ... down to a leaf."""
    chain = [joint]
    while children := skeleton.children(chain[-1]):
        chain.append(children[0])
    return chain


@dataclass(frozen=True)
class _Line:
    """The vector from the mean of the `start` joints to the mean of the `end` joints."""

    start: tuple[str, ...]
    end: tuple[str, ...]

    def vector(self, positions: torch.Tensor) -> torch.Tensor:
        """(..., 3) from (..., 22, 3) positions."""
        def mean(names):
            return positions[..., [JOINTS.index(n) for n in names], :].mean(-2)
        return mean(self.end) - mean(self.start)

    def rest_vector(self, rest: torch.Tensor) -> torch.Tensor:
        return self.vector(rest)


@dataclass(frozen=True)
class _LimbPlane:
    """Normal of the plane through three joints a, b, c: unit(b - a) x unit(c - b), whose length
    is the sine of the bend at b; rest_axis: its direction in the T-pose (the flexion axis)."""

    joints: tuple[str, str, str]
    rest_axis: tuple[float, float, float]

    def vector(self, positions: torch.Tensor) -> torch.Tensor:
        a, b, c = (positions[..., JOINTS.index(n), :] for n in self.joints)
        return torch.linalg.cross(normalize(b - a, dim=-1), normalize(c - b, dim=-1))

    def rest_vector(self, rest: torch.Tensor) -> torch.Tensor:
        return torch.tensor(self.rest_axis, dtype=rest.dtype, device=rest.device)


@dataclass(frozen=True)
class _Aim:
    """A joint's rotation: `bone` points exactly along the observed one; `twist` references, in
    order of preference, set the turn about it."""

    bone: _Line
    twist: tuple[_Line | _LimbPlane, ...] = ()


def _bone(joint: str, child: str) -> _Line:
    return _Line((joint,), (child,))


# Elbow flexion axis in the canonical T-pose: the forearm bends forward and 29 degrees up (measured
# on CMU and HDM05 skeletons mapped onto the canonical body: 27-30 degrees over three subjects).
_ELBOW_TILT = math.radians(29.0)
_SHOULDERS = _Line(("right_shoulder",), ("left_shoulder",))
# Half way between the hips and the shoulders lines: the lower spine takes part of the torso's
# twist (on CMU takes this halves the spine1/spine2 twist error of using the shoulders alone).
_WAIST = _Line(("right_hip", "right_shoulder"), ("left_hip", "left_shoulder"))


def _limb_aims(side: str, sign: float) -> dict[str, _Aim]:
    """Aims of one side's limbs; sign: +1 left (+X), -1 right."""
    hip, knee, ankle, foot, collar, shoulder, elbow, wrist = (
        f"{side}_{n}" for n in ("hip", "knee", "ankle", "foot", "collar", "shoulder", "elbow", "wrist"))
    elbow_axis = (0.0, -sign * math.cos(_ELBOW_TILT), sign * math.sin(_ELBOW_TILT))
    return {
        hip: _Aim(_bone(hip, knee), (_LimbPlane((hip, knee, ankle), (1.0, 0.0, 0.0)),)),
        knee: _Aim(_bone(knee, ankle)),
        ankle: _Aim(_bone(ankle, foot), (_LimbPlane((knee, ankle, foot), (-1.0, 0.0, 0.0)),)),
        collar: _Aim(_bone(collar, shoulder)),
        shoulder: _Aim(_bone(shoulder, elbow), (_LimbPlane((shoulder, elbow, wrist), elbow_axis),)),
        elbow: _Aim(_bone(elbow, wrist)),
    }


_AIMS: dict[str, _Aim] = {
    "pelvis": _Aim(_Line(("right_hip",), ("left_hip",)), (_Line(("left_hip", "right_hip"), ("spine1",)),)),
    "spine1": _Aim(_bone("spine1", "spine2"), (_WAIST,)),
    "spine2": _Aim(_bone("spine2", "spine3"), (_SHOULDERS,)),
    "spine3": _Aim(_bone("spine3", "neck"), (_Line(("right_collar",), ("left_collar",)), _SHOULDERS)),
    "neck": _Aim(_bone("neck", "head")),
} | _limb_aims("left", 1.0) | _limb_aims("right", -1.0)


def positions_to_rotations(positions, skeleton: Skeleton) -> tuple[torch.Tensor, torch.Tensor]:
    """Local joint rotations and root positions that pose the skeleton at the given joints.

    positions: (..., 22, 3) canonical joint positions in metres (bone-corrected ones are
        reproduced exactly where the pose is reachable; only bone directions are used).
    skeleton: a skeleton with the canonical joints (humotion.canonical.JOINTS), any bone lengths;
        its rest pose defines the zero rotations.
    Returns (rotations (..., 22, 4) wxyz unit quaternions, each joint relative to its parent and
    the pelvis's in the world; root positions (..., 3) metres, the pelvis). The module docstring
    says how each joint's twist is chosen. Differentiable almost everywhere (not at exactly
    opposite bones).
    """
    if skeleton.names != JOINTS:
        raise ValueError("positions_to_rotations needs a skeleton with the canonical joints (humotion.canonical.JOINTS)")
    positions = _checked_positions(positions, JOINTS)
    rest = skeleton.rest_positions().to(device=positions.device, dtype=positions.dtype)
    identity = torch.eye(3, dtype=positions.dtype, device=positions.device).expand(positions.shape[:-2] + (3, 3))
    world: list[torch.Tensor] = []
    for joint, parent in enumerate(PARENTS):
        parent_frame = world[parent] if parent >= 0 else identity
        aim = _AIMS.get(JOINTS[joint])
        world.append(parent_frame if aim is None else _aimed_frame(aim, positions, rest, parent_frame))
    world_frames = torch.stack(world, dim=-3)
    return rot.matrix_to_quat(local_rotations(world_frames, PARENTS)), positions[..., 0, :]


def _aimed_frame(aim: _Aim, positions: torch.Tensor, rest: torch.Tensor, parent_frame: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) world orientation of a joint: the smallest turn from its parent's frame that
    aims its bone, then the twist about the bone that its references ask for."""
    bone = aim.bone.vector(positions)
    swing = rot.rotation_matrix_between(parent_frame @ aim.bone.rest_vector(rest), bone)
    untwisted = swing @ parent_frame
    axis = normalize(bone, dim=-1)
    angle = _twist_angle(aim, positions, rest, untwisted, axis)
    return rot.convert(axis * angle[..., None], "rotvec", "matrix") @ untwisted


def _twist_angle(aim: _Aim, positions: torch.Tensor, rest: torch.Tensor, untwisted: torch.Tensor,
                 axis: torch.Tensor) -> torch.Tensor:
    """(...) radians about the (..., 3) unit bone axis that line each twist reference up with its
    observed direction. References are blended in order: each takes the share it is trusted with
    (see TWIST_SURE) of what earlier ones left; the rest stays with no twist."""
    def across(v: torch.Tensor, along: torch.Tensor) -> torch.Tensor:
        return v - (v * along).sum(-1, keepdim=True) * along

    rest_bone = normalize(aim.bone.rest_vector(rest), dim=-1)
    blend = axis.new_zeros(axis.shape[:-1] + (2,))
    left = axis.new_ones(axis.shape[:-1])
    for reference in aim.twist:
        rest_reference = reference.rest_vector(rest)
        rest_strength = float(across(rest_reference, rest_bone).norm())
        if rest_strength < 1e-6:  # the skeleton itself gives this reference no direction
            continue
        seen = across(reference.vector(positions), axis)
        expected = across((untwisted @ rest_reference[:, None])[..., 0], axis)
        cos = (expected * seen).sum(-1)
        sin = (axis * torch.linalg.cross(expected, seen)).sum(-1)
        trust = _smoothstep((seen.norm(dim=-1) / rest_strength - TWIST_UNSURE) / (TWIST_SURE - TWIST_UNSURE))
        blend = blend + (left * trust)[..., None] * normalize(torch.stack([cos, sin], -1), dim=-1)
        left = left * (1 - trust)
    blend = blend + torch.stack([left, torch.zeros_like(left)], -1)
    return torch.atan2(blend[..., 1], blend[..., 0])


def _smoothstep(x: torch.Tensor) -> torch.Tensor:
    x = x.clamp(0, 1)
    return x * x * (3 - 2 * x)

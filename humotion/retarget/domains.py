"""Skeleton domains of the learned retargeter, and the motion features its networks read and write.

A domain is one joint structure (the 31-joint CMU ASF skeleton, the 100-joint iClone game rig)
worn by any number of bodies with other bone lengths. Its networks model the joints on the paths
from the pelvis to the rig's 22 key joints (humotion.retarget.keyjoints), 25 on the CMU
skeleton and 24 on the game rig; the others (fingers, toe ends, twist and share bones, face)
are not modelled and take the domain's mean local rotation from its training data.

A skeleton belongs to a domain when it has every modelled joint by name with the same parent
(the domain's first joint, the pelvis, may hang below other joints: the game rig's 101-joint
variant has a floor bone above it). Features per frame, in the frame of the clip's first
frame (turned about Y so the pelvis faces +Z there, its ground point at the origin):
- rotations (J, 6): 6D rotations (humotion.rotations), the pelvis's world rotation and every
  other modelled joint's local rotation;
- root (3,): the pelvis's horizontal velocity x, z in hip heights per second (0 on the first
  frame) and its height in hip heights (hip height: pelvis above the soles in the T-pose,
  humotion.retarget.rig.Rig.hip_height), so a longer-legged body takes longer strides.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from humotion import rotations as rot
from humotion.motion import Motion
from humotion.retarget.rig import Rig
from humotion.skeleton import Skeleton, forward_kinematics

END_EFFECTORS = ("head", "left_wrist", "right_wrist", "left_ankle", "right_ankle", "left_foot", "right_foot")
"""Key joints whose pelvis-relative positions a retargeted motion keeps (in units of body height)."""


@dataclass(frozen=True)
class DomainSpec:
    """One joint structure: name; joints (J,) modelled joint names, pelvis first, parents before
    children; parents (J,) indices into joints (-1 for the pelvis); parts (J,) index into
    humotion.retarget.parts.PARTS; effectors: index into joints of each END_EFFECTORS joint;
    others: names of the reference skeleton's other joints (set to the domain's mean rotation)."""

    name: str
    joints: tuple[str, ...]
    parents: tuple[int, ...]
    parts: tuple[int, ...]
    effectors: tuple[int, ...]
    others: tuple[str, ...]

    @classmethod
    def of(cls, name: str, skeleton: Skeleton) -> "DomainSpec":
        """The domain of a reference skeleton (its key joints found as humotion.retarget.Rig does)."""
        rig = Rig.of(skeleton, label=name)
        pelvis = rig.joint("pelvis")
        keep = {pelvis}
        for driver in rig.drivers:
            j = int(driver)
            while j != pelvis:
                if j < 0:
                    raise ValueError(f"{name}: key joint {skeleton.names[driver]!r} is not below the pelvis "
                                     f"{skeleton.names[pelvis]!r}")
                keep.add(j)
                j = skeleton.parents[j]
        joints = sorted(keep)
        parents = tuple(joints.index(skeleton.parents[j]) if j != pelvis else -1 for j in joints)
        return cls(name, tuple(skeleton.names[j] for j in joints), parents,
                   tuple(int(rig.parts[j]) for j in joints),
                   tuple(joints.index(rig.joint(k)) for k in END_EFFECTORS),
                   tuple(n for j, n in enumerate(skeleton.names) if j not in keep))

    @property
    def num_joints(self) -> int:
        return len(self.joints)

    def indices(self, skeleton: Skeleton) -> list[int] | None:
        """The skeleton's index of every modelled joint, or None when it is not of this domain."""
        position = {n: i for i, n in enumerate(skeleton.names)}
        if any(n not in position for n in self.joints):
            return None
        found = [position[n] for n in self.joints]
        if any(skeleton.parents[found[j]] != found[p] for j, p in enumerate(self.parents) if p >= 0):
            return None
        return found

    def describe(self) -> str:
        return f"{self.name} ({len(self.joints) + len(self.others)} joints, pelvis {self.joints[0]!r})"


@dataclass(frozen=True)
class Body:
    """What the networks need of one skeleton of a domain: offsets (J, 3) of the modelled joints
    in metres (the pelvis's zero: its rest position says nothing of the body), facing (3, 3) the
    pelvis's rest alignment (Rig.alignment[0]), hip_height and height (standing, T-pose) in metres."""

    offsets: torch.Tensor
    facing: torch.Tensor
    hip_height: float
    height: float

    @classmethod
    def of(cls, spec: DomainSpec, rig: Rig) -> "Body":
        index = spec.indices(rig.skeleton)
        if index is None:
            raise ValueError(f"skeleton {rig.label or rig.skeleton!r} is not of domain {spec.describe()}")
        offsets = rig.skeleton.offsets[index].clone()
        offsets[0] = 0.0
        return cls(offsets, rig.alignment[0].float(), rig.hip_height(),
                   rig.standing_height())


def read_motion(motion: Motion, spec: DomainSpec) -> tuple[torch.Tensor, torch.Tensor]:
    """(rotations (T, J, 3, 3): the pelvis's world rotation then the local rotations of the
    modelled joints; pelvis world positions (T, 3), metres) of a motion on a skeleton of the domain."""
    index = spec.indices(motion.skeleton)
    world, positions = motion.world()
    rotations = rot.quat_to_matrix(motion.rotations[:, index])
    rotations[:, 0] = world[:, index[0]]
    return rotations, positions[:, index[0]]


def yaw_matrix(angle: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotations by angle (...) radians about +Y."""
    return rot.convert(torch.stack([torch.zeros_like(angle), angle, torch.zeros_like(angle)], -1), "rotvec", "matrix")


def to_features(rotations: torch.Tensor, pelvis: torch.Tensor, facing: torch.Tensor, hip_height: torch.Tensor,
                fps: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Network features of clips or windows (module docstring).

    rotations (..., T, J, 3, 3) and pelvis (..., T, 3) from read_motion; facing (..., 3, 3) and
    hip_height (...) of each body (Body). Returns rotations (..., T, J, 6), root (..., T, 3), and
    the frame they are in: yaw (...) radians and origin (..., 3) metres, for from_features.
    """
    forward = (rotations[..., 0, 0, :, :] @ facing)[..., :, 2]                 # first frame's pelvis
    yaw = torch.atan2(forward[..., 0], forward[..., 2])
    turn = yaw_matrix(-yaw)[..., None, :, :]                                   # (..., 1, 3, 3)
    origin = pelvis[..., 0, :] * torch.tensor([1.0, 0.0, 1.0])
    rotations = torch.cat([(turn @ rotations[..., 0, :, :])[..., None, :, :], rotations[..., 1:, :, :]], -3)
    position = ((pelvis - origin[..., None, :])[..., None, :] @ turn.transpose(-1, -2))[..., 0, :]
    position = position / hip_height[..., None, None]
    velocity = torch.diff(position[..., [0, 2]], dim=-2, prepend=position[..., :1, [0, 2]]) * fps
    root = torch.cat([velocity, position[..., 1:2]], -1)
    return rot.convert(rotations, "matrix", "sixd"), root, yaw, origin


def from_features(rotations: torch.Tensor, root: torch.Tensor, yaw: torch.Tensor, origin: torch.Tensor,
                  hip_height: float, fps: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Inverse of to_features for one clip on a body with this hip height: rotations (T, J, 6)
    and root (T, 3) -> rotations (T, J, 3, 3) and pelvis world positions (T, 3), metres."""
    matrices = rot.convert(rotations, "sixd", "matrix")
    turn = yaw_matrix(yaw)
    matrices = torch.cat([(turn @ matrices[:, 0])[:, None], matrices[:, 1:]], 1)
    horizontal = torch.cumsum(root[:, :2], 0) / fps
    position = torch.stack([horizontal[:, 0], root[:, 2], horizontal[:, 1]], -1) * hip_height
    return matrices, position @ turn.T + origin


def joint_positions(spec: DomainSpec, rotations: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """(..., T, J, 3) positions of the modelled joints relative to the pelvis, metres, from 6D
    rotations (..., T, J, 6) (pelvis world, others local) and offsets (..., J, 3)."""
    matrices = rot.convert(rotations, "sixd", "matrix")
    root = torch.zeros(matrices.shape[:-3] + (3,), dtype=matrices.dtype)
    return forward_kinematics(matrices, root, offsets[..., None, :, :], spec.parents)[1]


def mean_rotations(motions: list[Motion], names: tuple[str, ...]) -> torch.Tensor:
    """(J, 4) mean local rotation (wxyz) of each of the J joints in `names` over the motions'
    frames (identity for a joint none of them has); float32."""
    sums = torch.zeros(len(names), 4)
    sums[:, 0] = 1e-6
    for motion in motions:
        for k, name in enumerate(names):
            if name in motion.skeleton.names:
                q = motion.rotations[:, motion.skeleton.index(name)]
                q = q * torch.where((q @ sums[k]) < 0, -1.0, 1.0)[:, None]    # one hemisphere
                sums[k] += q.sum(0)
    return torch.nn.functional.normalize(sums, dim=-1)


def domain_of(skeleton: Skeleton, specs) -> DomainSpec:
    """The domain of specs a skeleton belongs to; ValueError naming the domains otherwise."""
    for spec in specs:
        if spec.indices(skeleton) is not None:
            return spec
    known = "; ".join(spec.describe() for spec in specs)
    raise ValueError(f"a skeleton of {skeleton.num_joints} joints (root {skeleton.names[0]!r}) is of none of the "
                     f"skeleton domains these weights were trained on: {known}. Use the classical retargeter "
                     "(--method classical) or train weights on that skeleton (humotion train retarget).")


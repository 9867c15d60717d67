"""Kinematics and linear blend skinning of the body rig: one torch implementation, used by the
data generator (numpy in, numpy out) and by the learned body model (torch, differentiable).

Pose convention (SMPL-style): ``rotations`` are each joint's rest-relative rotation expressed in
world-aligned rest axes. World rotation A_j = A_parent(j) @ R_j; posed joint
p_j = p_parent + A_parent (rest_j - rest_parent); root p_0 = rest_0 + translation; the skinning
transform of bone j is x -> A_j (x - rest_j) + p_j = A_j x + t_j.

    A, t, joints = skinning_transforms(rest_joints, parents, rotations, translation)
    vertices = linear_blend_skinning(rest_vertices, weights, A, t)

Forward kinematics is humotion.skeleton.forward_kinematics' recursion evaluated one depth level
at a time (:func:`forward_kinematics_by_level`, checked equal to it in the tests), since a
per-joint loop over the 76-joint rig was most of a batch-1 forward pass. Learned skinning
weights (:class:`LearnedSkinWeights`) live here too.
"""

from __future__ import annotations

import functools

import numpy as np
import torch

from humotion import rotations as rot

GAP_JOINTS = {"shoulders": "upperarm01", "elbows": "lowerarm01", "wrists": "wrist", "hips": "upperleg01",
              "knees": "lowerleg01"}
"""Joint blend zones where the LBS-vs-DQS gap and the pose correctives are reported (both sides)."""


def _as_tensor(x, dtype: torch.dtype) -> torch.Tensor:
    return x if torch.is_tensor(x) else torch.tensor(np.asarray(x), dtype=dtype)


@functools.lru_cache(maxsize=16)
def depth_levels(parents: tuple[int, ...]) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Joints grouped by depth below the root, root level first: [(joints, their parents), ...]
    as index tensors (cached per rig)."""
    depth: list[int] = []
    for p in parents:
        depth.append(0 if p < 0 else depth[p] + 1)
    levels = []
    for k in range(max(depth) + 1):
        joints = [j for j, d in enumerate(depth) if d == k]
        levels.append((torch.tensor(joints), torch.tensor([max(parents[j], 0) for j in joints])))
    return levels


def forward_kinematics_by_level(local: torch.Tensor, root: torch.Tensor, offsets: torch.Tensor, parents):
    """humotion.skeleton.forward_kinematics for a deep rig, one batched 4x4 product per depth
    level (17 for the 76-joint body rig) instead of a step per joint: about 4x fewer tensor
    operations, which is most of a batch-1 forward pass. local (..., J, 3, 3), root (..., 3),
    offsets (..., J, 3); returns world rotations (..., J, 3, 3) and positions (..., J, 3);
    differentiable."""
    shape = local.shape[:-3]
    J = local.shape[-3]
    offsets = offsets.expand(shape + (J, 3))
    # local transforms [R_j | o_j] (the root's offset is its world position)
    top = torch.cat([local, torch.cat([root[..., None, :], offsets[..., 1:, :]], dim=-2)[..., None]], dim=-1)
    bottom = local.new_tensor([0.0, 0.0, 0.0, 1.0]).expand(shape + (J, 1, 4))
    transforms = torch.cat([top, bottom], dim=-2)  # (..., J, 4, 4)
    world = transforms
    for level, (joints, parent) in enumerate(depth_levels(tuple(int(p) for p in parents))):
        if level == 0:
            continue
        joints, parent = joints.to(local.device), parent.to(local.device)
        world = world.index_copy(-3, joints, world[..., parent, :, :] @ transforms[..., joints, :, :])
    return world[..., :3, :3], world[..., :3, 3]


def skinning_transforms(rest_joints, parents, rotations, translation):
    """Bone transforms of the pose convention above.

    rest_joints (J, 3) or (K, J, 3); rotations (K, J, 3, 3) matrices or (K, J, 4) wxyz
    quaternions; translation (K, 3). Returns (A (K, J, 3, 3), t (K, J, 3), posed joints (K, J, 3)),
    x -> A x + t per bone. Torch in: torch out, differentiable, in the rotations' dtype. numpy in:
    numpy out, float64.
    """
    as_numpy = not torch.is_tensor(rotations)
    dtype = torch.float64 if as_numpy else rotations.dtype
    rotations = _as_tensor(rotations, dtype).to(dtype)
    if rotations.shape[-1] == 4:
        rotations = rot.quat_to_matrix(rotations)
    rest = _as_tensor(rest_joints, dtype).to(dtype=dtype, device=rotations.device)
    rest = rest.expand(rotations.shape[:-2] + (3,))
    parents = [int(p) for p in parents]
    offsets = rest - rest[..., [max(p, 0) for p in parents], :]
    root = rest[..., 0, :] + _as_tensor(translation, dtype).to(dtype=dtype, device=rotations.device)
    A, joints = forward_kinematics_by_level(rotations, root, offsets.expand(rotations.shape[:-2] + (3,)), parents)
    t = joints - (A @ rest[..., None])[..., 0]
    if as_numpy:
        return A.numpy(), t.numpy(), joints.numpy()
    return A, t, joints


def linear_blend_skinning(vertices, weights, A, t):
    """Plain LBS: vertices (K, V, 3) or (V, 3), weights (V, J) or (K, V, J), bone transforms
    A (K, J, 3, 3), t (K, J, 3) -> (K, V, 3). Torch in: torch out (differentiable); numpy in:
    numpy out, float64."""
    as_numpy = not torch.is_tensor(A)
    dtype = torch.float64 if as_numpy else A.dtype
    A, t = _as_tensor(A, dtype).to(dtype), _as_tensor(t, dtype).to(dtype)
    vertices = _as_tensor(vertices, dtype).to(dtype)
    weights = _as_tensor(weights, dtype).to(dtype)
    count = A.shape[0]
    transforms = torch.cat([A.flatten(-2), t], dim=-1)  # (K, J, 12)
    blended = weights @ transforms  # (K, V, 12)
    vertices = vertices.expand((count,) + vertices.shape[-2:])
    out = (blended[..., :9].unflatten(-1, (3, 3)) @ vertices[..., None])[..., 0] + blended[..., 9:]
    return out.numpy() if as_numpy else out


def blend_zones(weights: np.ndarray, names, parents, threshold: float = 0.05) -> dict[str, np.ndarray]:
    """(V,) bool per GAP_JOINTS region: vertices skinned to both sides of the joint (the weight of
    the joint's subtree, over both body sides, between threshold and 1 - threshold), where linear
    blend skinning and dual quaternions differ most."""
    names, parents = list(names), [int(p) for p in parents]
    zones = {}
    for region, bone in GAP_JOINTS.items():
        zone = np.zeros(len(weights), dtype=bool)
        for s in ("L", "R"):
            subtree = {names.index(f"{bone}.{s}")}
            for j, p in enumerate(parents):
                if p in subtree:
                    subtree.add(j)
            share = weights[:, sorted(subtree)].sum(1)
            zone |= (share > threshold) & (share < 1 - threshold)
        zones[region] = zone
    return zones


def skin_support(weights: np.ndarray, parents, size: int) -> np.ndarray:
    """(V, size) bone indices each vertex may be skinned to: the bones Anny's weights use at
    the vertex (heaviest first), then their parents, then their children, then the parents'
    parents, as room allows; -1 pads. weights (V, J)."""
    parents = [int(p) for p in parents]
    children = [[c for c, p in enumerate(parents) if p == j] for j in range(len(parents))]
    out = np.full((len(weights), size), -1, dtype=np.int64)
    for v, row in enumerate(weights):
        used = [int(j) for j in np.argsort(-row) if row[j] > 0]
        rings = [used, [parents[j] for j in used if parents[j] >= 0], [c for j in used for c in children[j]],
                 [parents[parents[j]] for j in used if parents[j] >= 0 and parents[parents[j]] >= 0]]
        chosen: list[int] = []
        for ring in rings:
            for j in ring:
                if j not in chosen and len(chosen) < size:
                    chosen.append(j)
        out[v, :len(chosen)] = chosen
    return out


class LearnedSkinWeights(torch.nn.Module):
    """Skinning weights learned per vertex over a fixed neighbourhood of bones (see
    :func:`skin_support`): a softmax over that neighbourhood, so weights are non-negative, sum to
    one and are exactly zero for every other bone.

    num_vertices, num_joints, size: the neighbourhood's size per vertex.
    """

    def __init__(self, num_vertices: int, num_joints: int, size: int):
        super().__init__()
        self.num_joints = num_joints
        self.register_buffer("index", torch.zeros(num_vertices, size, dtype=torch.long))
        self.register_buffer("valid", torch.zeros(num_vertices, size, dtype=torch.bool))
        self.logits = torch.nn.Parameter(torch.zeros(num_vertices, size))

    @torch.no_grad()
    def init_from(self, weights: np.ndarray, parents, floor: float = 1e-4) -> None:
        """Neighbourhoods and logits from initial weights (V, J) (Anny's): softmax of
        log(weight + floor) over the neighbourhood, ~ the initial weights."""
        support = skin_support(weights, parents, self.index.shape[1])
        valid = support >= 0
        index = np.where(valid, support, 0)
        self.index.copy_(torch.as_tensor(index))
        self.valid.copy_(torch.as_tensor(valid))
        initial = np.take_along_axis(weights, index, axis=1) * valid
        self.logits.copy_(torch.as_tensor(np.log(initial + floor), dtype=self.logits.dtype))

    def sparse(self) -> torch.Tensor:
        """(V, size) weights over each vertex's neighbourhood (zero on padding)."""
        return torch.softmax(self.logits.masked_fill(~self.valid, -torch.inf), dim=-1)

    def forward(self) -> torch.Tensor:
        """Dense (V, J) weights."""
        w = self.sparse()
        dense = torch.zeros(w.shape[0], self.num_joints, dtype=w.dtype, device=w.device)
        return dense.scatter_add(1, self.index, w)

"""Kinematics and linear blend skinning of the body rig: one torch implementation, used by the
data generator (numpy in, numpy out) and by the learned body model (torch, differentiable).

Pose convention (SMPL-style): ``rotations`` are each joint's rest-relative rotation expressed in
world-aligned rest axes. World rotation A_j = A_parent(j) @ R_j; posed joint
p_j = p_parent + A_parent (rest_j - rest_parent); root p_0 = rest_0 + translation; the skinning
transform of bone j is x -> A_j (x - rest_j) + p_j = A_j x + t_j.

    A, t, joints = skinning_transforms(rest_joints, parents, rotations, translation)
    vertices = linear_blend_skinning(rest_vertices, weights, A, t)

Forward kinematics is humotion.skeleton.forward_kinematics' recursion evaluated one depth level
at a time (humotion.skeleton.forward_kinematics_by_level, checked equal to it in the tests), since a
per-joint loop over the 76-joint rig was most of a batch-1 forward pass. Skinning multiplies by
the weights block by block of vertices, each block with only the bones it uses
(:class:`SkinBlocks`, about a quarter of the rig on the full-resolution body; the speed of a
batched forward pass). Learned skinning weights (:class:`LearnedSkinWeights`) live here too.
"""

from __future__ import annotations

import numpy as np
import torch

from humotion import rotations as rot
from humotion.skeleton import forward_kinematics_by_level

GAP_JOINTS = {"shoulders": "upperarm01", "elbows": "lowerarm01", "wrists": "wrist", "hips": "upperleg01",
              "knees": "lowerleg01"}
"""Joint blend zones where the LBS-vs-DQS gap and the pose correctives are reported (both sides)."""


def _as_tensor(x, dtype: torch.dtype) -> torch.Tensor:
    return x if torch.is_tensor(x) else torch.tensor(np.asarray(x), dtype=dtype)


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


class SkinBlocks:
    """Skinning weights (V, J) cut into blocks of consecutive vertices, each keeping only the bones
    with weight somewhere in the block: the form :func:`linear_blend_skinning` multiplies by.

    A body mesh's vertices come in runs over a few neighbouring bones (on the full-resolution body
    a block of 512 vertices uses about 18 of the 76 bones), so blending the bone transforms per
    block does a fraction of a dense (V, J) product's work, and each block's blended transforms
    stay in cache while they are applied. Blocks are built on first use for a block size and kept
    (build one SkinBlocks per weights and reuse it, as the body model does at inference).

    weights (V, J) tensor. prune=False keeps every bone in every block: the gradient then reaches
    every entry of `weights`; with pruning (default) it reaches only bones a block uses, which
    leaves out only zero weights (exact for weights that are a softmax, as the learned ones are:
    a zero softmax output adds nothing to its logits' gradient).
    """

    def __init__(self, weights: torch.Tensor, prune: bool = True):
        self.weights, self.prune = weights, prune
        self._blocks: dict[int, list[tuple[torch.Tensor, torch.Tensor]]] = {}

    def blocks(self, rows: int) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """[(bones (n,) int64, weights (rows, n) of the block's vertices on them), ...] over
        consecutive blocks of `rows` vertices (the last one shorter)."""
        if rows not in self._blocks:
            pieces = self.weights.split(rows)
            device = self.weights.device
            if self.prune:  # which bones each block uses, read in one transfer from the device
                used = torch.stack([(w != 0).any(0) for w in pieces]).cpu()
                bones = [u.nonzero()[:, 0].to(device) for u in used]
            else:
                bones = [torch.arange(self.weights.shape[1], device=device)] * len(pieces)
            self._blocks[rows] = [(b, w.index_select(1, b)) for b, w in zip(bones, pieces)]
        return self._blocks[rows]


def block_rows(count: int, num_vertices: int, device: torch.device) -> int:
    """Vertices per block of :class:`SkinBlocks` for a batch of `count` meshes of `num_vertices`:
    on the CPU about 32k blended transform entries (12 per mesh and vertex) per block, so that
    they stay in cache, and 512 to 2,048 vertices (smaller blocks use fewer bones each: at
    batch 1, 2,048-vertex blocks of the 13,718-vertex mesh took about 0.95x the time of one
    block when idle, less with the other core busy); elsewhere (GPU) all vertices in one block."""
    return max(512, min(2048, 32768 // max(count, 1))) if device.type == "cpu" else max(num_vertices, 1)


def linear_blend_skinning(vertices, weights, A, t):
    """Plain LBS: vertices (K, V, 3) or (V, 3) (m), weights (V, J), (K, V, J) or a
    :class:`SkinBlocks` of (V, J) weights, bone transforms A (K, J, 3, 3), t (K, J, 3) (m) ->
    posed vertices (K, V, 3) (m): v' = sum_j w_vj (A_j v + t_j). Torch in: torch out
    (differentiable; with (V, J) weights that need no gradient and more vertices than a block,
    bones without weight in a block of vertices are skipped, see SkinBlocks); numpy in: numpy
    out, float64.

    The bone transforms are blended and applied block by block of vertices
    (:func:`skin_in_blocks`), vertex index last, so every elementwise step runs along the vertices
    in cache. The result
    is a (K, V, 3) view of coordinate planes (K, 3, V), not a contiguous tensor; vertices given
    as such a view (``planes.transpose(-1, -2)``, as the body model does) are read without a copy.
    """
    as_numpy = not torch.is_tensor(A)
    dtype = torch.float64 if as_numpy else A.dtype
    A, t = _as_tensor(A, dtype).to(dtype), _as_tensor(t, dtype).to(dtype)
    planes = _as_tensor(vertices, dtype).to(dtype).transpose(-1, -2)  # (K, 3, V) or (3, V)
    rows = block_rows(len(A), planes.shape[-1], planes.device)
    if not isinstance(weights, SkinBlocks):
        weights = _as_tensor(weights, dtype).to(dtype)
        if weights.dim() == 2:  # bones skipped only over several blocks and where no gradient is wanted
            weights = SkinBlocks(weights, prune=len(weights) > rows and not needs_gradient(weights))
    if isinstance(weights, SkinBlocks):
        out = skin_in_blocks(planes.split(rows, dim=-1), weights.blocks(rows), A, t, planes.shape[-1],
                             needs_gradient(planes, A, t, weights.weights))
    else:  # (K, V, J)
        transforms = torch.cat([A.flatten(-2), t], dim=-1)  # (K, J, 12)
        blended = transforms.transpose(1, 2) @ weights.transpose(1, 2)  # (K, 12, V)
        out = _apply_blended(blended, planes)
    out = out.transpose(1, 2)
    return out.numpy() if as_numpy else out


def skin_in_blocks(surfaces, blocks: list[tuple[torch.Tensor, torch.Tensor]], A: torch.Tensor, t: torch.Tensor,
                   num_vertices: int, gradient: bool) -> torch.Tensor:
    """LBS block by block of vertices: surfaces, an iterable of the mesh's consecutive vertex
    blocks as coordinate planes (K, 3, n) or (3, n) (m), blocks = SkinBlocks.blocks(n) for the
    same blocks, bone transforms A (K, J, 3, 3), t (K, J, 3) (m) -> posed coordinate planes
    (K, 3, V) (m). gradient: whether any block of the surface, A, t or the weights needs one.

    Per block, the bone transforms the block uses are blended in one matrix product (blended
    (K, 12, n): blended[k, 3c + d] = sum_j w_vj A[k, j, c, d], blended[k, 9 + c] = sum_j w_vj
    t[k, j, c]) and applied to the block's vertices while both are in cache. A block's surface
    can be computed just before it is skinned (a generator; the body model adds its pose
    correctives and expression so). Without a gradient to keep, each posed block is written
    straight into the result; with one, they are joined at the end.
    """
    count, num_joints = A.shape[:2]
    columns = torch.cat([A.flatten(-2), t], dim=-1).transpose(0, 1).reshape(num_joints, count * 12)  # (J, K 12)
    out = None if gradient else columns.new_empty(count, 3, num_vertices)
    pieces, start = [], 0
    for (bones, w), planes in zip(blocks, surfaces):
        blended = (columns.index_select(0, bones).T @ w.T).view(count, 12, -1)
        if out is None:
            pieces.append(_apply_blended(blended, planes))
        else:
            _apply_blended(blended, planes, out=out[..., start:start + len(w)])
        start += len(w)
    if start != num_vertices:
        raise ValueError(f"skin_in_blocks: the blocks cover {start} vertices, not {num_vertices}")
    return out if out is not None else torch.cat(pieces, dim=-1)


def needs_gradient(*tensors: torch.Tensor) -> bool:
    """Whether autograd records an operation on these tensors (any shape)."""
    return torch.is_grad_enabled() and any(x.requires_grad for x in tensors)


def _apply_blended(blended: torch.Tensor, planes: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
    """Blended transforms (K, 12, n) (layout of :func:`skin_in_blocks`) applied to vertices as
    coordinate planes (K, 3, n) or (3, n) -> (K, 3, n), written into `out` if given."""
    # split and unbind rather than slices: one cat or stack each in the backward pass, not a
    # zero-filled copy per slice
    rotation, translation = blended.split((9, 3), dim=1)  # (K, 9, n), (K, 3, n)
    a_x, a_y, a_z = rotation.unflatten(1, (3, 3)).unbind(2)  # columns of A: (K, 3, n) each
    x, y, z = planes.unsqueeze(-2).unbind(-3)  # (K, 1, n) or (1, n) each
    posed = torch.addcmul(translation, a_x, x)
    posed = torch.addcmul(posed, a_y, y)
    return torch.addcmul(posed, a_z, z, out=out)


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

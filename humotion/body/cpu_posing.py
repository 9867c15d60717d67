"""Posing a batch of bodies on the CPU when no gradient is wanted: the surface to pose (rest +
pose correctives + expression) is formed and skinned block by block of vertices, vertex-major
with the batch last, so that one compiled loop (numba) blends each vertex's bones and applies the
result to all bodies of the batch at once, in SIMD lanes along the batch.

This is the body model's inference path (:meth:`humotion.body.model.BodyModel.forward` takes it
on the CPU without gradients), with the forward kinematics and the rest meshes' heights (the
pose correctives' scale) compiled too, and the big matrix products of small batches reading
float16 copies of the weights (:func:`rows_product`); the torch path of
:mod:`humotion.body.skinning` stays the reference, used for gradients and on other devices, and
the tests hold the two equal.

Layouts: "vertex-major" meshes are (V, 3, B) (or their (3 V, B) rows x0, y0, z0, x1, ... by
bodies), the layout in which the matrix products of the shape, correctives and expression come
out with the batch last.
"""

from __future__ import annotations

import functools
from typing import Callable, NamedTuple

import numpy as np
import torch


class Kernels(NamedTuple):
    """The compiled loops below (numba functions of numpy arrays; each documents its arrays)."""

    pose_block: Callable
    pose_block_of_one: Callable
    forward_kinematics: Callable
    heights: Callable
    half_product: Callable


def compiled(function: Callable) -> Callable:
    """function compiled by numba (no Python objects, fast math, no bounds checks, the GIL
    released), its machine code cached on disk next to this module or in numba's user cache
    directory; where neither can be written (a read-only install without a home directory),
    compiled afresh in each process instead of failing."""
    from numba import njit

    options = dict(fastmath=True, boundscheck=False, nogil=True)
    try:
        return njit(cache=True, **options)(function)
    except RuntimeError:   # numba: "cannot cache function ...: no locator available for file ..."
        return njit(**options)(function)


@functools.cache
def _kernels() -> Kernels:
    """The kernels, compiled (or loaded from numba's cache) on first use."""
    from humotion.body.half_weights import half_product

    return Kernels(*(compiled(f) for f in (pose_block, pose_block_of_one, forward_kinematics, heights, half_product)))


def pose_block(surface, moves, move_rows, transforms, bones, weights, out):
    """surface (n, 3, B) f32 rest + correctives (m); moves (E, 3, B) f32 expression offsets (m)
    and move_rows (n,) i32, each vertex's row in moves or -1; transforms (J, 12 B) f32, per
    bone its A (3 x 3, row-major) then t, each of the 12 numbers for the B bodies in a row;
    bones (n, S) i32 and weights (n, S) f32 each vertex's skinning; out (n, 3, B) f32."""
    n, _, batch = surface.shape
    entries, support = transforms.shape[1], bones.shape[1]
    blended = np.empty(entries, np.float32)
    for v in range(n):
        blended[:] = 0.0
        for s in range(support):
            weight = weights[v, s]
            if weight == 0.0:   # (an early continue: an if-block around the loop ran 2.4x slower)
                continue
            bone = transforms[bones[v, s]]
            for i in range(entries):
                blended[i] += weight * bone[i]
        for c in range(3):
            rotation, translation = 3 * c * batch, (9 + c) * batch
            for b in range(batch):
                out[v, c, b] = (blended[rotation + b] * surface[v, 0, b]
                                + blended[rotation + batch + b] * surface[v, 1, b]
                                + blended[rotation + 2 * batch + b] * surface[v, 2, b] + blended[translation + b])
        row = move_rows[v]
        if row >= 0:   # the expression's offset, rotated: A (s + m) + t = (A s + t) + A m
            for c in range(3):
                rotation = 3 * c * batch
                for b in range(batch):
                    out[v, c, b] += (blended[rotation + b] * moves[row, 0, b]
                                     + blended[rotation + batch + b] * moves[row, 1, b]
                                     + blended[rotation + 2 * batch + b] * moves[row, 2, b])


def pose_block_of_one(surface, moves, move_rows, transforms, bones, weights, out):
    """pose_block for one body, its arrays without the batch axis: surface (n, 3), moves (E, 3),
    transforms (J, 12), out (n, 3) (loops of known length: 1.8x as fast as pose_block's at B = 1)."""
    blended = np.empty(12, np.float32)
    for v in range(surface.shape[0]):
        blended[:] = 0.0
        for s in range(bones.shape[1]):
            weight = weights[v, s]
            if weight == 0.0:
                continue
            bone = transforms[bones[v, s]]
            for i in range(12):
                blended[i] += weight * bone[i]
        x, y, z = surface[v, 0], surface[v, 1], surface[v, 2]
        row = move_rows[v]
        if row >= 0:
            x, y, z = x + moves[row, 0], y + moves[row, 1], z + moves[row, 2]
        for c in range(3):
            out[v, c] = blended[3 * c] * x + blended[3 * c + 1] * y + blended[3 * c + 2] * z + blended[9 + c]


def forward_kinematics(rotations, rest, translation, parents, A, t, joints):
    """rotations (B, J, 3, 3), rest joints (B or 1, J, 3) (m), translation (B, 3) (m), parents
    (J,) i32, each before its children (root: -1) -> A (B, J, 3, 3), t (B, J, 3), joints (B, J, 3)
    written (the convention of humotion.body.skinning.skinning_transforms)."""
    for b in range(rotations.shape[0]):
        r = b if rest.shape[0] > 1 else 0
        for j in range(rotations.shape[1]):
            p = parents[j]
            for c in range(3):
                if p < 0:
                    joints[b, j, c] = rest[r, j, c] + translation[b, c]
                    for d in range(3):
                        A[b, j, c, d] = rotations[b, j, c, d]
                else:   # p_j = p_parent + A_parent (rest_j - rest_parent); A_j = A_parent R_j
                    joints[b, j, c] = joints[b, p, c] + (A[b, p, c, 0] * (rest[r, j, 0] - rest[r, p, 0])
                                                         + A[b, p, c, 1] * (rest[r, j, 1] - rest[r, p, 1])
                                                         + A[b, p, c, 2] * (rest[r, j, 2] - rest[r, p, 2]))
                    for d in range(3):
                        A[b, j, c, d] = (A[b, p, c, 0] * rotations[b, j, 0, d] + A[b, p, c, 1] * rotations[b, j, 1, d]
                                         + A[b, p, c, 2] * rotations[b, j, 2, d])
            for c in range(3):   # t_j = p_j - A_j rest_j
                t[b, j, c] = joints[b, j, c] - (A[b, j, c, 0] * rest[r, j, 0] + A[b, j, c, 1] * rest[r, j, 1]
                                                + A[b, j, c, 2] * rest[r, j, 2])


def heights(rest, out):
    """rest (V, 3, B) vertex-major meshes -> out (B,) their vertical extents (max y - min y)."""
    if rest.shape[2] == 1:   # one body: in registers (2.2x as fast as the loop below)
        top = bottom = rest[0, 1, 0]
        for v in range(1, rest.shape[0]):
            top, bottom = max(top, rest[v, 1, 0]), min(bottom, rest[v, 1, 0])
        out[0] = top - bottom
        return
    top, bottom = rest[0, 1].copy(), rest[0, 1].copy()
    for v in range(1, rest.shape[0]):
        for b in range(rest.shape[2]):
            top[b] = max(top[b], rest[v, 1, b])
            bottom[b] = min(bottom[b], rest[v, 1, b])
    out[:] = top - bottom


def vertex_major_heights(rest_vertices: torch.Tensor) -> torch.Tensor:
    """:func:`humotion.body.model.mesh_height` of meshes (B, V, 3) that are a view of vertex-major
    (V, 3, B) ones (as the decoder gives them with vertex_major=True; others are copied so first):
    (B,) heights (m), without gradients (torch's reductions along the strided axis took 6-10x as
    long)."""
    rest = rest_vertices.permute(1, 2, 0)
    out = rest.new_empty(rest.shape[2])
    _kernels().heights(rest.contiguous().numpy(), out.numpy())
    return out


def bone_transforms(rest_joints: torch.Tensor, parents: torch.Tensor, rotations: torch.Tensor,
                    translation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`humotion.body.skinning.skinning_transforms` compiled, float32 on the CPU, without
    gradients: rest_joints (B or 1, J, 3) (m), parents (J,) int32 with every parent before its
    children (root: -1), rotations (B, J, 3, 3), translation (B, 3) (m) -> A (B, J, 3, 3),
    t (B, J, 3), posed joints (B, J, 3)."""
    A = rotations.new_empty(rotations.shape)
    t, joints = rotations.new_empty(rotations.shape[:-1]), rotations.new_empty(rotations.shape[:-1])
    _kernels().forward_kinematics(rotations.contiguous().numpy(), rest_joints.contiguous().numpy(),
                                  translation.contiguous().numpy(), parents.numpy(), A.numpy(), t.numpy(), joints.numpy())
    return A, t, joints


HALF_PRODUCT_BATCH = 4
"""The largest batch :func:`rows_product` multiplies by the float16 copy (faster than torch's
float32 product up to here: see :mod:`humotion.body.half_weights`)."""


def rows_product(offset: torch.Tensor | None, weight: torch.Tensor, half: np.ndarray | None, factors: torch.Tensor,
                 out: torch.Tensor | None = None) -> torch.Tensor:
    """offset (R, 1 or B) (None: 0) + weight (R, K) @ factors.T -> (R, B), written into `out`
    (contiguous) if given: factors (B, K); half: the weight's float16 bits
    (:func:`humotion.body.half_weights.half_bits`) or None. Up to batch HALF_PRODUCT_BATCH with
    `half`, by the compiled float16 product (half the bytes read); otherwise by torch."""
    if half is None or len(factors) > HALF_PRODUCT_BATCH:
        if offset is None:
            return torch.mm(weight, factors.T, out=out)
        return torch.addmm(offset, weight, factors.T, out=out)
    out = weight.new_empty(len(weight), len(factors)) if out is None else out
    offset = weight.new_empty(0, 1) if offset is None else offset.contiguous()
    _kernels().half_product(half, factors.contiguous().numpy(), offset.numpy(), out.numpy())
    return out


def vertex_block_rows(batch: int) -> int:
    """Vertices per block of :func:`pose_vertex_major` for a batch of B bodies: about 32k numbers
    per coordinate of a block's scratch (512 vertices at B = 64, which stays in cache), at least
    512; the whole full-resolution mesh at B = 1 (one call to each step instead of seven: 0.2 ms
    of the 2.3 ms)."""
    return max(512, 32768 // max(batch, 1))


def pose_vertex_major(rest: torch.Tensor, corrective_rows: torch.Tensor | None, corrective_half: np.ndarray | None,
                      factors: torch.Tensor | None, moves: torch.Tensor | None, move_rows: torch.Tensor | None,
                      A: torch.Tensor, t: torch.Tensor, bones: torch.Tensor, weights: torch.Tensor, rows: int) -> torch.Tensor:
    """Posed meshes (V, 3, B) (m), vertex-major, float32 on the CPU, without gradients.

    rest (3 V, B or 1) vertex-major rest meshes (m); corrective_rows (3 V, H), the pose
    correctives' regressor weight, with its float16 bits corrective_half (or None: see
    :func:`rows_product`), and factors (B, H) of PoseCorrectives.factors, or all None;
    moves (E, 3, B or 1) expression offsets (m) and move_rows (V,) int32 each vertex's row in them
    (-1: none), or both None; A (B, J, 3, 3), t (B, J, 3) skinning transforms (x -> A x + t);
    bones (V, S) int32 and weights (V, S) each vertex's bones and weights; rows: vertices per
    block (:func:`vertex_block_rows`). Per block, the rest and the correctives are summed into a
    small scratch by one matrix product, which the kernel reads with the expression's offsets.
    """
    batch, num_joints = A.shape[:2]
    num_vertices = len(bones)
    kernels = _kernels()
    transforms = torch.cat([A.flatten(-2), t], -1).permute(1, 2, 0).reshape(num_joints, 12 * batch).contiguous()
    if moves is None:
        moves, move_rows = rest.new_zeros(0, 3, batch), torch.full((num_vertices,), -1, dtype=torch.int32)
    moves = moves.expand(-1, -1, batch).contiguous()
    out = rest.new_empty(num_vertices, 3, batch)
    scratch = rest.new_empty(3 * min(rows, num_vertices), batch)
    arrays = [x.numpy() for x in (moves, move_rows, transforms, bones, weights, out)]
    moves_np, move_rows_np, transforms_np, bones_np, weights_np, out_np = arrays
    for start in range(0, num_vertices, rows):
        block = slice(start, min(start + rows, num_vertices))
        coordinates = slice(3 * block.start, 3 * block.stop)
        surface = scratch[:coordinates.stop - coordinates.start]
        if factors is None:
            surface.copy_(rest[coordinates].expand(-1, batch))
        else:
            half = None if corrective_half is None else corrective_half[coordinates]
            rows_product(rest[coordinates], corrective_rows[coordinates], half, factors, out=surface)
        surface_np = surface.view(-1, 3, batch).numpy()
        if batch == 1:
            kernels.pose_block_of_one(surface_np[..., 0], moves_np[..., 0], move_rows_np[block], transforms_np,
                                      bones_np[block], weights_np[block], out_np[block, :, 0])
        else:
            kernels.pose_block(surface_np, moves_np, move_rows_np[block], transforms_np, bones_np[block],
                               weights_np[block], out_np[block])
    return out

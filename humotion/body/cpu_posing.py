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

from typing import TYPE_CHECKING

import numpy as np
import torch

if TYPE_CHECKING:
    from humotion.body.model import BodyModel


def _kernels():
    """:mod:`humotion.body.cpu_kernels`, imported on first use (it imports numba)."""
    from humotion.body import cpu_kernels

    return cpu_kernels


def half_bits(weight: torch.Tensor) -> np.ndarray | None:
    """weight (R, K) float32 as the bits of float16 numbers, (R, K) uint16, for the compiled
    float16 loops; None where float16 does not hold every number exactly (such a matrix is
    multiplied in float32)."""
    half = weight.detach().half()
    if not torch.equal(half.float(), weight.detach()):
        return None
    return half.numpy().view(np.uint16)


def vertex_major_heights(rest_vertices: torch.Tensor) -> torch.Tensor:
    """:func:`humotion.body.anthropometry.mesh_height` of meshes (B, V, 3) that are a view of vertex-major
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
"""The largest batch whose products read the float16 copies (see :func:`uses_float16`)."""


def uses_float16(batch: int) -> bool:
    """Whether the products of `batch` bodies read float16 copies of the weights (:func:`half_bits`)
    in the compiled loop: up to HALF_PRODUCT_BATCH bodies (from 8 on torch's float32 product is
    faster), with torch on one thread, where numba compiles for a CPU that converts float16 in
    hardware (cpu_kernels.FLOAT16_IN_HARDWARE). The loop runs on one thread; torch's product
    runs on all of torch's threads and is as fast from two on (the body model card's Speed
    section; `bench/body_products.py`)."""
    return batch <= HALF_PRODUCT_BATCH and torch.get_num_threads() == 1 and _kernels().FLOAT16_IN_HARDWARE


def rows_product(offset: torch.Tensor | None, weight: torch.Tensor, half: np.ndarray | None, factors: torch.Tensor,
                 out: torch.Tensor | None = None) -> torch.Tensor:
    """offset (R, 1 or B) (None: 0) + weight (R, K) @ factors.T -> (R, B), written into `out`
    (contiguous) if given: factors (B, K); half: the weight's float16 bits (:func:`half_bits`),
    read by the compiled float16 loop (give them only where :func:`uses_float16`), or None:
    torch's float32 product."""
    if half is None:
        if offset is None:
            return torch.mm(weight, factors.T, out=out)
        return torch.addmm(offset, weight, factors.T, out=out)
    out = weight.new_empty(len(weight), len(factors)) if out is None else out
    offset = weight.new_empty(0, 1) if offset is None else offset.contiguous()
    _kernels().half_product(half, factors.contiguous().numpy(), offset.numpy(), out.numpy())
    return out


def pose_body(body: BodyModel, rest_vertices: torch.Tensor, factors: torch.Tensor | None, moves: torch.Tensor | None,
              A: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """The body model's posed meshes (B, V, 3) (m), a view of (V, 3, B), by :func:`pose_vertex_major`
    with the model's weights (their int32 and float16 forms kept in body.derived): rest_vertices
    (B or 1, V, 3) and moves (B or 1, expression_vertices, 3) or None, views of vertex-major
    tensors (as the decoders give them with vertex_major=True), factors (B, corrective_hidden) or
    None, A (B, J, 3, 3), t (B, J, 3)."""
    V = body.num_vertices
    skin = body.skin
    bones, weights = body.derived.get("vertex_skinning", [skin.logits, skin.index, skin.valid],
                                      lambda: (skin.index.to(torch.int32), skin.sparse().contiguous()))
    move_rows = None
    if moves is not None:
        index = body.expression_index
        move_rows = body.derived.get("move_rows", [index], lambda: torch.full((V,), -1, dtype=torch.int32).index_copy(
            0, index, torch.arange(len(index), dtype=torch.int32)))
        moves = moves.permute(1, 2, 0)
    rest = rest_vertices.permute(1, 2, 0).reshape(3 * V, -1)
    corrective_rows = corrective_half = None
    if factors is not None:
        corrective_rows = body.correctives.regressor.weight
        corrective_half = body.derived.float16_bits("correctives", corrective_rows, len(factors))
    return pose_vertex_major(rest, corrective_rows, corrective_half, factors, moves, move_rows, A, t, bones,
                             weights).permute(2, 0, 1)


def vertex_block_rows(batch: int) -> int:
    """Vertices per block of :func:`pose_vertex_major` for a batch of B > 1 bodies: about 32k
    numbers per coordinate of a block's scratch (512 vertices at B = 64, which stays in cache), at
    least 512."""
    return max(512, 32768 // batch)


def pose_vertex_major(rest: torch.Tensor, corrective_rows: torch.Tensor | None, corrective_half: np.ndarray | None,
                      factors: torch.Tensor | None, moves: torch.Tensor | None, move_rows: torch.Tensor | None,
                      A: torch.Tensor, t: torch.Tensor, bones: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Posed meshes (V, 3, B) (m), vertex-major, float32 on the CPU, without gradients.

    rest (3 V, B or 1) vertex-major rest meshes (m); corrective_rows (3 V, H), the pose
    correctives' regressor weight, with its float16 bits corrective_half (or None: see
    :func:`rows_product`, :func:`uses_float16`), and factors (B, H) of PoseCorrectives.factors,
    or all None;
    moves (E, 3, B or 1) expression offsets (m) and move_rows (V,) int32 each vertex's row in them
    (-1: none), or both None; A (B, J, 3, 3), t (B, J, 3) skinning transforms (x -> A x + t);
    bones (V, S) int32 and weights (V, S) each vertex's bones and weights.

    One body is posed by one loop over the mesh, which adds the correctives from their float16
    rows itself (when given). A batch is posed block by block of vertices
    (:func:`vertex_block_rows`): the rest and the correctives are summed into a small scratch by
    one matrix product, which the batched loop reads with the expression's offsets.
    """
    batch, num_joints = A.shape[:2]
    num_vertices = len(bones)
    kernels = _kernels()
    transforms = torch.cat([A.flatten(-2), t], -1).permute(1, 2, 0).reshape(num_joints, 12 * batch).contiguous()
    if moves is None:
        moves, move_rows = rest.new_zeros(0, 3, batch), torch.full((num_vertices,), -1, dtype=torch.int32)
    moves = moves.expand(-1, -1, batch).contiguous()
    out = rest.new_empty(num_vertices, 3, batch)
    arrays = [x.numpy() for x in (moves, move_rows, transforms, bones, weights, out)]
    moves_np, move_rows_np, transforms_np, bones_np, weights_np, out_np = arrays
    if batch == 1:
        if factors is not None and corrective_half is None:   # added here, by torch
            rest, factors = torch.addmm(rest, corrective_rows, factors.T), None
        # no correctives: float32 rows, so that the loop compiled holds no float16 conversion
        correctives = corrective_half if factors is not None else np.zeros((0, 0), np.float32)
        factors_np = factors[0].contiguous().numpy() if factors is not None else np.zeros(0, np.float32)
        kernels.pose_one_body(rest.view(num_vertices, 3).numpy(), correctives, factors_np, moves_np[..., 0],
                              move_rows_np, transforms_np, bones_np, weights_np, out_np[..., 0])
        return out
    rows = vertex_block_rows(batch)
    scratch = rest.new_empty(3 * min(rows, num_vertices), batch)
    for start in range(0, num_vertices, rows):
        block = slice(start, min(start + rows, num_vertices))
        coordinates = slice(3 * block.start, 3 * block.stop)
        surface = scratch[:coordinates.stop - coordinates.start]
        if factors is None:
            surface.copy_(rest[coordinates].expand(-1, batch))
        else:
            half = None if corrective_half is None else corrective_half[coordinates]
            rows_product(rest[coordinates], corrective_rows[coordinates], half, factors, out=surface)
        kernels.pose_block(surface.view(-1, 3, batch).numpy(), moves_np, move_rows_np[block], transforms_np,
                           bones_np[block], weights_np[block], out_np[block])
    return out

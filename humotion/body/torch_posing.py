"""Posing bodies in torch, differentiably: the body model's forward pass where a gradient is
wanted or off the CPU (without either it takes the compiled path of
:mod:`humotion.body.cpu_posing`, which the tests hold equal to this one).

The surface to pose, rest + pose correctives + expression, is formed block by block of vertices
as coordinate planes (B, 3, n), each block skinned (:func:`humotion.body.skinning.skin_in_blocks`)
just after it is formed, while it is in cache:

    vertices = pose_in_blocks(body, rest_vertices, factors, moves, A, t)    # (B, V, 3)
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Iterator

import torch

from humotion.body.skinning import block_rows, needs_gradient, skin_in_blocks

if TYPE_CHECKING:
    from humotion.body.model import BodyModel


def planar(rows: torch.Tensor) -> torch.Tensor:
    """(3 V, ...) rows for vertex coordinates in the usual order (x0, y0, z0, x1, ...) -> the same
    rows as coordinate planes (x0, x1, ..., y0, y1, ..., z0, ...), the order the forward pass
    computes meshes in: a (B, 3 V) result of them is (B, 3, V), whose transposed view is (B, V, 3)
    without a copy, and skinning reads each coordinate along the vertices."""
    return rows.unflatten(0, (-1, 3)).transpose(0, 1).flatten(0, 1)


def pose_in_blocks(body: BodyModel, rest_vertices: torch.Tensor, factors: torch.Tensor | None,
                   moves: torch.Tensor | None, A: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Posed meshes (B, V, 3) (m), a view of coordinate planes (B, 3, V): rest_vertices (B, V, 3)
    (m); factors (B, corrective_hidden) of PoseCorrectives.factors, or None for no correctives;
    moves (B or 1, expression_vertices, 3) of BodyModel.expression_moves (m), or None for the
    neutral face; A (B, J, 3, 3), t (B, J, 3) skinning transforms (x -> A x + t)."""
    batch, V = len(A), body.num_vertices
    moves = None if moves is None else moves.expand(batch, -1, -1).flatten(1)
    rows = block_rows(batch, V, A.device)
    weights = expression = None
    if factors is not None:
        weight = body.correctives.regressor.weight
        weights = body.derived.get(f"corrective_blocks/{rows}", [weight], lambda: corrective_blocks(weight, rows))
    if moves is not None:
        index = body.expression_index
        expression = body.derived.get(f"expression_blocks/{rows}", [index], lambda: expression_blocks(index, V, rows))
    surfaces = surface_blocks(rest_vertices.transpose(1, 2), rows, factors, weights, moves, expression)
    gradient = needs_gradient(rest_vertices, A, t, body.skin.logits, *(x for x in (factors, moves) if x is not None))
    vertices = skin_in_blocks(surfaces, body.skin_blocks().blocks(rows), A, t, V, gradient)
    return vertices.transpose(1, 2)


def surface_blocks(rest_planes: torch.Tensor, rows: int, factors: torch.Tensor | None,
                   weights: list[torch.Tensor] | None, moves: torch.Tensor | None,
                   expression: list[tuple[torch.Tensor, torch.Tensor]] | None) -> Iterator[torch.Tensor]:
    """Yield the mesh to pose, rest + pose correctives + expression, as coordinate planes
    (B, 3, n) block by block of `rows` vertices (the last block shorter), each computed just
    before it is skinned: rest_planes (B or 1, 3, V) (m); factors (B, corrective_hidden) of
    PoseCorrectives.factors and the correctives' weights cut by :func:`corrective_blocks`, or
    both None for no correctives; moves (B, 3 x expression_vertices) of
    BodyModel.expression_moves(...).flatten(1) and where they go (:func:`expression_blocks`), or
    both None for the neutral face. A block with neither is a view of rest_planes; sums are never
    written into it."""
    batch = len(factors) if factors is not None else len(moves) if moves is not None else len(rest_planes)
    for b, planes in enumerate(rest_planes.split(rows, dim=-1)):
        surface = planes
        if factors is not None:
            surface = torch.mm(factors, weights[b].T).view(batch, 3, -1).add_(planes)
        if expression is not None and len(expression[b][0]):
            coordinates, columns = expression[b]
            flat = surface.expand(batch, -1, -1).reshape(batch, -1)
            moved = moves.index_select(1, columns)
            if factors is None:   # flat may still be a view of rest_planes: add out of place
                flat = flat.index_add(1, coordinates, moved)
            else:                 # the correctives' fresh sum
                flat.index_add_(1, coordinates, moved)
            surface = flat.view(batch, 3, -1)
        yield surface


def corrective_blocks(weight: torch.Tensor, rows: int) -> list[torch.Tensor]:
    """The pose correctives' regressor weight (3 V, hidden) cut for :func:`surface_blocks`: per
    block of `rows` vertices, (3 n, hidden) rows giving the block's coordinate planes (x of its n
    vertices, then y, then z)."""
    planes = planar(weight).unflatten(0, (3, -1))   # (3, V, hidden)
    return [block.reshape(-1, weight.shape[1]) for block in planes.split(rows, dim=1)]


def expression_blocks(index: torch.Tensor, num_vertices: int, rows: int) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Where the expressions' moves go, per block of `rows` vertices (:func:`surface_blocks`):
    (coordinates (m,) in the block's planes flattened (3 n,), columns (m,) of
    expression_moves(...).flatten(1) that add to them); index (expression_vertices,) the vertices
    the expressions move, of a mesh of num_vertices."""
    vertex = index.repeat_interleave(3)                                  # (3 E,) in moves' column order
    plane = torch.arange(3, device=index.device).repeat(len(index))
    blocks = []
    for start in range(0, num_vertices, rows):
        size = min(rows, num_vertices - start)
        columns = ((vertex >= start) & (vertex < start + size)).nonzero()[:, 0]
        blocks.append((plane[columns] * size + vertex[columns] - start, columns))
    return blocks

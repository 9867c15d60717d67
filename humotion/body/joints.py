"""The joint-centre predictor of the body model: joints regressed locally from the rest shape.

Each joint j reads a fixed support of at most `size` rest-mesh vertices spread (farthest-point
sampling) over the vertices it skins (weight to j or its parent above a threshold):

    centre_j     = sum_s a_js v_s                      a_j = softmax over the support (convex)
    correction_j = sum_s u_js (v_s - centre_j)         u_j sums to zero (so does not see translation)
    joint_j      = centre_j + bound * tanh(|correction_j| / bound) * correction_j / |correction_j|

The convex centre keeps the joint inside the hull of its own vertices; the correction, an affine
local regression on top, is what reaches joints a convex combination cannot (Anny's spine joints
sit inside the torso, off every local surface hull) and its size is softly bounded by `bound`
metres so centres stay inside the body. Both parts are translation-equivariant and sparse by
construction (size of V vertices); :meth:`JointRegressor.l1` (the L1 norm of u) keeps the
correction sparse and small, and :func:`bone_direction_loss` keeps bone directions near the
template's. :meth:`JointRegressor.fit` starts the weights from a ridge regression of true joints.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn


def joint_support(template_vertices: np.ndarray, template_joints: np.ndarray, weights: np.ndarray, parents,
                  size: int, threshold: float = 0.02) -> np.ndarray:
    """(J, size) vertex indices (-1 pads): per joint, `size` vertices spread by farthest-point
    sampling (from the one nearest the joint) over those whose skinning weight to the joint or
    its parent is above threshold (all vertices when there are none)."""
    out = np.full((len(template_joints), size), -1, dtype=np.int64)
    for j, p in enumerate(int(p) for p in parents):
        share = weights[:, j] + (weights[:, p] if p >= 0 else 0.0)
        candidates = np.flatnonzero(share > threshold)
        if len(candidates) == 0:
            candidates = np.arange(len(template_vertices))
        points = template_vertices[candidates]
        chosen = farthest_points(points, size, start=int(np.linalg.norm(points - template_joints[j], axis=-1).argmin()))
        out[j, :len(chosen)] = candidates[chosen]
    return out


def farthest_points(points: np.ndarray, count: int, start: int = 0) -> np.ndarray:
    """Indices of min(count, N) points spread over points (N, 3) by farthest-point sampling from
    point `start`, in the order chosen."""
    chosen = [start]
    distance = np.linalg.norm(points - points[start], axis=-1)
    while len(chosen) < min(count, len(points)):
        chosen.append(int(distance.argmax()))
        distance = np.minimum(distance, np.linalg.norm(points - points[chosen[-1]], axis=-1))
    return np.array(chosen)


class JointRegressor(nn.Module):
    """Rest vertices (B, V, 3) -> joint centres (B, J, 3); see the module docstring."""

    def __init__(self, num_vertices: int, num_joints: int, size: int, bound: float):
        super().__init__()
        self.num_vertices, self.bound = num_vertices, bound
        self.register_buffer("index", torch.zeros(num_joints, size, dtype=torch.long))
        self.register_buffer("valid", torch.zeros(num_joints, size, dtype=torch.bool))
        self.logits = nn.Parameter(torch.zeros(num_joints, size))
        self.correction = nn.Parameter(torch.zeros(num_joints, size))

    @torch.no_grad()
    def init_support(self, support: np.ndarray) -> None:
        """Supports (J, size) from :func:`joint_support`; uniform centres, no correction."""
        valid = support >= 0
        self.index.copy_(torch.as_tensor(np.where(valid, support, 0)))
        self.valid.copy_(torch.as_tensor(valid))
        self.logits.zero_()
        self.correction.zero_()

    def centre_weights(self) -> torch.Tensor:
        """(J, size) convex weights a of the centres."""
        return torch.softmax(self.logits.masked_fill(~self.valid, -torch.inf), dim=-1)

    unit = 0.01
    """Scale of the correction parameters: u = unit * parameter, so an optimizer step of a given
    size moves the joints ~100 times less than it would move u directly (u multiplies lever arms
    of tens of centimetres)."""

    def correction_weights(self) -> torch.Tensor:
        """(J, size) weights u of the corrections (zero sum per joint, zero on padding)."""
        u = self.unit * self.correction * self.valid
        return (u - u.sum(-1, keepdim=True) / self.valid.sum(-1, keepdim=True)) * self.valid

    def forward(self, vertices: torch.Tensor) -> torch.Tensor:
        """(B, V, 3) -> (B, J, 3). The supports' coordinates are gathered once as planes
        (B, 3, J, size) (read without a copy when vertices are a view of planes (B, 3, V)) and
        weighted along the support (the correction sum_s u_s (v_s - centre) is sum_s u_s v_s,
        u summing to zero)."""
        gathered = vertices.transpose(1, 2).index_select(2, self.index.flatten()).unflatten(2, self.index.shape)
        centre = (gathered * self.centre_weights()).sum(-1).transpose(1, 2)          # (B, J, 3)
        correction = (gathered * self.correction_weights()).sum(-1).transpose(1, 2)
        return self.bounded(centre, correction)

    def linear_sums(self, rows: torch.Tensor) -> torch.Tensor:
        """Per-vertex rows (V, 3, n) -> (2, J, 3, n): their centre and correction sums, the
        linear part of forward. For meshes that are linear in some features (rest = rows @ f),
        forward(rest) is bounded(*(linear_sums(rows) @ f)) without forming the meshes."""
        weights = torch.stack([self.centre_weights(), self.correction_weights()])   # (2, J, size)
        return torch.einsum("kjs,jscn->kjcn", weights, rows[self.index])

    def bounded(self, centre: torch.Tensor, correction: torch.Tensor) -> torch.Tensor:
        """Joint centres (..., J, 3) from the support centres and the corrections (..., J, 3),
        each correction softly bounded to `bound` metres."""
        size = correction.norm(dim=-1, keepdim=True).clamp_min(1e-9)
        return centre + self.bound * torch.tanh(size / self.bound) * correction / size

    def dense(self) -> torch.Tensor:
        """(J, V) the linear regressor matrix the joints follow while the corrections stay well
        inside their bound (mostly zeros), for inspection and export."""
        w = self.centre_weights() + self.correction_weights()
        return torch.zeros(w.shape[0], self.num_vertices, dtype=w.dtype, device=w.device).scatter_add(1, self.index, w)

    def l1(self) -> torch.Tensor:
        """Mean over joints of the L1 norm of the correction weights: a scalar tensor."""
        return self.correction_weights().abs().sum(-1).mean()

    def fit(self, rest: torch.Tensor, joints: torch.Tensor, ridge: float = 1e-6, steps: int = 200) -> float:
        """Start the weights from true joints (N, J, 3) of rest meshes (N, V, 3): the convex
        centres fitted first (Adam on the logits), then per joint the ridge-regularised zero-sum
        correction weights that best explain the rest (closed form, as if unbounded). Returns
        the mean error in mm."""
        rest, joints = rest.to(self.logits.dtype), joints.to(self.logits.dtype)
        with torch.no_grad():
            self.logits.zero_()
            self.correction.zero_()
        optimizer = torch.optim.Adam([self.logits], lr=0.05)
        for _ in range(steps):
            loss = (self(rest) - joints).norm(dim=-1).mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        with torch.no_grad():
            a = self.centre_weights().double()
            correction = torch.zeros_like(self.correction, dtype=torch.float64)
            for j in range(len(self.index)):
                keep = self.valid[j]
                X = rest[:, self.index[j][keep]].double()  # (N, S, 3)
                D = X - (a[j][keep][:, None] * X).sum(1, keepdim=True)
                # joint - centre = sum_s u_s (v_s - centre) with sum u = 0: eliminate u_0
                A = (D[:, 1:] - D[:, :1]).permute(0, 2, 1).reshape(-1, int(keep.sum()) - 1)
                b = (joints[:, j].double() - (a[j][keep][:, None] * X).sum(1)).reshape(-1)
                gram = A.T @ A + ridge * len(A) * torch.eye(A.shape[1], dtype=A.dtype)
                u = torch.linalg.solve(gram, A.T @ b)
                correction[j, :int(keep.sum())] = torch.cat([-u.sum()[None], u])
            self.correction.copy_((correction / self.unit).to(self.correction.dtype))
            return float(((self(rest) - joints).norm(dim=-1) * 1000).mean())


def bone_direction_loss(joints: torch.Tensor, template_joints: torch.Tensor, parents) -> torch.Tensor:
    """Mean 1 - cos between predicted bone vectors (joint - parent) and the template's:
    joints (B, J, 3), template_joints (J, 3)."""
    children = [j for j, p in enumerate(parents) if p >= 0]
    index = [int(parents[j]) for j in children]
    bones = joints[:, children] - joints[:, index]
    reference = template_joints[children] - template_joints[index]
    keep = reference.norm(dim=-1) > 1e-4
    cos = torch.nn.functional.cosine_similarity(bones[:, keep], reference[keep].expand_as(bones[:, keep]), dim=-1)
    return (1.0 - cos).mean()

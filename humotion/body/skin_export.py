"""Skinning weights for 4 joints per vertex, fitted to the body model's own skinning, for glTF
files (JOINTS_0 / WEIGHTS_0, the 4 joints per vertex every engine reads).

The model skins a vertex with up to 12 bones; keeping the heaviest 4, renormalised, moves the
shoulders, clavicles, neck and wrists by up to 2-3 cm. Instead (:func:`four_joint_weights`):

1. Merge: a joint the model's limits freeze (twist bones, metacarpals, in-between spine and neck
   bones: they never move relative to their parent in the data) moves rigidly with its parent in
   every pose the model is posed with, so its weight goes to its nearest moving ancestor. Exact.
2. Fit: among each vertex's subsets of at most 4 of its `candidates` heaviest (merged) joints,
   the non-negative weights summing to 1 whose linear blend skinning is nearest the model's own
   in mean square over random poses within the joint limits, plus a small ridge towards the
   model's weights (which settles the choice where poses cannot, as for a vertex at a joint
   centre). Each subset's equality-constrained least squares is solved in closed form; the best
   subset whose solution is non-negative is the exact optimum.

On held-out CMU motion (test subjects' frames) the result is within 7-9 mm of the model at worst
(a few clavicle and neck vertices that five independently moving bones skin) and about 1 mm at
the 99th percentile, against 27 mm and 4.5-7 mm for the heaviest 4; the random poses need no data and
do about as well there as CMU training frames. The pose correctives (rest-pose offsets of a few
millimetres, added before skinning) are left out of the fit; the file carries them as morph
targets either way.
"""

from __future__ import annotations

import itertools

import torch

from humotion import rotations as rot
from humotion.body.limits import JointLimits
from humotion.body.skinning import skinning_transforms

POSES = 512
"""Random poses the fit averages over."""

RIDGE = 1e-6
"""m^2: weight of the squared distance of the fitted weights from the model's (mean squared
vertex error of the poses is in m^2: a weight change of 0.1 costs as much as 0.1 mm)."""


def moving_ancestors(parents, frozen: torch.Tensor) -> torch.Tensor:
    """(J,) each joint's nearest ancestor (itself included) that frozen (J,) bool leaves free."""
    out = []
    for j in range(len(parents)):
        while frozen[j] and parents[j] >= 0:
            j = parents[j]
        out.append(j)
    return torch.tensor(out)


def limit_poses(limits: JointLimits, count: int, seed: int = 0) -> torch.Tensor:
    """(count, J, 3, 3) float64 rotations, uniform within the limits' boxes of rotation vectors."""
    generator = torch.Generator().manual_seed(seed)
    unit = 2 * torch.rand(count, *limits.centre.shape, generator=generator, dtype=torch.float64) - 1
    return rot.convert(limits.centre.double() + limits.half_range.double() * unit, "rotvec", "matrix")


def pose_moments(rest_joints: torch.Tensor, parents, rotations: torch.Tensor) -> torch.Tensor:
    """(J, J, 4, 4) mean over poses of B_j^T B_k, where B_j = [A_j | t_j] (3, 4) is bone j's
    skinning transform in a pose: then mean_p (B_pj x) . (B_pk x) = x^T M_jk x for homogeneous
    rest positions x = (x, y, z, 1), m. rest_joints (J, 3) m; rotations (P, J, 3, 3)."""
    rotations = rotations.double()
    A, t, _ = skinning_transforms(rest_joints.double(), parents, rotations,
                                  torch.zeros(len(rotations), 3, dtype=torch.float64))
    B = torch.cat([A, t[..., None]], -1)
    return torch.einsum("pjab,pkac->jkbc", B, B) / len(B)


def fit_influences(weights: torch.Tensor, rest_vertices: torch.Tensor, moments: torch.Tensor, count: int = 4,
                   candidates: int = 6, ridge: float = RIDGE, chunk: int = 2048) -> torch.Tensor:
    """(V, J) weights with at most `count` joints per vertex, non-negative, rows summing to 1,
    whose skinning is nearest that of weights (V, J) (rows summing to 1) over the poses of
    moments (J, J, 4, 4) (:func:`pose_moments`), for rest_vertices (V, 3) m; chosen among the
    vertex's `candidates` heaviest joints (more than 5 changed nothing on held-out motion; see
    the module docstring). chunk: vertices at a time."""
    support = int((weights > 0).sum(1).max())
    candidates = min(candidates, support)
    subsets = [torch.tensor(list(itertools.combinations(range(candidates), size)))
               for size in range(1, min(count, candidates) + 1)]
    out = torch.zeros(weights.shape, dtype=torch.float64)
    for start in range(0, len(weights), chunk):
        w, joints = weights[start:start + chunk].double().topk(support, 1)
        x = torch.cat([rest_vertices[start:start + chunk].double(), torch.ones(len(w), 1, dtype=torch.float64)], 1)
        gram = torch.einsum("vb,vjkbc,vc->vjk", x, moments[joints[:, :, None], joints[:, None, :]], x)
        # mean_p (p_j - m) . (p_k - m), p_j: the vertex moved by bone j, m = sum_j w_j p_j the model's vertex
        gw = (gram @ w[..., None])[..., 0]
        spread = gram - gw[:, :, None] - gw[:, None, :] + (w * gw).sum(1)[:, None, None]
        best = torch.full((len(w),), torch.inf, dtype=torch.float64)
        fitted = torch.zeros_like(w)
        for subset in subsets:
            size = subset.shape[1]
            kkt = torch.zeros(len(w), len(subset), size + 1, size + 1, dtype=torch.float64)
            kkt[..., :size, :size] = spread[:, subset[:, :, None], subset[:, None, :]] + ridge * torch.eye(size)
            kkt[..., :size, size] = kkt[..., size, :size] = 1.0
            target = torch.cat([ridge * w[:, subset], torch.ones(len(w), len(subset), 1, dtype=torch.float64)], -1)
            u = torch.linalg.solve(kkt, target)[..., :size]
            # mean squared distance from the model's vertex + ridge |u - w|^2, less a constant
            error = (u[..., None, :] @ kkt[..., :size, :size] @ u[..., None])[..., 0, 0] \
                - 2 * ridge * (u * w[:, subset]).sum(-1)
            error = error.masked_fill((u < 0).any(-1) | (w[:, subset] == 0).any(-1), torch.inf)
            error, pick = error.min(1)
            better = error < best
            best = torch.where(better, error, best)
            rows = torch.zeros_like(w).scatter(1, subset[pick], u[torch.arange(len(w)), pick])
            fitted[better] = rows[better]
        out[start:start + chunk].scatter_(1, joints, fitted)
    return out


def four_joint_weights(weights: torch.Tensor, rest_vertices: torch.Tensor, rest_joints: torch.Tensor, parents,
                       limits: JointLimits, poses: int = POSES, seed: int = 0) -> torch.Tensor:
    """(V, J) float64 skinning weights with at most 4 joints per vertex that skin the body like
    the model's weights (V, J): frozen joints merged into their moving ancestors, then the fit
    over `poses` random poses within the limits (fixed seed); see the module docstring.
    rest_vertices (V, 3), rest_joints (J, 3): the body at rest, m."""
    merged = torch.zeros(weights.shape, dtype=torch.float64).index_add_(
        1, moving_ancestors(parents, limits.frozen), weights.double())
    moments = pose_moments(rest_joints, parents, limit_poses(limits, poses, seed))
    return fit_influences(merged, rest_vertices, moments)

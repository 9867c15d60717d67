"""Training losses of SparsePoser (specs/sparse-tracking.md): L_data, L_smooth, L_SE3, L_forecast,
L_aux, summed with weights (all 1 in the reference). A term with weight 0 (or left out of the
weights) is not computed at all, so ablations cost nothing.

Rotations are compared as rotation MATRICES (the predicted 6D after Gram-Schmidt), not as raw
6D: the squared Frobenius distance ||R_hat - R||^2 = 4 (1 - cos angle) depends only on the
rotation error, whereas raw 6D could be wrong in scale without being wrong in rotation. A joint
transform's squared error is ||R_hat - R||_F^2 + ||p_hat - p||^2 (the homogeneous 4x4 matrices'
difference), positions in metres. Every term is a mean over batch, frames and joints (sums over
a joint's matrix entries / xyz), so its size does not depend on the window length.

The homogeneous difference mixes units: in metres a joint 15 cm off costs 0.02, a bone 20 degrees
off 0.24, so the positions weigh about 5 % of L_SE3 and L_aux. position_weight (default 1, the
plain matrix difference in metres) multiplies the position part of those two terms; 10 is the
same difference with positions in units of 1 / sqrt(10) m = 32 cm (model card: tried for the
lower body's error).

=========  ========================================================================================
term       definition (B windows, T frames, 22 joints)
=========  ========================================================================================
data       mean ||R_hat - R||^2 over local joint rotations (root: global) + mean ||g_hat - g||^2 over
           root positions
smooth     mean |dR_hat - dR|_1 + mean |dg_hat - dg|_1, d = frame-to-frame change (t >= 1)
se3        mean joint transform error in world space, after forward kinematics of the prediction on
           the window's own skeleton offsets
forecast   mean ||x_hat - x||^2 of each hand's forecast 9-D pose (6D + world position) (t >= 1: the
           first frame has no history to forecast from)
aux        mean joint transform error of g_aux's body-coordinate transforms (relative to the root,
           in the root's frame)
=========  ========================================================================================
"""

from __future__ import annotations

import torch

from humotion import rotations as rot
from humotion.canonical import PARENTS
from humotion.skeleton import forward_kinematics
from humotion.sparse.model import SparseOutput, sixd_to_matrix

TERMS = ("data", "smooth", "se3", "forecast", "aux")
DEFAULT_WEIGHTS = {term: 1.0 for term in TERMS}


def loss_weights(ablate=(), **weights: float) -> dict[str, float]:
    """Weights for :func:`sparse_loss`: 1 for every term, 0 for the ablated ones, overrides by name.
    L_data cannot be ablated (the spec: every term but L_data is optional)."""
    unknown = (set(ablate) | set(weights)) - set(TERMS)
    if unknown:
        raise ValueError(f"unknown loss terms {sorted(unknown)}; terms: {', '.join(TERMS)}")
    if "data" in ablate:
        raise ValueError("L_data cannot be ablated; set its weight instead")
    out = dict(DEFAULT_WEIGHTS)
    out.update({term: 0.0 for term in ablate})
    out.update(weights)
    return out


def targets(local_rotations: torch.Tensor, root_positions: torch.Tensor, offsets: torch.Tensor,
            hands: torch.Tensor | None = None) -> dict:
    """Ground truth for the losses from a batch of canonical-body windows.

    local_rotations: (B, T, 22, 3, 3) matrices or (B, T, 22, 4) wxyz quaternions (root global);
    root_positions: (B, T, 3) metres; offsets: (B, 22, 3) each window's skeleton offsets, metres;
    hands: (B, T, 2, 9) true world 6D + position of the left and right hand signals (needed by
    the forecast term), i.e. signals["left"] / ["right"] before any hiding.
    Returns a dict: rotations, root_positions, offsets, hands, world_rotations (B, T, 22, 3, 3),
    world_positions (B, T, 22, 3), body_rotations, body_positions (relative to the root).
    """
    if local_rotations.shape[-1] == 4:
        local_rotations = rot.quat_to_matrix(local_rotations)
    world_r, world_p = forward_kinematics(local_rotations, root_positions, offsets[:, None], PARENTS)
    root_t = world_r[..., :1, :, :].transpose(-1, -2)
    return {
        "rotations": local_rotations, "root_positions": root_positions, "offsets": offsets, "hands": hands,
        "world_rotations": world_r, "world_positions": world_p,
        "body_rotations": root_t @ world_r,
        "body_positions": (root_t @ (world_p - world_p[..., :1, :])[..., None])[..., 0],
    }


def _transform_error(r_hat, p_hat, r, p, position_weight: float = 1.0) -> torch.Tensor:
    """Mean over everything of ||R_hat - R||_F^2 + w ||p_hat - p||^2, (..., J, 3, 3) / (..., J, 3)."""
    return ((r_hat - r) ** 2).sum((-1, -2)).mean() + position_weight * ((p_hat - p) ** 2).sum(-1).mean()


def data_loss(pred: SparseOutput, target: dict) -> torch.Tensor:
    """Squared error of the pose (rotation matrices (B, T, 22, 3, 3)) and of the root trajectory
    (B, T, 3), metres: a scalar tensor."""
    return (((pred.rotations - target["rotations"]) ** 2).sum((-1, -2)).mean()
            + ((pred.root_positions - target["root_positions"]) ** 2).sum(-1).mean())


def smooth_loss(pred: SparseOutput, target: dict) -> torch.Tensor:
    """L1 of the difference between predicted and true frame-to-frame changes of the pose
    (B, T, 22, 3, 3) and trajectory (B, T, 3): a scalar tensor."""
    rotations = (pred.rotations.diff(dim=1) - target["rotations"].diff(dim=1)).abs().sum((-1, -2)).mean()
    trajectory = (pred.root_positions.diff(dim=1) - target["root_positions"].diff(dim=1)).abs().sum(-1).mean()
    return rotations + trajectory


def predicted_world(pred: SparseOutput, target: dict) -> tuple[torch.Tensor, torch.Tensor]:
    """World joint rotations (B, T, 22, 3, 3) and positions (B, T, 22, 3) of the prediction,
    by forward kinematics on the target windows' skeleton offsets."""
    return forward_kinematics(pred.rotations, pred.root_positions, target["offsets"][:, None], PARENTS)


def se3_loss(pred: SparseOutput, target: dict, position_weight: float = 1.0) -> torch.Tensor:
    """Squared error of every joint's world transform after forward kinematics (positions times
    position_weight, module docstring), of world rotations (B, T, 22, 3, 3) and positions
    (B, T, 22, 3): a scalar tensor."""
    r, p = predicted_world(pred, target)
    return _transform_error(r, p, target["world_rotations"], target["world_positions"], position_weight)


def forecast_loss(pred: SparseOutput, target: dict) -> torch.Tensor:
    """Squared error of the forecast hand 9-D poses (B, T, 2, 9) against the truth, frames 1..T-1:
    a scalar tensor."""
    if pred.forecast is None:
        raise ValueError("forecast loss needs the model's forecasts (a fixed mask token has none: set its weight to 0)")
    if target.get("hands") is None:
        raise ValueError("forecast loss needs target['hands'] (targets(..., hands=...))")
    return ((pred.forecast[:, 1:] - target["hands"][:, 1:]) ** 2).sum(-1).mean()


def aux_loss(pred: SparseOutput, target: dict, position_weight: float = 1.0) -> torch.Tensor:
    """Squared error of g_aux's body-coordinate joint transforms (B, T, 22, 9) (positions times
    position_weight): a scalar tensor."""
    aux = pred.aux
    if aux is None:
        raise ValueError("aux loss needs the model's aux outputs (call the model with aux=True)")
    return _transform_error(sixd_to_matrix(aux[..., :6]), aux[..., 6:], target["body_rotations"], target["body_positions"],
                            position_weight)


LOSSES = {"data": data_loss, "smooth": smooth_loss, "se3": se3_loss, "forecast": forecast_loss, "aux": aux_loss}
TRANSFORM_TERMS = ("se3", "aux")
"""The terms that compare joint transforms (rotation and position), whose position part position_weight scales."""


def sparse_loss(pred: SparseOutput, target: dict, weights: dict[str, float] | None = None,
                position_weight: float = 1.0) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """(weighted sum, {term: unweighted value}) over the terms with a non-zero weight, scalar tensors.

    pred: SparsePoser's outputs (rotations, root_positions, forecast, aux); target: :func:`targets`.
    weights: term -> weight (default all 1); missing or 0 terms are skipped (not computed).
    position_weight: the weight of positions (metres squared) in the se3 and aux transform errors.
    """
    weights = DEFAULT_WEIGHTS if weights is None else weights
    unknown = set(weights) - set(TERMS)
    if unknown:
        raise ValueError(f"unknown loss terms {sorted(unknown)}; terms: {', '.join(TERMS)}")
    terms = {name: LOSSES[name](pred, target, *([position_weight] if name in TRANSFORM_TERMS else []))
             for name in TERMS if weights.get(name, 0.0)}
    total = sum(weights[name] * value for name, value in terms.items())
    if not terms:
        raise ValueError("every loss weight is 0: nothing to train")
    return total, terms

"""Optional refinement after the network: fit the upper body to the observed head and hands.

Minimises E = E_data + E_reg over the upper-body joints' rotations and the root trajectory,
leaving the predicted lower body untouched (the observations say nothing about the legs):

- E_data: over the observed points (head at the eyes always; a hand when visible), the squared
  distance for controllers (MC), or the general robust loss of Barron (2019) for hand tracking
  (HT), so a hand that re-enters the view far from where the network put it does not yank the
  arm:  rho(r; a, b, c) = b * |a - 2| / a * (((r / c)^2 / |a - 2| + 1)^(a / 2) - 1), r in metres.
- E_reg: squared change of the rotations (radians) and root positions (metres) from the
  network's prediction, plus the squared acceleration of the upper-body joints (metres per
  (1/30 s)^2), so the fit stays close to the prediction and moves smoothly: with the robust data
  term, a hand re-entering the view is reached over several frames instead of in one jump.

Solved with L-BFGS (history 10, learning rate 1, strong Wolfe line search), as in the spec.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from humotion import rotations as rot
from humotion.canonical import JOINTS
from humotion.motion import Motion
from humotion.optimize import minimise_lbfgs
from humotion.skeleton import forward_kinematics

UPPER_JOINTS = ("spine1", "spine2", "spine3", "neck", "head", "left_collar", "right_collar", "left_shoulder",
                "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist")


@dataclass
class RefineConfig:
    """robust: use the robust penalty (HT) instead of plain squared distance (MC).
    alpha, scale_m, weight: the robust loss's shape a, scale c (metres) and weight b; the default
        b = 2 c^2 makes it equal the squared distance for small residuals.
    pose_weight, root_weight, smooth_weight: E_reg weights (per radian^2, per m^2, per (m / (1/30 s)^2)^2).
    rotation_weight: weight of the observed orientation residual (6D difference) against position.
    """

    robust: bool = False
    alpha: float = 1.0
    scale_m: float = 0.05
    weight: float = 2 * 0.05**2
    pose_weight: float = 0.01
    root_weight: float = 0.1
    smooth_weight: float = 3.0
    rotation_weight: float = 0.1
    iterations: int = 30


def robust_loss(r: torch.Tensor, a: float, b: float, c: float) -> torch.Tensor:
    """Barron's general robust loss of residuals r (any shape); a must not be 0 or 2."""
    k = abs(a - 2)
    return b * k / a * (((r / c) ** 2 / k + 1) ** (a / 2) - 1)


def refine(motion: Motion, observed_rotations: torch.Tensor, observed_positions: torch.Tensor,
           visible: torch.Tensor, head_offset: torch.Tensor, config: RefineConfig = RefineConfig()) -> Motion:
    """The predicted motion with its upper body and root fitted to the observations.

    motion: predicted motion on the canonical skeleton, T frames.
    observed_rotations (T, 3, 3, 3) and observed_positions (T, 3, 3): world transforms of the
        head (at the eyes), left wrist and right wrist, in that order, metres.
    visible: (T, 2) bool, whether each hand was observed (the head always is).
    head_offset: (3,) eye position in the head joint's frame, metres.
    """
    skeleton = motion.skeleton
    if skeleton.names != JOINTS:
        raise ValueError("refine expects a motion on the canonical skeleton (humotion.canonical)")
    upper = [JOINTS.index(j) for j in UPPER_JOINTS]
    sensors = [JOINTS.index(j) for j in ("head", "left_wrist", "right_wrist")]
    offsets = skeleton.offsets
    start_root = motion.root_positions.clone()
    mask = torch.cat([torch.ones(len(visible), 1, dtype=torch.bool), torch.as_tensor(visible, dtype=torch.bool)], dim=1)
    observed_rotations = torch.nan_to_num(torch.as_tensor(observed_rotations, dtype=torch.float32))  # unseen hands
    observed_positions = torch.nan_to_num(torch.as_tensor(observed_positions, dtype=torch.float32))
    # Unknowns: a rotation vector per upper joint and frame applied after the prediction's own
    # rotation (zero = the prediction), and the root positions.
    delta = torch.zeros(len(motion), len(upper), 3, requires_grad=True)
    root = start_root.clone().requires_grad_(True)
    fixed = rot.quat_to_matrix(motion.rotations)
    sensor_offsets = torch.zeros(3, 3)
    sensor_offsets[0] = torch.as_tensor(head_offset, dtype=torch.float32)
    per_30hz = (motion.fps / 30.0) ** 2     # accelerations in metres per (1/30 s)^2, whatever the rate

    def energy() -> torch.Tensor:
        local = fixed.clone()
        local[:, upper] = fixed[:, upper] @ rot.convert(delta, "rotvec", "matrix")
        world_r, world_p = forward_kinematics(local, root, offsets, skeleton.parents)
        r_s, p_s = world_r[:, sensors], world_p[:, sensors]
        points = p_s + (r_s @ sensor_offsets[..., None])[..., 0]
        distance = (points - observed_positions).norm(dim=-1)
        turn = (rot.convert(r_s, "matrix", "sixd") - rot.convert(observed_rotations, "matrix", "sixd")).norm(dim=-1)
        if config.robust:
            data = robust_loss(distance, config.alpha, config.weight, config.scale_m)
        else:
            data = distance**2
        data = ((data + config.rotation_weight * turn**2) * mask).sum()
        reg = config.pose_weight * (delta**2).sum() + config.root_weight * ((root - start_root) ** 2).sum()
        if len(root) > 2:
            reg = reg + config.smooth_weight * ((world_p[:, upper].diff(n=2, dim=0) * per_30hz) ** 2).sum()
        return data + reg

    minimise_lbfgs([delta, root], energy, config.iterations)
    rotations = motion.rotations.clone()
    rotations[:, upper] = rot.quat_mul(motion.rotations[:, upper], rot.convert(delta.detach(), "rotvec", "quat"))
    return Motion(skeleton, rotations, root.detach(), motion.fps, name=motion.name)

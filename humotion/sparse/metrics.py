"""Accuracy metrics for full-body motion predicted from sparse observations.

All take predicted and true motion on the canonical body, as world joint positions
(..., T, 22, 3) in metres and/or local joint rotation matrices (..., T, 22, 3, 3), at fps.
The means run over every leading dimension, frame and joint.

=========  ==========  ======================================================================
metric     unit        definition
=========  ==========  ======================================================================
MPJRE      degrees     mean geodesic angle between predicted and true local joint rotations
MPJPE      cm          mean joint position error
MPJVE      cm/s        mean error of joint velocities (finite differences x fps)
Jitter     10^2 m/s^3  mean magnitude of the predicted joints' jerk (third differences x fps^3)
hand       cm          MPJPE of the two wrists
upper      cm          MPJPE of the joints above the pelvis (spine, neck, head, arms)
lower      cm          MPJPE of the pelvis and legs
unseen     cm          error of a wrist on the frames its hand is not seen (HT; where the mask
hand                   token stands in for it): :func:`unseen_hand_error`
target     cm          distance of a wrist from its tracked hand on the frames the hand is seen
                       (what a user sees: the avatar's hand against the controller):
                       :func:`target_error`
reach      cm          the same on the frames the hand is within the arm's length (upper arm plus
                       forearm) of the body's shoulder, where the arm alone can meet it;
                       beyond: the share (%) of seen wrist-frames outside it (:func:`reach_error`)
pen        % frames    share of frames with a foot more than 2 cm below the floor
                       (:func:`penetration`); depth: the deepest, cm below the floor
skate      cm/s        mean horizontal speed of the feet (balls) over the frames they are in
                       contact (:func:`skating`); contacts by humotion.sparse.solve.foot_contacts
=========  ==========  ======================================================================

Feet: a foot's sole is the lower of its ankle and ball, each less its standing height above the
toe tips (humotion.sparse.solve.sole_heights); the floor is a height per clip or per frame.
"""

from __future__ import annotations

import numpy as np
import torch

from humotion.canonical import JOINTS

LOWER_BODY = ("pelvis", "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle",
              "left_foot", "right_foot")
UPPER_BODY = tuple(j for j in JOINTS if j not in LOWER_BODY)
HANDS = ("left_wrist", "right_wrist")


def _index(names) -> list[int]:
    return [JOINTS.index(n) for n in names]


def mpjre(pred_rot: torch.Tensor, true_rot: torch.Tensor) -> float:
    """Mean geodesic angle (degrees) between (..., J, 3, 3) local rotation matrices."""
    relative = pred_rot.transpose(-1, -2) @ true_rot
    cos = ((relative.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1)
    return float(torch.rad2deg(torch.arccos(cos)).mean())


def mpjpe(pred_pos: torch.Tensor, true_pos: torch.Tensor, joints=None) -> float:
    """Mean joint position error (cm) over (..., J, 3) positions in metres, optionally on some joints."""
    if joints is not None:
        pred_pos, true_pos = pred_pos[..., _index(joints), :], true_pos[..., _index(joints), :]
    return float((pred_pos - true_pos).norm(dim=-1).mean() * 100)


def mpjve(pred_pos: torch.Tensor, true_pos: torch.Tensor, fps: float) -> float:
    """Mean joint velocity error (cm/s) over (..., T, J, 3) positions in metres."""
    pred_vel, true_vel = pred_pos.diff(dim=-3) * fps, true_pos.diff(dim=-3) * fps
    return float((pred_vel - true_vel).norm(dim=-1).mean() * 100)


def jitter(pos: torch.Tensor, fps: float) -> float:
    """Mean jerk magnitude (10^2 m/s^3) of (..., T, J, 3) positions in metres; needs T >= 4."""
    jerk = pos.diff(n=3, dim=-3) * fps**3
    return float(jerk.norm(dim=-1).mean() / 100)


def evaluate(pred_pos, true_pos, pred_rot, true_rot, fps: float) -> dict[str, float]:
    """Every metric of the module docstring, as a dict keyed by its name."""
    return {
        "MPJRE": mpjre(pred_rot, true_rot),
        "MPJPE": mpjpe(pred_pos, true_pos),
        "MPJVE": mpjve(pred_pos, true_pos, fps),
        "Jitter": jitter(pred_pos, fps),
        "hand": mpjpe(pred_pos, true_pos, HANDS),
        "upper": mpjpe(pred_pos, true_pos, UPPER_BODY),
        "lower": mpjpe(pred_pos, true_pos, LOWER_BODY),
    }


def unseen_hand_error(pred_pos: torch.Tensor, true_pos: torch.Tensor, visible: torch.Tensor) -> tuple[float, int]:
    """(mean error in cm, count) of the wrists over the frames their hand is unseen: positions
    (T, 22, 3) metres, visible (T, 2) left / right flags. The mean is NaN when no hand is ever
    unseen (count 0)."""
    errors = (pred_pos[:, _index(HANDS)] - true_pos[:, _index(HANDS)]).norm(dim=-1)     # (T, 2)
    hidden = ~visible.bool()
    count = int(hidden.sum())
    return (float(errors[hidden].mean() * 100) if count else float("nan")), count


def target_error(pred_pos: torch.Tensor, hand_positions: torch.Tensor, visible: torch.Tensor) -> tuple[float, int]:
    """(mean distance in cm, count) of the wrists from the tracked hands over the frames each hand
    is seen: pred_pos (T, 22, 3) metres, hand_positions (T, 2, 3) left / right wrists as
    tracked (any value where unseen), visible (T, 2). NaN when no hand is seen (count 0)."""
    seen = torch.as_tensor(visible).bool()
    hands = torch.nan_to_num(torch.as_tensor(hand_positions, dtype=pred_pos.dtype))
    errors = (pred_pos[:, _index(HANDS)] - hands).norm(dim=-1)
    count = int(seen.sum())
    return (float(errors[seen].mean() * 100) if count else float("nan")), count


def reach_error(pred_pos: torch.Tensor, hand_positions: torch.Tensor, visible: torch.Tensor,
                arm_lengths) -> tuple[float, int, float]:
    """(mean distance in cm of the wrists from the tracked hands over the seen frames where the
    hand is within arm_lengths of the predicted shoulder, that count, percent of seen
    wrist-frames beyond it): pred_pos (T, 22, 3) metres, hand_positions (T, 2, 3) left / right
    as tracked, visible (T, 2), arm_lengths (2,) metres (upper arm + forearm). NaN when no seen
    hand is in reach (percent NaN when none is seen)."""
    seen = torch.as_tensor(visible).bool()
    hands = torch.nan_to_num(torch.as_tensor(hand_positions, dtype=pred_pos.dtype))
    shoulders = pred_pos[:, _index(("left_shoulder", "right_shoulder"))]
    within = seen & ((hands - shoulders).norm(dim=-1) <= torch.as_tensor(arm_lengths, dtype=pred_pos.dtype) + 1e-4)
    errors = (pred_pos[:, _index(HANDS)] - hands).norm(dim=-1)
    count, total = int(within.sum()), int(seen.sum())
    beyond = 100 * (total - count) / total if total else float("nan")
    return (float(errors[within].mean() * 100) if count else float("nan")), count, beyond


def penetration(pred_pos: torch.Tensor, clearance, floor, depth: float = 0.02) -> tuple[float, float]:
    """(percent of frames where a foot's sole is more than depth metres below the floor, the
    deepest sole in cm below the floor (0 when none is below)): pred_pos (T, 22, 3) metres,
    clearance (2,) (solve.foot_clearance), floor metres (one or (T,))."""
    from humotion.sparse.solve import sole_heights

    soles = sole_heights(np.asarray(pred_pos, np.float64), np.asarray(clearance), floor)   # (T, 2)
    below = (soles < -depth).any(-1)
    return float(below.mean() * 100), float(max(0.0, -soles.min()) * 100)


def skating(pred_pos: torch.Tensor, contacts, fps: float) -> tuple[float, int]:
    """(mean horizontal speed in cm/s of the feet's balls over their contact frames, count of
    foot-frames in contact): pred_pos (T, 22, 3) metres, contacts (T, 2) bool (a frame's speed
    is its move from the frame before; the first frame is left out). NaN when no contact."""
    from humotion.sparse.solve import BALLS

    balls = np.asarray(pred_pos, np.float64)[:, BALLS][:, :, [0, 2]]
    speed = np.linalg.norm(np.diff(balls, axis=0), axis=-1) * fps * 100           # (T - 1, 2)
    planted = np.asarray(contacts, bool)[1:]
    count = int(planted.sum())
    return (float(speed[planted].mean()) if count else float("nan")), count

"""Headset input signals synthesised from canonical-body motion (see specs/sparse-tracking.md).

Three tracked devices, :data:`DEVICES` = ("head", "left", "right"):

- head: the headset, at the EYES (the point between the eyes, like OpenXR's VIEW space), not at
  the neck: the canonical head joint's world transform composed with a fixed point in the head
  frame, :func:`eye_offset`. The point is anthropometric, scaled with the body's standing height
  H: EYE_BELOW_TOP * H = 0.064 H below the head top (eye height is 0.936 H; Drillis & Contini as
  tabulated by Winter) and EYE_FORWARD * H = 0.05 H in front of it (8.5 cm at 1.70 m), measured
  along the head frame's up (+Y) and forward (+Z) axes. On the 1.70 m template that is 5.1 cm
  above and 8.5 cm in front of the head joint. The head-top end site anchors it because the head
  joint itself sits at different heights on different rigs. The headset's orientation is the head
  joint's (identity = looking along +Z, the body's rest facing).
- left / right: the wrist joints (canonical left_wrist / right_wrist), world rotation and position.
  Hand trackers report the wrist (OpenXR XR_HAND_JOINT_WRIST_EXT), and the wrist is a joint the
  body model predicts, so no offset is added. The orientation is the canonical wrist frame:
  identity = the T-pose hand (fingers pointing away from the body along +X for the left hand and
  -X for the right, palm down).

Positions are in WORLD space: metres, right-handed, Y up, +Z the body's rest facing, left = +X
(as the spec asks). :func:`recentre` moves them to a stream-relative ground origin.

Input components, :data:`COMPONENTS` = ("head", "left", "right", "left_in_head", "right_in_head"),
each 9 numbers per frame: the 6D rotation (first two matrix columns, (r00, r10, r20, r01, r11, r21),
:func:`humotion.rotations.convert` form 'sixd') then the position (3). Hands in the head's frame:
x_lh = x_h^-1 x_l, i.e. R_lh = R_h^T R_l and P_lh = R_h^T (P_l - P_h). Each component also has a
velocity "<name>_vel" (9): the 6D of R_{t-1}^T R_t and P_t - P_{t-1}. The first frame gets the
velocity of a device at rest, :data:`REST_VELOCITY` = (1, 0, 0, 0, 1, 0, 0, 0, 0) (the 6D of the
identity and no translation), as if the stream had been still before it; a constant motion has
that velocity on every frame. Everything is batched over leading dims and differentiable (except
visibility, a boolean).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from humotion import canonical
from humotion import rotations as rot
from humotion.motion import Motion
from humotion.skeleton import Skeleton

DEVICES = ("head", "left", "right")
COMPONENTS = ("head", "left", "right", "left_in_head", "right_in_head")
HAND_COMPONENTS = ("left", "right", "left_in_head", "right_in_head")
SCENARIOS = ("MC", "HT")
EYE_BELOW_TOP = 0.064
EYE_FORWARD = 0.05
REST_VELOCITY = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0)
HAND_OF = (0, 1, 0, 1)           # which hand (0 left, 1 right) each of HAND_COMPONENTS belongs to
_HEAD, _LEFT, _RIGHT = (canonical.JOINTS.index(n) for n in ("head", "left_wrist", "right_wrist"))


@dataclass(frozen=True)
class Frustum:
    """The headset's hand-tracking camera volume, attached to the eyes.

    It looks along the head's forward axis (+Z of the head frame) tilted down by tilt_down_deg
    (about the head's left-right axis). A point is inside when its depth d along that view axis
    is in [near_m, far_m] and its horizontal and vertical angles from the axis are within half of
    each field of view: |side| <= d tan(h/2), |up| <= d tan(v/2). Angles in degrees, fov < 180.
    """

    horizontal_fov_deg: float = 120.0
    vertical_fov_deg: float = 120.0
    near_m: float = 0.1
    far_m: float = 1.2
    tilt_down_deg: float = 20.0

    def __post_init__(self):
        for name in ("horizontal_fov_deg", "vertical_fov_deg"):
            if not 0 < getattr(self, name) < 180:
                raise ValueError(f"Frustum.{name} must be in (0, 180) degrees, got {getattr(self, name)}")
        if not 0 <= self.near_m < self.far_m:
            raise ValueError(f"Frustum needs 0 <= near_m < far_m, got near {self.near_m}, far {self.far_m}")


@dataclass(frozen=True)
class Dropout:
    """Random hand-tracking losses inside the view: spans start at rate_per_s (per hand) and last
    mean_duration_s on average (geometric in frames, at least one frame). Rough guesses."""

    rate_per_s: float = 0.2
    mean_duration_s: float = 0.3


def eye_offset(skeleton: Skeleton) -> torch.Tensor:
    """(3,) float32 position of the eyes in the head joint's frame, metres (module docstring).

    skeleton: the canonical body (it needs the 'head_top' end site on the head joint).
    """
    if "head_top" not in skeleton.end_site_names or skeleton.names[_HEAD:_HEAD + 1] != ("head",):
        raise ValueError("eye_offset needs the canonical body (a 'head' joint with a 'head_top' end site); "
                         "map the motion with humotion.canonical.to_canonical first")
    top = skeleton.end_site_offsets[skeleton.end_site_names.index("head_top")]
    height = skeleton.height()
    return top + torch.tensor([0.0, -EYE_BELOW_TOP * height, EYE_FORWARD * height])


def device_poses(world_rotations: torch.Tensor, world_positions: torch.Tensor, eye: torch.Tensor):
    """World poses of the three DEVICES from canonical-body forward kinematics.

    world_rotations: (..., T, 22, 3, 3); world_positions: (..., T, 22, 3) metres;
    eye: (3,) or (..., 3) eye offset in the head frame (:func:`eye_offset`), one per sequence.
    Returns (rotations (..., T, 3, 3, 3), positions (..., T, 3, 3)) in DEVICES order.
    """
    eye = torch.as_tensor(eye, dtype=world_positions.dtype, device=world_positions.device).unsqueeze(-2)
    head_r = world_rotations[..., _HEAD, :, :]
    eyes = world_positions[..., _HEAD, :] + (head_r @ eye[..., None])[..., 0]
    rotations = torch.stack([head_r, world_rotations[..., _LEFT, :, :], world_rotations[..., _RIGHT, :, :]], dim=-3)
    positions = torch.stack([eyes, world_positions[..., _LEFT, :], world_positions[..., _RIGHT, :]], dim=-2)
    return rotations, positions


def hand_visibility(head_rotation: torch.Tensor, head_position: torch.Tensor, hand_positions: torch.Tensor,
                    frustum: Frustum = Frustum()) -> torch.Tensor:
    """Whether each hand is inside the headset frustum.

    head_rotation: (..., 3, 3) world rotation of the head; head_position: (..., 3) the eyes;
    hand_positions: (..., K, 3) world positions (K = 2: left, right), metres.
    Returns (..., K) bool.
    """
    local = torch.einsum("...ji,...kj->...ki", head_rotation, hand_positions - head_position.unsqueeze(-2))
    tilt = math.radians(frustum.tilt_down_deg)
    x, y, z = local.unbind(-1)
    depth = z * math.cos(tilt) - y * math.sin(tilt)
    up = y * math.cos(tilt) + z * math.sin(tilt)
    return ((depth >= frustum.near_m) & (depth <= frustum.far_m)
            & (x.abs() <= depth * math.tan(math.radians(frustum.horizontal_fov_deg) / 2))
            & (up.abs() <= depth * math.tan(math.radians(frustum.vertical_fov_deg) / 2)))


def random_dropouts(visible: torch.Tensor, rate_per_s: float, mean_duration_s: float, fps: float,
                    generator: torch.Generator | None = None) -> torch.Tensor:
    """visible with random spans of lost tracking removed.

    visible: (..., T, K) bool, time on dim -2. A span starts on each frame with probability
    rate_per_s / fps (per hand) and lasts a geometric number of frames >= 1 with mean
    max(1, mean_duration_s * fps). Returns (..., T, K) bool.
    """
    visible = torch.as_tensor(visible, dtype=torch.bool)
    shape, frames = visible.shape, visible.shape[-2]
    starts = torch.rand(shape, generator=generator) < min(1.0, rate_per_s / fps)
    mean_frames = mean_duration_s * fps
    if mean_frames > 1:
        lam = -math.log1p(-1.0 / mean_frames)
        length = torch.empty(shape, dtype=torch.float64).exponential_(lam, generator=generator).floor().long() + 1
    else:
        length = torch.ones(shape, dtype=torch.long)
    t = torch.arange(frames).view(frames, 1).expand(shape)
    end = torch.where(starts, t + length, torch.full_like(length, -1))
    lost = torch.cummax(end, dim=-2).values > t
    return visible & ~lost.to(visible.device)


def simulate_visibility(rotations: torch.Tensor, positions: torch.Tensor, scenario: str = "MC",
                        frustum: Frustum = Frustum(), dropout: Dropout | None = None, fps: float = 30.0,
                        generator: torch.Generator | None = None) -> torch.Tensor:
    """(..., T, 2) bool hand visibility for device poses from :func:`device_poses`.

    scenario 'MC' (controllers): always visible; 'HT' (hand tracking): inside the frustum.
    dropout, when given, removes random spans in either scenario (fps is needed only then).
    """
    scenario = scenario.upper()
    if scenario not in SCENARIOS:
        raise ValueError(f"unknown scenario {scenario!r}; expected one of {SCENARIOS}")
    if scenario == "MC":
        visible = torch.ones(positions.shape[:-2] + (2,), dtype=torch.bool, device=positions.device)
    else:
        visible = hand_visibility(rotations[..., 0, :, :], positions[..., 0, :], positions[..., 1:, :], frustum)
    if dropout is not None:
        visible = random_dropouts(visible, dropout.rate_per_s, dropout.mean_duration_s, fps, generator)
    return visible


def component_poses(rotations: torch.Tensor, positions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The poses of the COMPONENTS from device poses (module docstring).

    rotations: (..., 3, 3, 3) and positions: (..., 3, 3) in DEVICES order.
    Returns (rotations (..., 5, 3, 3), positions (..., 5, 3)): the devices, then the hands in the
    head's frame.
    """
    to_head = rotations[..., :1, :, :].transpose(-1, -2)                      # (..., 1, 3, 3)
    in_head_r = to_head @ rotations[..., 1:, :, :]
    in_head_p = (to_head @ (positions[..., 1:, :] - positions[..., :1, :])[..., None])[..., 0]
    return torch.cat([rotations, in_head_r], dim=-3), torch.cat([positions, in_head_p], dim=-2)


def component_signals(rotations: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
    """:func:`pose_signals` stacked as :func:`stack_components` stacks them, without "visible".

    rotations: (..., T, 3, 3, 3) and positions: (..., T, 3, 3) as for pose_signals.
    Returns (..., T, 5, 18): per component its 6D rotation, position, then their velocity.
    """
    r, p = component_poses(rotations, positions)                              # (..., T, 5, 3, 3), (..., T, 5, 3)
    prev_r = torch.cat([r[..., :1, :, :, :], r[..., :-1, :, :, :]], dim=-4)
    prev_p = torch.cat([p[..., :1, :, :], p[..., :-1, :, :]], dim=-3)
    return _with_velocities(r, p, prev_r, prev_p)


def frame_signals(rotations: torch.Tensor, positions: torch.Tensor, visible: torch.Tensor,
                  previous_rotations: torch.Tensor, previous_positions: torch.Tensor,
                  previous_visible: torch.Tensor) -> torch.Tensor:
    """One frame's stacked signals (5, 18) from this and the previous frame's device poses
    ((3, 3, 3) rotations, (3, 3) positions, (2,) visible flags; on a stream's first frame pass
    the current ones as previous): :func:`component_signals` then :func:`hide_components` of
    the last frame, except that unseen hands' values are left as they are (the network never
    reads them), which keeps the tracker's per-frame graph small."""
    r, p = component_poses(torch.stack([previous_rotations, rotations]), torch.stack([previous_positions, positions]))
    x = _with_velocities(r[1], p[1], r[0], p[0])                             # (5, 18)
    both = (visible > 0.5) & (previous_visible > 0.5)
    both = torch.cat([both.new_ones(1), both.index_select(0, torch.tensor(HAND_OF, device=both.device))])[:, None]
    return torch.cat([x[:, :9], torch.where(both, x[:, 9:], x.new_tensor(REST_VELOCITY))], dim=-1)


def _with_velocities(r: torch.Tensor, p: torch.Tensor, prev_r: torch.Tensor, prev_p: torch.Tensor) -> torch.Tensor:
    """(..., 5, 18): 6D rotations and positions of the components, then their velocities from the
    previous poses; r, prev_r (..., 5, 3, 3), p, prev_p (..., 5, 3)."""
    return torch.cat([rot.convert(r, "matrix", "sixd"), p,
                      rot.convert(prev_r.transpose(-1, -2) @ r, "matrix", "sixd"), p - prev_p], dim=-1)


def _unstack(stacked: torch.Tensor, signals: dict) -> dict:
    """signals with its COMPONENTS and their velocities replaced by those of stacked (..., 5, 18)."""
    out = dict(signals)
    for i, name in enumerate(COMPONENTS):
        out[name], out[f"{name}_vel"] = stacked[..., i, :9], stacked[..., i, 9:]
    return out


def pose_signals(rotations: torch.Tensor, positions: torch.Tensor, visible: torch.Tensor | None = None) -> dict:
    """Input signals from device poses.

    rotations: (..., T, 3, 3, 3) and positions: (..., T, 3, 3) of head (eyes), left and right wrist
    in DEVICES order (world, metres); visible: (..., T, 2) hand flags (default: all visible).
    Returns {component: (..., T, 9), component + "_vel": (..., T, 9), "visible": (..., T, 2) float}
    for every component in COMPONENTS. Hand values are the given poses whether seen or not; see
    :func:`hide_unseen`.
    """
    out = _unstack(component_signals(rotations, positions), {})
    if visible is None:
        visible = torch.ones(positions.shape[:-2] + (2,))
    out["visible"] = torch.as_tensor(visible).to(dtype=positions.dtype, device=positions.device)
    return out


def headset_signals(world_rotations: torch.Tensor, world_positions: torch.Tensor, eye: Skeleton | torch.Tensor,
                    visible: torch.Tensor | None = None) -> dict:
    """Input signals from canonical-body forward kinematics (a pure function).

    world_rotations: (..., T, 22, 3, 3); world_positions: (..., T, 22, 3) metres (Motion.world());
    eye: the canonical Skeleton, or its (3,) / (..., 3) :func:`eye_offset`;
    visible: (..., T, 2) hand flags (default: all visible). Returns :func:`pose_signals`' dict.
    """
    if isinstance(eye, Skeleton):
        eye = eye_offset(eye)
    return pose_signals(*device_poses(world_rotations, world_positions, eye), visible)


def signals_from_motion(motion: Motion, scenario: str = "MC", frustum: Frustum = Frustum(),
                        dropout: Dropout | None = None, generator: torch.Generator | None = None) -> dict:
    """Input signals (dict of (T, 9) tensors and "visible" (T, 2)) of a motion in a scenario.

    motion: on the canonical body (other known rigs are mapped with to_canonical first).
    scenario: 'MC' (hands always visible) or 'HT' (visible inside frustum); dropout: optional
    random tracking losses (:class:`Dropout`) drawn with generator.
    """
    if motion.skeleton.names != canonical.JOINTS:
        motion = canonical.to_canonical(motion)
    rotations, positions = device_poses(*motion.world(), eye_offset(motion.skeleton))
    visible = simulate_visibility(rotations, positions, scenario, frustum, dropout, motion.fps, generator)
    return pose_signals(rotations, positions, visible)


def hide_unseen(signals: dict) -> dict:
    """Signals as a headset would give them: unseen hands carry no information.

    Where a hand is not visible, its components (world and in-head) and their velocities are
    zeros (an impossible 6D, so unmistakable); where it is visible but was not on the previous
    frame, its velocities are REST_VELOCITY (no previous pose to difference). NaN in hidden
    entries (real recordings) is replaced too. Returns a new dict; other keys are kept.
    """
    return _unstack(hide_components(stack_components(signals), signals["visible"]), signals)


def hide_components(stacked: torch.Tensor, visible: torch.Tensor) -> torch.Tensor:
    """:func:`hide_unseen` on stacked signals: stacked (..., T, 5, 18) (:func:`stack_components`),
    visible (..., T, 2) 0/1 hand flags. Returns (..., T, 5, 18)."""
    seen = visible > 0.5
    both = seen & torch.cat([seen[..., :1, :], seen[..., :-1, :]], dim=-2)
    head = torch.ones_like(seen[..., :1])
    hand_of = torch.tensor(HAND_OF, device=stacked.device)
    seen, both = (torch.cat([head, flags.index_select(-1, hand_of)], dim=-1)[..., None] for flags in (seen, both))
    rest = stacked.new_tensor(REST_VELOCITY)
    return torch.cat([torch.where(seen, stacked[..., :9], 0.0),
                      torch.where(both, stacked[..., 9:], torch.where(seen, rest, 0.0))], dim=-1)


def recentre(signals: dict, origin_xz: torch.Tensor | None = None) -> dict:
    """Signals with world positions relative to a ground-plane origin.

    Subtracts (origin_x, 0, origin_z) from the positions of "head", "left" and "right" (the
    height above the floor is kept; rotations, in-head components and velocities are unchanged).
    origin_xz: (..., 2) metres per stream; default the head's (x, z) at the stream's first frame.
    Applied after :func:`hide_unseen`, hidden hands hold -origin instead of zeros, which is
    harmless when the consumer masks unseen hands by "visible" (as the model does).
    """
    head = signals["head"]
    if origin_xz is None:
        origin_xz = head[..., 0, [6, 8]]
    origin_xz = torch.as_tensor(origin_xz, dtype=head.dtype, device=head.device)
    return _unstack(recentre_components(stack_components(signals), origin_xz), signals)


def recentre_components(stacked: torch.Tensor, origin_xz: torch.Tensor) -> torch.Tensor:
    """:func:`recentre` on stacked signals: stacked (..., T, 5, 18) (:func:`stack_components`),
    origin_xz (..., 2) metres. Returns (..., T, 5, 18)."""
    devices = stacked.new_tensor([float(name in DEVICES) for name in COMPONENTS])[:, None]      # (5, 1)
    return stacked - devices * torch.nn.functional.pad(ground_point(origin_xz), (6, 9))[..., None, None, :]


def ground_point(origin_xz: torch.Tensor) -> torch.Tensor:
    """(..., 3) the point (x, 0, z) of ground-plane coordinates origin_xz (..., 2), exactly."""
    return origin_xz @ origin_xz.new_tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def stack_components(signals: dict) -> torch.Tensor:
    """(..., T, 5, 18) tensor: per component in COMPONENTS order, its 9 values then its velocity."""
    return torch.stack([torch.cat([signals[n], signals[f"{n}_vel"]], dim=-1) for n in COMPONENTS], dim=-2)

"""Lifting 2D keypoints to 3D joints (video capture, steps 3 and 4 of specs/video-capture.md).

    model = load_lifter()                                    # shipped weights, or load_lifter("runs/lift/lifter.pt")
    joints = lift_sequence(model, keypoints, confidence)     # (T, 21, 2) pixels, (T, 21) -> (T, 22, 3)
    joints_m = joints * height_m                             # metres, camera axes, pelvis at 0

Normalisation (:func:`normalise`), per frame: the midpoint of the hips is the origin and the
scale 1/lambda makes lambda, the largest distance from there to a confident keypoint, equal 1.

The network (:class:`Lifter`) is a temporal convolutional network after VideoPose3D (Pavllo et
al., "3D human pose estimation in video with temporal convolutions and semi-supervised
training", CVPR 2019): a convolution of width 3 over the input frames, then residual blocks of
dilated convolutions (width 3, dilation 3, 9, ...) and 1x1 convolutions with batch norm, ReLU
and dropout, no padding, so a window of W = 3^levels frames (27 by default: 0.9 s at 30 fps)
gives the pose of one frame. A centred model lifts the middle frame of its window (offline, for
video files); a causal one the last frame, from past frames only (live cameras, no delay).

Input per frame and keypoint: the normalised x and y and the confidence (0 for a missing
keypoint, whose x and y are then 0). Output: the 22 canonical joints (humotion.canonical.JOINTS)
relative to the pelvis joint, in the camera's axes (OpenCV: x right, y down, z forward), in units
of the person's standing height: multiply by the height in metres (e.g. the template's, see
humotion.capture.template) before the bone-length correction of humotion.capture.joint_angles.
The scale of a person cannot be told from one camera's normalised 2D keypoints; their shape can.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from humotion import rotations as rot
from humotion.assets import ASSETS
from humotion.canonical import JOINTS
from humotion.capture.detection import KEYPOINTS
from humotion.model_files import load_model_file, save_model_file

DEFAULT_WEIGHTS: Path = ASSETS / "capture" / "lifter.pt"
"""Where the shipped lifting weights live (made by `humotion train lift`; see MODEL_CARD.md there)."""
LIVE_WEIGHTS: Path = ASSETS / "capture" / "lifter_causal.pt"
"""The shipped causal weights for live cameras (`humotion train lift --causal`), LiveLifter's default."""

NUM_KEYPOINTS, NUM_JOINTS = len(KEYPOINTS), len(JOINTS)
_HIPS = [KEYPOINTS.index("left_hip"), KEYPOINTS.index("right_hip")]


# -- inputs --------------------------------------------------------------------------------

def check_keypoints(keypoints, confidence) -> tuple[torch.Tensor, torch.Tensor]:
    """keypoints (..., 21, 2) and confidence (...,21) as float32 tensors, after checking shapes
    and values (finite pixels, confidences in [0, 1]); ValueError naming the problem otherwise."""
    keypoints = torch.as_tensor(keypoints, dtype=torch.float32)
    confidence = torch.as_tensor(confidence, dtype=torch.float32)
    if keypoints.dim() < 2 or keypoints.shape[-2:] != (NUM_KEYPOINTS, 2):
        raise ValueError(f"keypoints must have shape (..., {NUM_KEYPOINTS}, 2) (humotion's KEYPOINTS layout, "
                         f"x and y pixels), got {tuple(keypoints.shape)}")
    if confidence.shape != keypoints.shape[:-1]:
        raise ValueError(f"confidence must have shape {tuple(keypoints.shape[:-1])} (one per keypoint), "
                         f"got {tuple(confidence.shape)}")
    bad = ~torch.isfinite(keypoints).all(-1)
    if bad.any():
        where = [int(i) for i in torch.nonzero(bad)[0]]
        raise ValueError(f"keypoints contain NaN or infinity (first at index {tuple(where[:-1])}, keypoint "
                         f"{KEYPOINTS[where[-1]]!r}); give a missing keypoint confidence 0 and any finite position")
    if not (torch.isfinite(confidence) & (confidence >= 0) & (confidence <= 1)).all():
        raise ValueError("confidence values must lie in [0, 1] (0: missing keypoint)")
    return keypoints, confidence


def normalise(keypoints, confidence, min_confidence: float = 0.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Keypoints centred on the pelvis and scaled so the farthest confident one is at distance 1.

    keypoints: (..., 21, 2) pixels; confidence: (..., 21) in [0, 1]. A keypoint is confident when
    its confidence exceeds min_confidence. Per frame: centre (..., 2) pixels, the midpoint of the
    hips (one hip when only one is confident, the mean of the confident keypoints when neither
    is); lambda the largest distance from the centre to a confident keypoint; scale (...) = 1 /
    lambda (0 when no keypoint is confident or all sit on the centre). Returns (normalised
    (..., 21, 2) = (keypoints - centre) * scale, 0 for keypoints that are not confident; scale;
    centre). Image axes are kept: x right, y down.
    """
    keypoints, confidence = check_keypoints(keypoints, confidence)
    seen = (confidence > min_confidence).float()
    hips = seen[..., _HIPS]
    hip_centre = (keypoints[..., _HIPS, :] * hips[..., None]).sum(-2) / hips.sum(-1, keepdim=True).clamp_min(1)
    mean_centre = (keypoints * seen[..., None]).sum(-2) / seen.sum(-1, keepdim=True).clamp_min(1)
    centre = torch.where(hips.sum(-1, keepdim=True) > 0, hip_centre, mean_centre)
    offsets = (keypoints - centre[..., None, :]) * seen[..., None]
    reach = offsets.norm(dim=-1).amax(-1)
    scale = torch.where(reach > 1e-6, 1 / reach.clamp_min(1e-6), torch.zeros_like(reach))
    return offsets * scale[..., None, None], scale, centre


def lifting_inputs(keypoints, confidence) -> torch.Tensor:
    """(..., 21, 3) network inputs: normalised x, y (see normalise) and the confidence."""
    keypoints, confidence = check_keypoints(keypoints, confidence)
    normalised, _, _ = normalise(keypoints, confidence)
    return torch.cat([normalised, confidence[..., None]], dim=-1)


CENTRE_SMOOTHING = 15
"""Frames of the moving mean over a person's centre before their perspective crop (person_centred)."""


def person_centred(keypoints: torch.Tensor, confidence: torch.Tensor,
                   camera) -> tuple[torch.Tensor, torch.Tensor]:
    """Keypoints as a camera turned to look at the person would see them: a perspective crop
    (Yu et al., "PCLs: geometry-aware neural reconstruction of 3D pose with perspective crop
    layers", CVPR 2021). The lifter's training cameras look at the person (within a few degrees,
    humotion.capture.keypoints.random_camera); a person near the edge of a wide image is seen
    skewed, which it was not shown.

    keypoints (T, 21, 2) pixels, confidence (T, 21); camera: a humotion.capture.keypoints.VirtualCamera
    (its intrinsics K are used). Per frame, R is the shortest rotation taking the ray through the
    person's centre (normalise's: the hips' midpoint, a moving mean over the frames with anything
    seen among CENTRE_SMOOTHING; no turn where there are none) to the optical axis. Returns the keypoints mapped by K R K^-1 (T, 21, 2) pixels and R
    (T, 3, 3); a point j in the turned camera's axes is R^T j in the camera's."""
    _, _, centre = normalise(keypoints, confidence)
    f = torch.stack([camera.fx, camera.fy]).float()
    c = torch.stack([camera.cx, camera.cy]).float()
    seen = (confidence > 0).any(-1, keepdim=True).float()                  # (T, 1): a frame with nothing seen has no centre
    reach = CENTRE_SMOOTHING // 2                     # a moving mean: the turn must not jitter with the hips

    def window_sum(values):                           # (T, k) summed over each frame's window, edges repeated
        padded = torch.cat([values[:1].expand(reach, -1), values, values[-1:].expand(reach, -1)])
        return padded.unfold(0, 2 * reach + 1, 1).sum(-1)

    weight = window_sum(seen)
    centre = torch.where(weight > 0, window_sum(centre * seen) / weight.clamp_min(1), c)   # nothing seen: no turn
    ray = torch.cat([(centre - c) / f, torch.ones(len(centre), 1)], dim=-1)
    turn = rot.rotation_matrix_between(ray, torch.tensor([0.0, 0.0, 1.0]).expand_as(ray))
    points = torch.cat([(keypoints - c) / f, torch.ones(keypoints.shape[:-1] + (1,))], dim=-1)   # (T, 21, 3)
    turned = points @ turn.transpose(-1, -2)
    return turned[..., :2] / turned[..., 2:].clamp_min(1e-6) * f + c, turn


# -- the network ---------------------------------------------------------------------------

@dataclass
class LiftingConfig:
    """Sizes of the Lifter. channels: width of every convolution; levels: the window is 3^levels
    frames (levels - 1 residual blocks); dropout: after every convolution but the last;
    causal: lift the window's last frame (live use) instead of its middle one."""

    channels: int = 256
    """Width of the convolutions."""
    levels: int = 3
    """Window of 3^levels frames (3: 27)."""
    dropout: float = 0.25
    """Dropout after every convolution but the last."""
    causal: bool = False
    """Lift the last frame of each window (live cameras) instead of the middle one."""

    def __post_init__(self):
        if self.levels < 1 or self.channels < 1:
            raise ValueError(f"levels and channels must be positive, got {self.levels} and {self.channels}")

    @property
    def window(self) -> int:
        """Frames the network sees to lift one frame."""
        return 3 ** self.levels

    @property
    def target(self) -> int:
        """Index in the window of the frame lifted: the last (causal) or the middle one."""
        return self.window - 1 if self.causal else self.window // 2


class _Block(nn.Module):
    """Dilated convolution (width 3) then 1x1 convolution, each with batch norm, ReLU and dropout,
    plus the input frames that line up with the output (the last ones when causal)."""

    def __init__(self, channels: int, dilation: int, dropout: float, causal: bool):
        super().__init__()
        self.dilation, self.causal = dilation, causal
        self.layers = nn.Sequential(
            nn.Conv1d(channels, channels, 3, dilation=dilation, bias=False), nn.BatchNorm1d(channels), nn.ReLU(),
            nn.Dropout(dropout),
            nn.Conv1d(channels, channels, 1, bias=False), nn.BatchNorm1d(channels), nn.ReLU(), nn.Dropout(dropout))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.layers(x)
        start = 2 * self.dilation if self.causal else self.dilation
        return x[..., start:start + out.shape[-1]] + out


class Lifter(nn.Module):
    """Normalised 2D keypoints over a window of frames -> 3D canonical joints (module docstring).

    forward(inputs): inputs (B, T, 21, 3) with T >= config.window (x, y, confidence per keypoint,
    see lifting_inputs) -> (B, T - window + 1, 22, 3): output i is frame i + config.target, its
    joints relative to the pelvis (exactly 0), camera axes, units of standing height.
    """

    def __init__(self, config: LiftingConfig | None = None):
        super().__init__()
        self.config = config = config or LiftingConfig()
        self.fps = 30.0  # frame rate the weights were trained at (load_lifter sets the file's)
        c = config.channels
        self.expand = nn.Sequential(nn.Conv1d(NUM_KEYPOINTS * 3, c, 3, bias=False), nn.BatchNorm1d(c), nn.ReLU(),
                                    nn.Dropout(config.dropout))
        self.blocks = nn.Sequential(*(_Block(c, 3 ** level, config.dropout, config.causal)
                                      for level in range(1, config.levels)))
        self.head = nn.Conv1d(c, (NUM_JOINTS - 1) * 3, 1)
        nn.init.zeros_(self.head.weight)  # start from every joint on the pelvis, not a random pose
        nn.init.zeros_(self.head.bias)

    def forward(self, inputs: torch.Tensor) -> torch.Tensor:
        """inputs (B, T, 21, 3) -> joints (B, T - window + 1, 22, 3), as in the class docstring."""
        window = self.config.window
        if inputs.dim() != 4 or inputs.shape[-2:] != (NUM_KEYPOINTS, 3) or inputs.shape[1] < window:
            raise ValueError(f"inputs must have shape (batch, frames >= {window}, {NUM_KEYPOINTS}, 3), "
                             f"got {tuple(inputs.shape)}")
        x = self.blocks(self.expand(inputs.flatten(2).transpose(1, 2)))
        joints = self.head(x).transpose(1, 2).unflatten(-1, (NUM_JOINTS - 1, 3))
        return torch.cat([joints.new_zeros(joints.shape[:2] + (1, 3)), joints], dim=2)


# -- whole sequences and live streams ------------------------------------------------------

@torch.no_grad()
def lift_sequence(model: Lifter, keypoints, confidence, chunk: int = 4096) -> torch.Tensor:
    """(T, 22, 3) joints (pelvis-relative, camera axes, units of standing height) of every frame.

    keypoints: (T, 21, 2) pixels of one person; confidence: (T, 21) in [0, 1] (0: missing), at
    the model's frame rate (model.fps). The sequence is padded by repeating its first frame
    (causal model: window - 1 times before) or both end frames (centred: half a window each side),
    so every frame gets a pose; a causal model's frame t depends on frames <= t only.
    chunk: frames lifted per forward pass (bounds memory). The model runs in eval mode.
    """
    keypoints, confidence = check_keypoints(keypoints, confidence)
    if keypoints.dim() != 3 or keypoints.shape[0] == 0:
        raise ValueError(f"keypoints must have shape (frames >= 1, {NUM_KEYPOINTS}, 2), got {tuple(keypoints.shape)}")
    features = lifting_inputs(keypoints, confidence)
    config = model.config
    before = config.target
    after = config.window - 1 - before
    padded = torch.cat([features[:1].expand(before, -1, -1), features, features[-1:].expand(after, -1, -1)])
    was_training = model.training
    model.eval()
    device = next(model.parameters()).device
    out = [model(padded[None, start:start + chunk + config.window - 1].to(device))[0].cpu()
           for start in range(0, len(features), chunk)]
    model.train(was_training)
    return torch.cat(out)


class LiveLifter:
    """A causal Lifter on a live stream, one frame at a time: push() gives the newest frame's
    joints, the same as lift_sequence on the stream so far (the first frame stands in for the
    frames before it). model: default the shipped causal weights (LIVE_WEIGHTS)."""

    def __init__(self, model: Lifter | None = None):
        model = model if model is not None else load_lifter(LIVE_WEIGHTS)
        if not model.config.causal:
            raise ValueError("a live stream needs a causal model (LiftingConfig(causal=True), "
                             "`humotion train lift --causal`); a centred one waits for future frames")
        self.model = model.eval()
        self.frames: deque[torch.Tensor] = deque(maxlen=model.config.window)

    def reset(self) -> None:
        """Forget the stream (a new person or a cut)."""
        self.frames.clear()

    @torch.no_grad()
    def push(self, keypoints, confidence) -> torch.Tensor:
        """(22, 3) joints of this frame from its (21, 2) keypoints and (21,) confidences."""
        keypoints, confidence = check_keypoints(keypoints, confidence)
        if keypoints.dim() != 2:
            raise ValueError(f"push one frame: keypoints ({NUM_KEYPOINTS}, 2), got {tuple(keypoints.shape)}")
        features = lifting_inputs(keypoints, confidence)
        if not self.frames:
            self.frames.extend([features] * (self.frames.maxlen - 1))
        self.frames.append(features)
        device = next(self.model.parameters()).device
        return self.model(torch.stack(list(self.frames))[None].to(device))[0, 0].cpu()


# -- files ---------------------------------------------------------------------------------

def save_lifter(model: Lifter, path: str | Path, **extra) -> None:
    """Save weights, config and frame rate (and extra plain fields: training step, validation)."""
    save_model_file(model, path, fps=getattr(model, "module", model).fps, **extra)


def load_lifter(path: str | Path | None = None, map_location="cpu") -> Lifter:
    """A Lifter in eval mode from a file of save_lifter or a training checkpoint (default: the
    shipped DEFAULT_WEIGHTS); humotion.model_files has the format."""
    path = Path(path) if path is not None else DEFAULT_WEIGHTS
    if not path.is_file():
        raise FileNotFoundError(f"lifting weights not found: {path}. Train them with `humotion train lift` "
                                "and pass the run's lifter.pt (or lifter_best.pt)")
    return load_model_file(path, Lifter, LiftingConfig, map_location)


def procrustes_align(pred: torch.Tensor, true: torch.Tensor) -> torch.Tensor:
    """pred (..., J, 3) moved onto true (..., J, 3) by the best similarity transform (rotation,
    uniform scale, translation; least squares, no reflection), as for PA-MPJPE."""
    pred_mean, true_mean = pred.mean(-2, keepdim=True), true.mean(-2, keepdim=True)
    p, t = pred - pred_mean, true - true_mean
    u, s, vh = torch.linalg.svd(p.transpose(-1, -2) @ t)
    sign = torch.sign(torch.linalg.det(u @ vh))
    flip = torch.ones_like(s)
    flip[..., -1] = sign
    rotation = u @ (flip[..., None] * vh)
    scale = (s * flip).sum(-1) / p.square().sum((-1, -2)).clamp_min(1e-12)
    return scale[..., None, None] * p @ rotation + true_mean

"""An AvatarPoser-style peer of SparsePoser, trained and evaluated the same way (a baseline).

Architecture written from the paper (Jiang et al., "AvatarPoser: Articulated Full-Body Pose
Tracking from Sparse Motion Sensing", ECCV 2022), not from its code:

1. Input per frame: the three DEVICES (head at the eyes, left and right wrist), each its 6D
   rotation, 6D rotational velocity (R_{t-1}^T R_t), position and linear velocity: 18 numbers,
   54 per frame, over a window of the last `window` frames (the paper: 40/41). Positions are
   taken relative to the ground point under the head on the window's first frame (the paper
   does not say; this makes the network translation invariant, like SparsePoser's recentring).
   An unseen hand's values are zeros, as :func:`humotion.sparse.signals.hide_unseen` gives them
   (the paper assumes the hands are always tracked; no visibility flag is added).
2. A linear embedding to `width` (256), a transformer encoder (3 layers, 8 heads), causal:
   every frame sees only itself and the frames before it in its window.
3. Two heads on each frame's encoder output: the "stabilizer" MLP predicting the global (root)
   orientation (6D) and an MLP predicting the 21 other joints' rotations relative to their
   parents (6D). They are decoupled, as in the paper.
4. The root position is not predicted: forward kinematics from the known head places it (the
   body's eyes at the headset), as AvatarPoser translates the body from the head.

Losses (:func:`peer_loss`, the paper's four terms, L1): global orientation, local rotations
(normalised 6D), joint positions after forward kinematics (root from the head) and the hands'
(wrists') positions, with weights ORIENTATION 0.05 / 1 / 1 / 1. The paper's inverse-kinematics
refinement of the arms is left out here: the shared arm/foot solve applied to every model's
motion in bench/sparse_eval.py stands in for it.

Deviation, for the training budget: the paper predicts only the last frame of each window;
here the encoder is causal and every frame of a training window is supervised (its context the
frames before it in the window), which is the same function for the last frame and uses each
window 40 times. At run time each frame is predicted from the window ending at it
(:meth:`AvatarPoserPeer.forward`), so a stream is online and one frame costs one window.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from humotion.canonical import JOINTS, PARENTS
from humotion.model_files import load_model_file, save_model_file
from humotion.skeleton import forward_kinematics
from humotion.sparse import signals as sg
from humotion.sparse.model import SparseOutput, sixd_to_matrix

NUM_JOINTS = len(JOINTS)
INPUTS = 3 * 18
LOSS_WEIGHTS = {"orientation": 0.05, "rotation": 1.0, "fk": 1.0, "hand": 1.0}
_WRISTS = (JOINTS.index("left_wrist"), JOINTS.index("right_wrist"))
_HEAD = JOINTS.index("head")
_IDENTITY_6D = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0)


@dataclass
class PeerConfig:
    """Sizes of the AvatarPoser-style peer. window: frames of context (the paper: 40/41);
    width: embedding and transformer width (256); layers, heads: transformer encoder (3, 8);
    feedforward: the encoder's feed-forward width (4 x width; the paper does not give it here);
    mlp: width of the two heads' hidden layer."""

    window: int = 40
    width: int = 256
    layers: int = 3
    heads: int = 8
    feedforward: int = 1024
    mlp: int = 256

    def __post_init__(self):
        if self.width % self.heads:
            raise ValueError(f"width ({self.width}) must be divisible by heads ({self.heads})")


def device_inputs(signals: dict) -> tuple[torch.Tensor, torch.Tensor]:
    """(..., T, 54) device inputs (per device: 6D, 6D velocity, position, velocity) in WORLD
    coordinates and (..., T, 3) head positions, from a signals dict (hidden hands are zeros)."""
    stacked = sg.stack_components(signals)[..., :3, :]                       # (..., T, 3, 18)
    x = torch.cat([stacked[..., 0:6], stacked[..., 9:15], stacked[..., 6:9], stacked[..., 15:18]], dim=-1)
    return x.flatten(-2), stacked[..., 0, 6:9]


def recentre_window(x: torch.Tensor) -> torch.Tensor:
    """x (B, W, 54) with the three device positions relative to the ground point under the head
    on the window's first frame; a hidden hand (6D all zero) stays all zeros."""
    origin = sg.ground_point(x[:, 0, [12, 14]])                                # (B, 3)
    shift = torch.zeros_like(x[:, :1]).unflatten(-1, (3, 18))
    shift[..., 12:15] = origin[:, None, None]
    seen = (x.unflatten(-1, (3, 18))[..., :6] != 0).any(-1, keepdim=True)    # (B, W, 3, 1)
    return (x.unflatten(-1, (3, 18)) - shift * seen).flatten(-2)


def root_from_head(rotations: torch.Tensor, head_positions: torch.Tensor, offsets: torch.Tensor,
                   eye: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Place the body so its eyes are at the headset.

    rotations (..., 22, 3, 3) local (root global); head_positions (..., 3) the eyes, metres;
    offsets (..., 22, 3) or (22, 3); eye (..., 3) or (3,) the eyes in the head frame.
    Returns (root positions (..., 3), world rotations (..., 22, 3, 3), world positions (..., 22, 3)).
    """
    world_r, world_p = forward_kinematics(rotations, torch.zeros_like(head_positions), offsets, PARENTS)
    eyes = world_p[..., _HEAD, :] + (world_r[..., _HEAD, :, :] @ eye[..., None])[..., 0]
    root = head_positions - eyes
    return root, world_r, world_p + root[..., None, :]


class AvatarPoserPeer(nn.Module):
    """The peer network (module docstring). forward(signals) takes a signals dict of (T, 9) /
    (B, T, 9) and "visible" (like SparsePoser) and returns a SparseOutput: rotations
    (B, T, 22, 3, 3) local (joint 0 global), root_positions (B, T, 3) the template body's root
    placed under the headset (:func:`root_from_head`; the evaluation anchors each motion on its
    own body) and positions (B, T, 22, 3) that body's world joint positions, metres. Each frame
    is predicted from the window ending at it."""

    def __init__(self, config: PeerConfig | None = None):
        super().__init__()
        self.config = config = config or PeerConfig()
        self.fps = 30.0
        self.embed = nn.Linear(INPUTS, config.width)
        self.position = nn.Parameter(torch.randn(config.window, config.width) * 0.02)
        layer = nn.TransformerEncoderLayer(config.width, config.heads, config.feedforward, 0.0,
                                           activation="relu", batch_first=True)
        self.encoder = nn.TransformerEncoder(layer, config.layers, enable_nested_tensor=False)
        self.stabilizer = nn.Sequential(nn.Linear(config.width, config.mlp), nn.ReLU(), nn.Linear(config.mlp, 6))
        self.joints = nn.Sequential(nn.Linear(config.width, config.mlp), nn.ReLU(),
                                    nn.Linear(config.mlp, (NUM_JOINTS - 1) * 6))
        with torch.no_grad():  # start at the rest pose
            self.stabilizer[-1].bias.copy_(torch.tensor(_IDENTITY_6D))
            self.joints[-1].bias.copy_(torch.tensor(_IDENTITY_6D).repeat(NUM_JOINTS - 1))

    def encode_windows(self, x: torch.Tensor) -> torch.Tensor:
        """x (B, W, 54) world-frame device inputs, W <= config.window -> (B, W, 22, 6) raw 6D
        per frame, each frame seeing the frames before it in its window (causal)."""
        w = x.shape[1]
        mask = torch.triu(torch.full((w, w), float("-inf"), device=x.device), diagonal=1)
        h = self.encoder(self.embed(recentre_window(x)) + self.position[:w], mask=mask)
        return torch.cat([self.stabilizer(h), self.joints(h)], -1).unflatten(-1, (NUM_JOINTS, 6))

    def windows_raw(self, x: torch.Tensor, chunk: int = 256) -> torch.Tensor:
        """(B, T, 54) -> (B, T, 22, 6): every frame from the window of config.window frames
        ending at it (the first frames from the stream's start: one causal pass)."""
        w = self.config.window
        b, t = x.shape[:2]
        first = self.encode_windows(x[:, :min(w, t)])
        if t <= w:
            return first
        later = x.unfold(1, w, 1).permute(0, 1, 3, 2)[:, 1:].flatten(0, 1)    # (B * (T - W), W, 54)
        outs = [self.encode_last(part) for part in later.split(chunk)]
        return torch.cat([first, torch.cat(outs).unflatten(0, (b, t - w))], 1)

    def encode_last(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 22, 6) encode_windows(x)[:, -1] for full windows x (B, W, 54), W = config.window,
        with the last encoder layer computed for the last frame only (the other frames' outputs
        are unused; the last frame attends to every frame, so it needs no mask)."""
        w = x.shape[1]
        mask = torch.triu(torch.full((w, w), float("-inf"), device=x.device), diagonal=1)
        h = self.embed(recentre_window(x)) + self.position[:w]
        *early, last = self.encoder.layers
        for layer in early:
            h = layer(h, src_mask=mask)
        query = h[:, -1:]
        h = last.norm1(query + last.self_attn(query, h, h, need_weights=False)[0])
        h = last.norm2(h + last.linear2(last.activation(last.linear1(h))))[:, 0]
        return torch.cat([self.stabilizer(h), self.joints(h)], -1).unflatten(-1, (NUM_JOINTS, 6))

    def forward(self, signals: dict, offsets: torch.Tensor | None = None, eye: torch.Tensor | None = None,
                all_frames: bool = False) -> SparseOutput:
        """signals: dict (B, T, ...) or (T, ...). offsets (B, 22, 3) / eye (B, 3): the body to
        place under the head (default the 1.70 m template). all_frames: train on every frame of
        a window (one causal pass over x, no sliding windows; T must be <= config.window)."""
        unbatched = signals["head"].dim() == 2
        if unbatched:
            signals = {k: v.unsqueeze(0) for k, v in signals.items()}
        x, head = device_inputs(signals)
        raw = self.encode_windows(x) if all_frames else self.windows_raw(x)
        rotations = sixd_to_matrix(raw)
        if offsets is None:
            from humotion.canonical import canonical_skeleton
            skeleton = canonical_skeleton()
            offsets = skeleton.offsets.to(x.dtype)
            eye = sg.eye_offset(skeleton)
            offsets, eye = offsets.expand(x.shape[0], -1, -1), eye.expand(x.shape[0], -1)
        root, _, positions = root_from_head(rotations, head, offsets[:, None], eye[:, None])
        out = SparseOutput(rotations, root, positions=positions)
        return out.select(0) if unbatched else out


def peer_loss(model: AvatarPoserPeer, inputs: dict, target: dict, eye: torch.Tensor,
              weights: dict | None = None) -> tuple[torch.Tensor, dict]:
    """(weighted sum, {term: value}) of the paper's four L1 terms on a training batch from
    humotion.sparse.batches.make_batch (every frame supervised); eye (B, 3)."""
    weights = weights or LOSS_WEIGHTS
    out = model(inputs, target["offsets"], eye, all_frames=True)
    pred6, true6 = out.sixd, torch.cat([target["rotations"][..., 0], target["rotations"][..., 1]], -1)
    positions, true_positions = out.positions, target["world_positions"]
    terms = {"orientation": (pred6[..., 0, :] - true6[..., 0, :]).abs().mean(),
             "rotation": (pred6[..., 1:, :] - true6[..., 1:, :]).abs().mean(),
             "fk": (positions - true_positions).abs().mean(),
             "hand": (positions[..., _WRISTS, :] - true_positions[..., _WRISTS, :]).abs().mean()}
    return sum(weights[k] * v for k, v in terms.items()), terms


def save_peer(model: AvatarPoserPeer, path: str | Path, **extra) -> None:
    """Weights and config (humotion.model_files format)."""
    save_model_file(model, path, **extra)


def load_peer(path: str | Path, map_location="cpu") -> AvatarPoserPeer:
    """The peer in eval mode from save_peer's file or a training checkpoint."""
    return load_model_file(path, AvatarPoserPeer, PeerConfig, map_location)


# -- training --------------------------------------------------------------------------------

def _validate(model: AvatarPoserPeer, windows, config, device) -> dict[str, float]:
    """Loss and MPJPE (cm) on the validation windows in MC and in HT (no random losses)."""
    from humotion.sparse.train import validation_means

    def measure(model, batch, inputs, target):
        eye = batch["eye"].to(device)
        total, _ = peer_loss(model, inputs, target, eye)
        out = model(inputs, target["offsets"], eye, all_frames=True)
        return {"loss": total, "mpjpe": (out.positions - target["world_positions"]).norm(dim=-1).mean() * 100}

    return validation_means(model, windows, config, device, measure)


def train_peer(config, peer: PeerConfig | None = None) -> dict:
    """Train (or resume) the peer with SparsePoser's data pipeline and run settings.

    config: a humotion.sparse.train.TrainConfig (data, split, windows, augmentation, scenarios,
    steps, batch, seed, output folder; its `model` and `weights` fields are not used).
    Writes avatar_poser.pt / avatar_poser_best.pt and checkpoints in config.out_dir."""
    from humotion.sparse.train import run_data
    from humotion.training import Session, fit

    session = Session(config)
    data = run_data(config, session)
    device = session.device
    model = AvatarPoserPeer(peer or PeerConfig(window=config.length)).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.lr)

    def loss(model, batch):
        inputs, target = data.training_batch(batch)
        return peer_loss(model, inputs, target, batch["eye"].to(device))

    val_set = data.val_set
    return fit(session, model, optimizer, steps_per_epoch=data.steps_per_epoch, batches=data.batches, loss=loss,
               validate=(lambda module: _validate(module, val_set, config, device)) if val_set is not None else None,
               save_weights=lambda module, path, **extra: save_peer(module, path, fps=config.fps, **extra),
               weights_name="avatar_poser",
               describe=lambda val: f"val {val['loss']:.4f} (MC MPJPE {val['MC/mpjpe']:.1f} cm, "
                                    f"HT MPJPE {val['HT/mpjpe']:.1f} cm)")

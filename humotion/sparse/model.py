"""SparsePoser: full-body pose and root trajectory, online, from headset head and hand signals.

The network of specs/sparse-tracking.md, one frame at a time (all tensors float32, metres):

1. f_e, embedding: per input component (:data:`~humotion.sparse.signals.COMPONENTS`: head, left,
   right, left_in_head, right_in_head) four separate shallow MLPs, on the 6D rotation, the
   position, the rotation velocity (6D) and the position velocity, concatenated (4 * embed).
   An unseen hand's two components (world and in-head) take its mask token instead:
   e = v * e_visible + (1 - v) * token, computed as a select so hidden values never leak.
2. STAE: one GRU per component (5 GRUs, run as one grouped cell), then a transformer encoder
   whose 5 tokens are the components' GRU states (plus a learned per-component embedding).
3. TAMT, one token per hand: an MLP on the previous frame's STAE outputs of that hand's world
   and in-head components and of the head, giving the token for both of the hand's components
   (2 * 4 * embed numbers, halves for world / in-head). A forecaster reads the token and
   predicts that hand's 9-D world pose (6D + position) on the current frame (auxiliary loss).
   mask_token="fixed" replaces it by one learned constant per hand (ablation; no forecast).
   token_gradient="detached" (a training choice; the same function at run time) stops the
   gradient at TAMT's input: the token and the forecaster learn from the encoder's features
   without training the encoder through them.
4. Decoders, autoregressive: g_theta reads the STAE features and its previous output and has
   two heads, the global root orientation (6D) and the 21 other joints' rotations relative to
   their parents (6D). g_gamma reads the STAE features, the current pose, its previous output
   and where the previous root is relative to the current head; it predicts the root's
   translation from t-1 to t in the previous root's heading frame (yaw only), integrated to a
   trajectory; on the first frame a second head places the root relative to the head instead.
   g_aux (training only; never fed back) predicts every joint's transform in body coordinates.

Translation invariance: world positions are taken relative to the ground-plane point under the
head on the first frame of the stream (:func:`~humotion.sparse.signals.recentre`); the
trajectory is predicted in that frame and the origin is added back to every output position.

:meth:`SparsePoser.forward` (a window, for training) and :meth:`SparsePoser.step` (one frame of
a live stream) run the same per-frame function, so they give identical results.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Callable, ClassVar

import torch
from torch import nn

from humotion import rotations as rot
from humotion.canonical import JOINTS
from humotion.model_files import load_model_file, save_model_file
from humotion.sparse import signals as sg

NUM_JOINTS = len(JOINTS)
NUM_COMPONENTS = len(sg.COMPONENTS)
HAND_OF = sg.HAND_OF             # which hand (0 left, 1 right) each hand component belongs to
FRAME_OF = (0, 0, 1, 1)          # which half of the hand's token (0 world, 1 in-head) it takes
TAMT_CONTEXT = ((1, 3, 0), (2, 4, 0))   # per hand, the components TAMT reads: world, in-head, head
IDENTITY_6D = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0)
DELTA_SCALE = 0.05               # metres per unit of g_gamma's translation output
MASK_TOKENS = ("adaptive", "fixed")
TOKEN_GRADIENTS = ("full", "detached")


@dataclass
class SparseConfig:
    """Sizes of SparsePoser. embed: per part (rotation, position, their velocities), so a
    component's embedding has 4 * embed numbers; hidden: GRU state and transformer width;
    layers / heads / feedforward: transformer encoder (no dropout; feedforward None: 2 x hidden);
    decoder: decoder MLP width (None: 2 x hidden);
    mask_token: 'adaptive' (TAMT) or 'fixed' (learned constant); token_gradient: 'detached'
    (the losses do not reach the encoder through TAMT's input; training only, see the module
    docstring) or 'full' (they do: the forecast loss and the token's recurrent loop train the
    encoder too; how the networks before this option were trained, which load as 'detached')."""

    embed: int = 32
    """Embedding size per input part."""
    hidden: int = 128
    """GRU / transformer width."""
    layers: int = 2
    heads: int = 4
    feedforward: int | None = None
    """Transformer feed-forward width (None: 2 x hidden)."""
    decoder: int | None = None
    """Decoder MLP width (None: 2 x hidden)."""
    mask_token: str = "adaptive"
    """adaptive: TAMT; fixed: a learned constant."""
    token_gradient: str = "detached"
    """detached: the mask token and forecaster learn from the encoder without training it; full: they train it too
    (an ablation)."""
    TRAINING_ONLY: ClassVar[tuple[str, ...]] = ("token_gradient",)
    """Fields that change how the network trains, not what it computes."""

    def __post_init__(self):
        self.feedforward = 2 * self.hidden if self.feedforward is None else self.feedforward
        self.decoder = 2 * self.hidden if self.decoder is None else self.decoder
        if self.mask_token not in MASK_TOKENS:
            raise ValueError(f"mask_token must be one of {MASK_TOKENS}, got {self.mask_token!r}")
        if self.token_gradient not in TOKEN_GRADIENTS:
            raise ValueError(f"token_gradient must be one of {TOKEN_GRADIENTS}, got {self.token_gradient!r}")
        if self.hidden % self.heads:
            raise ValueError(f"hidden ({self.hidden}) must be divisible by heads ({self.heads})")


# -- grouped layers: one set of weights per component, applied in one batched matrix product --
# They take groups first, (G, B, features), so that product needs no transposes.

class GroupedLinear(nn.Module):
    """(G, B, in) -> (G, B, out) with separate weights per group (nn.Linear's init)."""

    def __init__(self, groups: int, n_in: int, n_out: int):
        super().__init__()
        bound = 1 / math.sqrt(n_in)
        self.weight = nn.Parameter(torch.empty(groups, n_in, n_out).uniform_(-bound, bound))
        self.bias = nn.Parameter(torch.empty(groups, n_out).uniform_(-bound, bound))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x (G, B, in) -> (G, B, out)."""
        return x @ self.weight + self.bias[:, None]


def grouped_mlp(groups: int, n_in: int, width: int, n_out: int) -> nn.Sequential:
    """A shallow per-group MLP: linear, GELU, linear."""
    return nn.Sequential(GroupedLinear(groups, n_in, width), nn.GELU(), GroupedLinear(groups, width, n_out))


class GroupedGRUCell(nn.Module):
    """G independent GRU cells (nn.GRUCell's equations and init) stepped together.

    x: (G, B, in), h: (G, B, hidden) -> (G, B, hidden).
    """

    def __init__(self, groups: int, n_in: int, hidden: int):
        super().__init__()
        self.input = GroupedLinear(groups, n_in, 3 * hidden)
        self.state = GroupedLinear(groups, hidden, 3 * hidden)
        bound = 1 / math.sqrt(hidden)
        for p in self.parameters():
            nn.init.uniform_(p, -bound, bound)

    def forward(self, x: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        """x (G, B, in), h (G, B, hidden) -> the next h (G, B, hidden)."""
        xr, xz, xn = self.input(x).chunk(3, dim=-1)
        hr, hz, hn = self.state(h).chunk(3, dim=-1)
        r, z = torch.sigmoid(xr + hr), torch.sigmoid(xz + hz)
        n = torch.tanh(xn + r * hn)
        return (1 - z) * n + z * h


def block_diagonal(weights: list[torch.Tensor]) -> torch.Tensor:
    """Grouped weights [(G, n_i, m_i), ...] -> (G, sum n_i, sum m_i), each on the diagonal."""
    total = sum(w.shape[-1] for w in weights)
    rows, start = [], 0
    for w in weights:
        rows.append(nn.functional.pad(w, (start, total - start - w.shape[-1])))
        start += w.shape[-1]
    return torch.cat(rows, dim=-2)


def mlp(n_in: int, width: int, n_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(n_in, width), nn.GELU(), nn.Linear(width, width), nn.GELU(), nn.Linear(width, n_out))


_CROSS = torch.tensor([[0, 0, 0], [0, 0, 1], [0, -1, 0],      # row 3i + j: a_i b_j's share of a x b
                       [0, 0, -1], [0, 0, 0], [1, 0, 0],
                       [0, 1, 0], [-1, 0, 0], [0, 0, 0]], dtype=torch.float32)
"""(9, 3): the flattened outer product a b^T times this is the cross product a x b."""
_HEADING_TERMS = torch.tensor([[1, 0, 0], [0, 0, 0], [0, 1, 0],
                               [0, 0, 0], [0, 0, 1], [0, 0, 0],
                               [0, -1, 0], [0, 0, 0], [1, 0, 0]], dtype=torch.float32)
"""(9, 3): a flattened rotation matrix times this is (R00 + R22, R02 - R20, R11)."""
_YAW_MATRIX = torch.tensor([[1, 0, 0, 0, 0, 0, 0, 0, 1],
                            [0, 0, 1, 0, 0, 0, -1, 0, 0]], dtype=torch.float32)
"""(2, 9): (cos, sin) times this, plus _YAW_ONE, is the flattened rotation about +Y."""
_YAW_ONE = torch.tensor([0, 0, 0, 0, 1, 0, 0, 0, 0], dtype=torch.float32)


def orthonormal_columns(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(..., 6) -> the three (..., 3) columns of its rotation matrix by Gram-Schmidt:
    humotion.rotations' 'sixd' (the first two columns), the same maths as
    roma.special_gramschmidt, written with few operations (the cross product as one matrix
    product) so the tracker's per-frame ONNX graph stays small."""
    first = x[..., :3] / torch.linalg.vector_norm(x[..., :3], dim=-1, keepdim=True)
    second = x[..., 3:] - (first * x[..., 3:]).sum(-1, keepdim=True) * first
    second = second / torch.linalg.vector_norm(second, dim=-1, keepdim=True)
    third = (first[..., :, None] * second[..., None, :]).flatten(-2) @ _CROSS.to(x)
    return first, second, third


def sixd_to_matrix(x: torch.Tensor) -> torch.Tensor:
    """(..., 6) -> (..., 3, 3): the rotation matrices of orthonormal_columns."""
    return torch.stack(orthonormal_columns(x), dim=-1)


def heading(rotation: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) yaw-only part of rotations: the twist about +Y (swing-twist decomposition).

    With the rotation's quaternion (w, x, y, z), the twist is (w, 0, y, 0) normalised, so the
    yaw angle has cos = (w^2 - y^2) / (w^2 + y^2) and sin = 2wy / (w^2 + y^2); in matrix entries
    w^2 - y^2 = (R00 + R22) / 2, w^2 + y^2 = (1 + R11) / 2 and 2wy = (R02 - R20) / 2, so no
    quaternion is needed. Well defined except for half turns about a horizontal axis (R11 = -1);
    differentiable elsewhere. Written as two constant matrix products (a small ONNX graph)."""
    terms = rotation.flatten(-2) @ _HEADING_TERMS.to(rotation)                 # (..., 3)
    cos_sin = terms[..., :2] / (1.0 + terms[..., 2:] + 2e-12)
    return (cos_sin @ _YAW_MATRIX.to(rotation) + _YAW_ONE.to(rotation)).unflatten(-1, (3, 3))


@dataclass
class SparseState:
    """What SparsePoser carries from one frame to the next (batch B, recentred frame).

    t: (B,) int64 frames seen (a tensor, so one compiled graph serves every frame).
    origin: (B, 2) ground-plane (x, z) of the head on frame 0, metres.
    hidden / stae: (B, 5, hidden) GRU states and STAE outputs. pose: (B, 22, 6) previous pose
    (root global, others local; normalised 6D). root: (B, 3) previous root position (recentred);
    root_rotation: (B, 3, 3) previous root orientation; delta: (B, 3) previous g_gamma output.
    """

    t: torch.Tensor
    origin: torch.Tensor
    hidden: torch.Tensor
    stae: torch.Tensor
    pose: torch.Tensor
    root: torch.Tensor
    root_rotation: torch.Tensor
    delta: torch.Tensor


@dataclass(frozen=True)
class SparseOutput:
    """What a sparse-tracking network gives for a window of headset frames: SparsePoser's
    outputs, and those of the bench's baselines (humotion.sparse.baselines.KnnPoser,
    humotion.sparse.peers.AvatarPoserPeer). World frame, metres, float32 tensors.

    Shapes below are for a batched window, (B, T, ...); an unbatched window has no B, one frame
    of SparsePoser.step no T. J is the canonical body's 22 joints. Reads as a dict too
    (``out["rotations"]``, keys(), items()), like smplx's ModelOutput. Operations return new
    outputs (select, map, dataclasses.replace).
    """

    rotations: torch.Tensor
    """(B, T, J, 3, 3) joint rotation matrices: joint 0 global, the others relative to their parent."""
    root_positions: torch.Tensor
    """(B, T, 3) root (pelvis) positions, metres."""
    positions: torch.Tensor | None = None
    """(B, T, J, 3) world joint positions, metres, from a network that poses a body itself
    (AvatarPoserPeer); None otherwise."""
    forecast: torch.Tensor | None = None
    """(B, T, 2, 9) each hand's (left, right) forecast world pose on the frame: 6D rotation and
    position (metres); None for a fixed mask token and for the baselines."""
    aux: torch.Tensor | None = None
    """(B, T, J, 9) g_aux's body-coordinate joint transforms: 6D rotation and position (metres)
    relative to the root, in the root's frame; None unless asked for (SparsePoser.forward's aux)."""
    state: SparseState | None = None
    """SparsePoser's state after the window's last frame, to carry on from (forward); None elsewhere."""

    def __post_init__(self):
        lead = tuple(self.rotations.shape[:-3])
        if tuple(self.rotations.shape[-3:]) != (NUM_JOINTS, 3, 3) or tuple(self.root_positions.shape) != (*lead, 3):
            raise ValueError(f"SparseOutput: rotations have shape {tuple(self.rotations.shape)} and root_positions "
                             f"{tuple(self.root_positions.shape)}; expected (..., {NUM_JOINTS}, 3, 3) and (..., 3), "
                             "the same leading dimensions")

    @property
    def sixd(self) -> torch.Tensor:
        """(B, T, J, 6) the rotations as normalised 6D (humotion.rotations' 'sixd': the matrices'
        first two columns)."""
        return rot.convert(self.rotations, "matrix", "sixd")

    def keys(self) -> tuple[str, ...]:
        """The outputs' names, as a dict's keys: the fields (sixd, derived, reads by name too)."""
        return tuple(f.name for f in fields(self))

    def items(self) -> list[tuple[str, object]]:
        """(name, value) of every field, as a dict's items; a missing output's value is None."""
        return [(name, getattr(self, name)) for name in self.keys()]

    def __getitem__(self, key: str):
        if key != "sixd" and key not in self.keys():
            raise KeyError(f"SparseOutput has no {key!r}; it has {', '.join(self.keys())} and sixd")
        return getattr(self, key)

    def map(self, function: Callable[[torch.Tensor], torch.Tensor]) -> SparseOutput:
        """A new output with function applied to every tensor (tensors of any shape in and out;
        None outputs stay None; the state is kept as it is)."""
        return replace(self, **{name: function(value) for name, value in self.items()
                                if isinstance(value, torch.Tensor)})

    def select(self, index) -> SparseOutput:
        """Every tensor indexed by index along its leading dimensions (e.g. 0: the first window
        of a batch; (slice(None), -1): each window's last frame)."""
        return self.map(lambda value: value[index])

    @classmethod
    def stack(cls, outputs: list[SparseOutput], dim: int) -> SparseOutput:
        """Outputs of equal shapes stacked along a new dimension dim (frames into a window);
        an output missing (None) from the first is None in the result; no state."""
        first = outputs[0]
        return cls(**{name: None if value is None else torch.stack([getattr(o, name) for o in outputs], dim)
                      for name, value in first.items() if name != "state"})


class SparsePoser(nn.Module):
    """Full-body motion from sparse headset signals (module docstring).

    Inputs are signal dicts from :mod:`humotion.sparse.signals` (pose_signals / headset_signals,
    usually through hide_unseen): COMPONENTS and their "_vel" (..., 9), "visible" (..., 2).
    Outputs are a :class:`SparseOutput` (world frame, metres; B and T as in the input, no B for
    an unbatched input): rotations, root_positions, forecast (None for a fixed token), aux
    (only when asked), and sixd derived from the rotations.
    """

    def __init__(self, config: SparseConfig | None = None):
        super().__init__()
        self.config = config = config or SparseConfig()
        e, h, d, c = config.embed, config.hidden, config.decoder, NUM_COMPONENTS
        token = 2 * 4 * e
        self.embed_rotation = grouped_mlp(c, 6, e, e)
        self.embed_position = grouped_mlp(c, 3, e, e)
        self.embed_rotation_velocity = grouped_mlp(c, 6, e, e)
        self.embed_position_velocity = grouped_mlp(c, 3, e, e)
        self.gru = GroupedGRUCell(c, 4 * e, h)
        self.component_embedding = nn.Parameter(torch.randn(c, h) * 0.02)
        layer = nn.TransformerEncoderLayer(h, config.heads, config.feedforward, 0.0,
                                           activation="gelu", batch_first=True, norm_first=True)
        self.encoder = nn.TransformerEncoder(layer, config.layers, enable_nested_tensor=False)
        self.encoder_norm = nn.LayerNorm(h)
        if config.mask_token == "adaptive":
            self.tamt = grouped_mlp(2, 3 * h, h, token)
            self.forecaster = grouped_mlp(2, token, h, 9)
        else:
            self.fixed_token = nn.Parameter(torch.randn(2, token) * 0.02)
        feat = c * h
        self.pose_trunk = mlp(feat + NUM_JOINTS * 6, d, d)
        self.root_head = nn.Linear(d, 6)
        self.joint_head = nn.Linear(d, (NUM_JOINTS - 1) * 6)
        self.trajectory_trunk = mlp(feat + NUM_JOINTS * 6 + 6, d // 2, d // 2)
        self.delta_head = nn.Linear(d // 2, 3)
        self.start_head = nn.Linear(d // 2, 3)
        self.aux = mlp(feat, d, NUM_JOINTS * 9)
        with torch.no_grad():  # start near the rest pose, the pelvis 0.6 m below the eyes
            self.root_head.bias.copy_(torch.tensor(IDENTITY_6D))
            self.joint_head.bias.copy_(torch.tensor(IDENTITY_6D).repeat(NUM_JOINTS - 1))
            self.start_head.bias.copy_(torch.tensor([0.0, -0.6, 0.0]))

    # -- state ---------------------------------------------------------------------------
    def initial_state(self, origin: torch.Tensor) -> SparseState:
        """The state before the first frame of streams whose ground origin is origin: (B, 2)
        metres, usually the head's (x, z) on the first frame."""
        b, h = origin.shape[0], self.config.hidden
        zeros = origin.new_zeros
        identity = origin.new_tensor(IDENTITY_6D).repeat(b, NUM_JOINTS, 1)
        return SparseState(torch.zeros(b, dtype=torch.int64, device=origin.device), origin.clone(),
                           zeros(b, NUM_COMPONENTS, h), zeros(b, NUM_COMPONENTS, h), identity, zeros(b, 3),
                           torch.eye(3, dtype=origin.dtype, device=origin.device).repeat(b, 1, 1), zeros(b, 3))

    # -- one frame -----------------------------------------------------------------------
    def _tokens(self, stae: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Mask tokens (2, B, 2, 4 * embed) (hand, batch, world / in-head) and forecasts (B, 2, 9)."""
        if self.config.mask_token == "fixed":
            return self.fixed_token[:, None].expand(-1, stae.shape[0], -1).unflatten(-1, (2, -1)), None
        context = stae.index_select(1, torch.tensor(TAMT_CONTEXT, device=stae.device).flatten())   # (B, 6, hidden)
        context = context.unflatten(1, (2, -1)).flatten(-2).transpose(0, 1)                         # (2, B, 3 * hidden)
        if self.config.token_gradient == "detached":
            context = context.detach()
        token = self.tamt(context)
        return token.unflatten(-1, (2, -1)), self.forecaster(token).transpose(0, 1)

    def _embed(self, x: torch.Tensor) -> torch.Tensor:
        """(5, B, 18) signals and velocities -> (5, B, 4 * embed): the four part MLPs (rotation
        x[..., 0:6], position 6:9, their velocities 9:15 and 15:18) evaluated as one MLP with
        block-diagonal weights, which is the same function in two matrix products."""
        parts = (self.embed_rotation, self.embed_position, self.embed_rotation_velocity, self.embed_position_velocity)
        first, _, second = zip(*parts)
        hidden = nn.functional.gelu(x @ block_diagonal([f.weight for f in first]) + torch.cat([f.bias for f in first], -1)[:, None])
        return hidden @ block_diagonal([s.weight for s in second]) + torch.cat([s.bias for s in second], -1)[:, None]

    def _encode(self, x: torch.Tensor) -> torch.Tensor:
        """The transformer encoder on (B, 5, hidden) tokens, written out (pre-norm layers, GELU,
        no dropout: what self.encoder computes, checked in the tests) because
        nn.MultiheadAttention's general path exports to about twice the ONNX nodes."""
        heads = self.config.heads
        for layer in self.encoder.layers:
            attention = layer.self_attn
            qkv = nn.functional.linear(layer.norm1(x), attention.in_proj_weight, attention.in_proj_bias)
            q, k, v = qkv.unflatten(-1, (3, heads, -1)).permute(2, 0, 3, 1, 4)          # (B, heads, 5, d) each
            weights = torch.softmax(q @ k.transpose(-1, -2) * q.shape[-1] ** -0.5, dim=-1)
            x = x + attention.out_proj((weights @ v).transpose(1, 2).flatten(2))
            x = x + layer.linear2(layer.activation(layer.linear1(layer.norm2(x))))
        return x

    def advance(self, x: torch.Tensor, visible: torch.Tensor, state: SparseState, aux: bool = False):
        """One frame, the step every public path runs. x: (B, 5, 18) signals + velocities in the
        stream's recentred frame (signals.recentre_components with state.origin); visible: (B, 2).
        Unseen hands' values in x are never read. Returns (the frame's SparseOutput, (B, ...)
        without T, positions in the recentred frame; the next state)."""
        tokens, forecast = self._tokens(state.stae)
        e = self._embed(x.transpose(0, 1))                                       # (5, B, 4E), groups first
        seen = (visible > 0.5).T.index_select(0, torch.tensor(HAND_OF, device=x.device))[..., None]   # (4, B, 1)
        masked = tokens[list(HAND_OF), :, list(FRAME_OF)]                        # (4, B, 4E)
        e = torch.cat([e[:1], torch.where(seen, e[1:], masked)])
        hidden = self.gru(e, state.hidden.transpose(0, 1)).transpose(0, 1)      # (B, 5, hidden)
        stae = self.encoder_norm(self._encode(hidden + self.component_embedding))
        feat = stae.flatten(1)

        trunk = self.pose_trunk(torch.cat([feat, state.pose.flatten(1)], -1))
        raw = torch.cat([self.root_head(trunk), self.joint_head(trunk)], -1).unflatten(-1, (NUM_JOINTS, 6))
        columns = orthonormal_columns(raw)
        rotations = torch.stack(columns, dim=-1)                                   # (B, 22, 3, 3)
        pose = torch.cat(columns[:2], dim=-1)                                       # normalised 6D

        head_position = x[:, 0, 6:9]
        first = (state.t == 0)[:, None]                                          # (B, 1)
        yaw = heading(torch.where(first[..., None], rotations[:, 0], state.root_rotation))   # (B, 3, 3)
        relative = torch.where(first, 0.0, (yaw.transpose(-1, -2) @ (head_position - state.root)[..., None])[..., 0])
        traj = self.trajectory_trunk(torch.cat([feat, pose.flatten(1), state.delta, relative], -1))
        delta = torch.where(first, 0.0, self.delta_head(traj) * DELTA_SCALE)
        root = torch.where(first, head_position + (yaw @ self.start_head(traj)[..., None])[..., 0],
                           state.root + (yaw @ delta[..., None])[..., 0])

        out = SparseOutput(rotations, root, forecast=forecast,
                           aux=self.aux(feat).unflatten(-1, (NUM_JOINTS, 9)) if aux else None)
        nxt = SparseState(state.t + 1, state.origin, hidden, stae, pose, root, rotations[:, 0], delta)
        return out, nxt

    # -- public paths --------------------------------------------------------------------
    def forward(self, signals: dict, state: SparseState | None = None, aux: bool | None = None) -> SparseOutput:
        """Run over a window. signals: dict of (B, T, 9) / (B, T, 2) tensors (or without B).

        state: carry on from an earlier call (default: a new stream starting at frame 0).
        aux: compute g_aux (default: in training mode). Returns the window's SparseOutput, its
        state the state after the last frame.
        """
        unbatched = signals["head"].dim() == 2
        if unbatched:
            signals = {k: v.unsqueeze(0) for k, v in signals.items()}
        if state is None:
            state = self.initial_state(signals["head"][:, 0, [6, 8]])
        result = self.forward_stacked(sg.stack_components(signals), signals["visible"], state, aux)
        return result.select(0) if unbatched else result

    def forward_stacked(self, x: torch.Tensor, visible: torch.Tensor, state: SparseState,
                        aux: bool | None = None) -> SparseOutput:
        """forward on stacked signals: x (B, T, 5, 18) world-frame signals as
        signals.stack_components stacks them, visible (B, T, 2); state is needed. Same outputs."""
        aux = self.training if aux is None else aux
        x = sg.recentre_components(x, state.origin)
        frames = []
        for t in range(x.shape[1]):
            out, state = self.advance(x[:, t], visible[:, t], state, aux)
            frames.append(out)
        return replace(self._to_world(SparseOutput.stack(frames, 1), state.origin), state=state)

    def step(self, frame: dict, state: SparseState | None = None) -> tuple[SparseOutput, SparseState]:
        """One frame of a live stream: frame is a signals dict of (B, 9) / (B, 2) tensors (or
        (9,) / (2,)). Returns (the frame's SparseOutput, without the T dimension and without a
        state; the state for the next frame). The first call (state None) fixes the stream's
        ground origin."""
        out = self.forward({k: v.unsqueeze(-2) for k, v in frame.items()}, state, aux=False)
        index = 0 if frame["head"].dim() == 1 else (slice(None), 0)
        return replace(out.select(index), state=None), out.state

    @staticmethod
    def _to_world(out: SparseOutput, origin: torch.Tensor) -> SparseOutput:
        """out (B, T, ...) in the recentred frame moved back by origin (B, 2), metres."""
        shift = sg.ground_point(origin)[:, None]                                  # (B, 1, 3)
        forecast = out.forecast
        if forecast is not None:
            forecast = torch.cat([forecast[..., :6], forecast[..., 6:] + shift[:, :, None]], -1)
        return replace(out, root_positions=out.root_positions + shift, forecast=forecast)


# -- saving and loading ------------------------------------------------------------------------

def save_sparse_model(model: SparsePoser, path: str | Path, **extra) -> None:
    """Save weights and config (and extra plain fields: fps, the training step, validation) to path."""
    save_model_file(model, path, **extra)


def load_sparse_model(path: str | Path, map_location="cpu") -> SparsePoser:
    """A SparsePoser in eval mode from a file of save_sparse_model or a training checkpoint;
    model.fps is the frame rate it was trained at (humotion.model_files has the format)."""
    return load_model_file(path, SparsePoser, SparseConfig, map_location)

"""The learned retargeter's networks (specs/retargeting.md): per skeleton domain a skeleton
encoder, a pose-aware attention motion encoder, a motion decoder and a discriminator, meeting in
a latent space of per-part codes shared by all domains.

Shapes: B windows (or one clip), T frames, J modelled joints of the domain (domains.DomainSpec),
N = 6 parts (humotion.retarget.parts.PARTS), d = config.width. Motions go in and out normalised
per domain (mean and standard deviation of the training features, buffers of the network).

Attention tokens per frame: the N part tokens, the J joint tokens, the root token (its velocity
and height), in the column order of the membership matrix P (N, J + 1) with the parts in front.
The separation matrix U (separation_matrix) lets a part attend to itself, its member joints and
the root; a joint to its part, the joints of its part and the root; the root to itself only. So
tokens exchange information within a part (plus the shared root) however many layers are
stacked: a part's code depends on its own joints, the root and its skeleton code, nothing else.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import nn

from humotion.model_files import load_model_file, save_model_file
from humotion.retarget.domains import DomainSpec
from humotion.retarget.parts import PARTS, membership_matrix

N = len(PARTS)
ROOT_FEATURES = 3


def separation_matrix(membership: torch.Tensor) -> torch.Tensor:
    """U (N + J + 1, N + J + 1) float from P (N, J + 1): 0 where a token may attend to another,
    -inf elsewhere. Tokens: parts, joints, root (module docstring); rows attend, columns are attended."""
    p = membership > 0
    n, m = p.shape
    joints = p[:, :-1]                                          # (N, J) membership of the joints
    allowed = torch.zeros(n + m, n + m, dtype=torch.bool)
    allowed[:n, :n] = torch.eye(n, dtype=torch.bool)            # a part sees itself,
    allowed[:n, n:] = p                                         # its joints and the root (P's last column)
    allowed[n:-1, :n] = joints.T                                # a joint sees its part,
    allowed[n:-1, n:-1] = (joints.T.float() @ joints.float()) > 0   # the joints sharing a part with it,
    allowed[n:-1, -1] = True                                    # and the root;
    allowed[-1, -1] = True                                      # the root sees itself only
    return torch.zeros(n + m, n + m).masked_fill(~allowed, float("-inf"))


def _conv(c_in: int, c_out: int, kernel: int, groups: int = 1) -> nn.Conv1d:
    return nn.Conv1d(c_in, c_out, kernel, padding=kernel // 2, groups=groups)


class SkeletonEncoder(nn.Module):
    """Per part k a 3-layer MLP with ReLU on the part's rest offsets S_k (L_k, 3): offsets
    (B, J, 3) metres -> skeleton codes (B, N, d)."""

    def __init__(self, parts: tuple[int, ...], width: int):
        super().__init__()
        self.members = [[j for j, part in enumerate(parts) if part == k] for k in range(N)]
        self.mlps = nn.ModuleList(
            nn.Sequential(nn.Linear(3 * len(m), width), nn.ReLU(), nn.Linear(width, width), nn.ReLU(),
                          nn.Linear(width, width)) for m in self.members)

    def forward(self, offsets: torch.Tensor) -> torch.Tensor:
        """offsets (B, J, 3) metres -> skeleton codes (B, N, d)."""
        return torch.stack([mlp(offsets[:, m].flatten(1)) for mlp, m in zip(self.mlps, self.members)], 1)


class AttentionLayer(nn.Module):
    """Pre-norm transformer layer whose attention is softmax(Q K^T / sqrt(d / heads) + U) V:
    tokens (S, K, d) and U (K, K) -> tokens (S, K, d)."""

    def __init__(self, width: int, heads: int):
        super().__init__()
        self.heads = heads
        self.norm_attention, self.norm_feedforward = nn.LayerNorm(width), nn.LayerNorm(width)
        self.qkv, self.out = nn.Linear(width, 3 * width), nn.Linear(width, width)
        self.feedforward = nn.Sequential(nn.Linear(width, 2 * width), nn.ReLU(), nn.Linear(2 * width, width))

    def forward(self, tokens: torch.Tensor, separation: torch.Tensor) -> torch.Tensor:
        """tokens (S, K, d) and separation U (K, K) -> tokens (S, K, d)."""
        q, k, v = self.qkv(self.norm_attention(tokens)).unflatten(-1, (3, self.heads, -1)).permute(2, 0, 3, 1, 4)
        attended = nn.functional.scaled_dot_product_attention(q, k, v, attn_mask=separation)   # (S, heads, K, d/heads)
        tokens = tokens + self.out(attended.transpose(1, 2).flatten(2))
        return tokens + self.feedforward(self.norm_feedforward(tokens))


class MotionEncoder(nn.Module):
    """Pose-aware attention (layers of masked self-attention over the N + J + 1 tokens of every
    frame) then two temporal convolutions per part: rotations (B, T, J, 6), root (B, T, 3) and
    skeleton codes (B, N, d) -> per-part latent codes (B, T, N, d)."""

    def __init__(self, parts: tuple[int, ...], width: int, heads: int, layers: int, kernel: int):
        super().__init__()
        joints = len(parts)
        self.joint_in = nn.Parameter(torch.randn(joints, 6, width) / 6 ** 0.5)  # one embedding per joint
        self.joint_bias = nn.Parameter(torch.zeros(joints, width))
        self.root_in = nn.Linear(ROOT_FEATURES, width)
        self.part_embedding = nn.Parameter(torch.randn(N, width) * 0.1)
        self.register_buffer("separation", separation_matrix(membership_matrix(torch.tensor(parts))), persistent=False)
        self.layers = nn.ModuleList(AttentionLayer(width, heads) for _ in range(layers))
        self.temporal = nn.Sequential(_conv(N * width, N * width, kernel, groups=N), nn.ReLU(),
                                      _conv(N * width, N * width, kernel, groups=N))

    def attend(self, rotations: torch.Tensor, root: torch.Tensor, codes: torch.Tensor) -> torch.Tensor:
        """(B, T, N + J + 1, d) tokens after the attention layers."""
        b, t = rotations.shape[:2]
        joints = torch.einsum("btjc,jcd->btjd", rotations, self.joint_in) + self.joint_bias
        parts = (codes + self.part_embedding)[:, None].expand(b, t, -1, -1)
        tokens = torch.cat([parts, joints, self.root_in(root)[:, :, None]], 2).flatten(0, 1)
        for layer in self.layers:
            tokens = layer(tokens, self.separation)
        return tokens.unflatten(0, (b, t))

    def forward(self, rotations: torch.Tensor, root: torch.Tensor, codes: torch.Tensor) -> torch.Tensor:
        """rotations (B, T, J, 6), root (B, T, 3), skeleton codes (B, N, d) -> latent (B, T, N, d)."""
        parts = self.attend(rotations, root, codes)[:, :, :N]                  # (B, T, N, d)
        return self.temporal(parts.flatten(2).transpose(1, 2)).transpose(1, 2).unflatten(2, (N, -1))


class MotionDecoder(nn.Module):
    """Fused codes (latent (B, T, N, d) + target skeleton codes (B, N, d)) -> rotations
    (B, T, J, 6) and root (B, T, 3) of the domain, through temporal convolutions."""

    def __init__(self, joints: int, width: int, hidden: int, kernel: int):
        super().__init__()
        self.joints = joints
        self.net = nn.Sequential(_conv(N * width, hidden, kernel), nn.ReLU(), _conv(hidden, hidden, kernel), nn.ReLU(),
                                 _conv(hidden, 6 * joints + ROOT_FEATURES, 1))

    def forward(self, latent: torch.Tensor, codes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """latent (B, T, N, d) and skeleton codes (B, N, d) -> (rotations (B, T, J, 6), root (B, T, 3)),
        normalised features."""
        out = self.net((latent + codes[:, None]).flatten(2).transpose(1, 2)).transpose(1, 2)
        return out[..., :6 * self.joints].unflatten(-1, (self.joints, 6)), out[..., 6 * self.joints:]


class Discriminator(nn.Module):
    """Strided temporal convolutions: rotations (B, T, J, 6) and root (B, T, 3) -> a realism
    score per stretch of frames (B, T / 4) (least-squares GAN: 1 real, 0 retargeted)."""

    def __init__(self, joints: int, hidden: int):
        super().__init__()
        self.net = nn.Sequential(nn.Conv1d(6 * joints + ROOT_FEATURES, hidden, 4, 2, 1), nn.LeakyReLU(0.2),
                                 nn.Conv1d(hidden, hidden, 4, 2, 1), nn.LeakyReLU(0.2), _conv(hidden, 1, 3))

    def forward(self, rotations: torch.Tensor, root: torch.Tensor) -> torch.Tensor:
        """rotations (B, T, J, 6) and root (B, T, 3) -> scores (B, T / 4)."""
        return self.net(torch.cat([rotations.flatten(2), root], -1).transpose(1, 2))[:, 0]


class Normalizer(nn.Module):
    """A domain's feature statistics and the mean rotation (wxyz) of its unmodelled joints."""

    def __init__(self, joints: int, others: int):
        super().__init__()
        self.register_buffer("rotation_mean", torch.zeros(joints, 6))
        self.register_buffer("rotation_std", torch.ones(joints, 6))
        self.register_buffer("root_mean", torch.zeros(ROOT_FEATURES))
        self.register_buffer("root_std", torch.ones(ROOT_FEATURES))
        self.register_buffer("other_rotations", torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(others, 1))

    def fit(self, rotations: torch.Tensor, root: torch.Tensor, other_rotations: torch.Tensor) -> None:
        """Statistics of features (..., J, 6) and (..., 3) (standard deviations at least 0.01)."""
        self.rotation_mean.copy_(rotations.flatten(0, -3).mean(0))
        self.rotation_std.copy_(rotations.flatten(0, -3).std(0).clamp_min(0.01))
        self.root_mean.copy_(root.flatten(0, -2).mean(0))
        self.root_std.copy_(root.flatten(0, -2).std(0).clamp_min(0.01))
        self.other_rotations.copy_(other_rotations)

    def normalize(self, rotations: torch.Tensor, root: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Features rotations (..., J, 6) and root (..., 3) (domains.to_features) -> the same
        shapes, less the mean and over the standard deviation."""
        return (rotations - self.rotation_mean) / self.rotation_std, (root - self.root_mean) / self.root_std

    def denormalize(self, rotations: torch.Tensor, root: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Inverse of :meth:`normalize`: rotations (..., J, 6) and root (..., 3), the same shapes."""
        return rotations * self.rotation_std + self.rotation_mean, root * self.root_std + self.root_mean


@dataclass
class RetargetConfig:
    """domains: the skeleton domains (DomainSpec or their dicts); width d of tokens and part codes;
    heads and layers of the attention; hidden: channels of decoders and discriminators; kernel:
    temporal convolution width, frames; window: frames of the training windows (longer clips
    are retargeted in windows of this length, humotion.retarget.learned)."""

    domains: list = field(default_factory=list)
    width: int = 32
    """Token and part-code width d."""
    heads: int = 2
    layers: int = 2
    hidden: int = 96
    """Channels of decoders and discriminators."""
    kernel: int = 5
    window: int = 64

    def __post_init__(self):
        self.domains = [d if isinstance(d, DomainSpec) else DomainSpec(**{k: tuple(v) if isinstance(v, list) else v
                                                                          for k, v in d.items()})
                        for d in self.domains]


class RetargetNet(nn.Module):
    """All networks of all domains (module docstring); .fps: the frame rate it works at."""

    def __init__(self, config: RetargetConfig):
        super().__init__()
        self.config, self.fps = config, 30.0
        c = config
        self.domains = {d.name: d for d in c.domains}
        self.skeleton_encoders = nn.ModuleDict({d.name: SkeletonEncoder(d.parts, c.width) for d in c.domains})
        self.encoders = nn.ModuleDict({d.name: MotionEncoder(d.parts, c.width, c.heads, c.layers, c.kernel)
                                       for d in c.domains})
        self.decoders = nn.ModuleDict({d.name: MotionDecoder(d.num_joints, c.width, c.hidden, c.kernel)
                                       for d in c.domains})
        self.discriminators = nn.ModuleDict({d.name: Discriminator(d.num_joints, c.hidden) for d in c.domains})
        self.normalizers = nn.ModuleDict({d.name: Normalizer(d.num_joints, len(d.others)) for d in c.domains})

    def retarget(self, source: str, rotations: torch.Tensor, root: torch.Tensor, source_offsets: torch.Tensor,
                 target: str, target_offsets: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Normalised features of domain `source` (B, T, J_s, 6), (B, T, 3) on bodies with offsets
        (B, J_s, 3) -> normalised features of domain `target` (B, T, J_t, 6), (B, T, 3) on bodies
        with offsets (B, J_t, 3)."""
        latent = self.encoders[source](rotations, root, self.skeleton_encoders[source](source_offsets))
        return self.decoders[target](latent, self.skeleton_encoders[target](target_offsets))


def save_retarget_net(net: RetargetNet, path, **extra) -> None:
    """Write the weights, config and frame rate (humotion.model_files)."""
    save_model_file(net, path, fps=net.fps, **extra)


def load_retarget_net(path) -> RetargetNet:
    """A RetargetNet in eval mode from a file of save_retarget_net or a training checkpoint."""
    return load_model_file(path, RetargetNet, RetargetConfig)

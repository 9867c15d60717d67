"""Pose-space deformation of the body model: pose-dependent corrective offsets of the rest mesh.

Pose features are the rotation matrices minus the identity of every joint but the root (whose
rotation is the body's global orientation), 9 numbers per joint, zero at the rest pose. They are
split into four groups, head (neck and above), body, left hand and right hand (the finger and
metacarpal bones of each hand), and each group goes through the same ReLU layer: the group's
features are the full feature vector with the other groups' entries zeroed, so one weight matrix
and bias serve all four, and nothing inside the layer mixes groups. The four hidden vectors are
summed and a linear regressor maps the sum to per-vertex offsets (zero at the rest pose: the
hidden layer's response to zero features is subtracted). Offsets scale with the body's height
relative to the template's (a child's elbow bulges less than an adult's).

    correctives = PoseCorrectives(num_vertices, joint_names, parents, hidden=32)
    offsets = correctives(rotations, scale)        # (B, J, 3, 3), (B,) -> (B, V, 3)
    factors = correctives.factors(rotations, scale)   # (B, hidden): offsets = factors @ weight.T
"""

from __future__ import annotations

import torch
from torch import nn

GROUPS = ("head", "body", "left_hand", "right_hand")


def pose_groups(joint_names, parents) -> torch.Tensor:
    """(4, J) float masks of GROUPS; the root belongs to none. Head: neck01 and its subtree;
    hands: finger* and metacarpal* bones of each side; body: the rest."""
    names = list(joint_names)
    parents = [int(p) for p in parents]
    head = {names.index("neck01")} if "neck01" in names else set()
    for j, p in enumerate(parents):
        if p in head:
            head.add(j)
    masks = torch.zeros(len(GROUPS), len(names))
    for j, name in enumerate(names):
        if parents[j] < 0:
            continue
        if j in head:
            masks[0, j] = 1
        elif name.startswith(("finger", "metacarpal")) and name.endswith(".L"):
            masks[2, j] = 1
        elif name.startswith(("finger", "metacarpal")) and name.endswith(".R"):
            masks[3, j] = 1
        else:
            masks[1, j] = 1
    return masks


def pose_features(rotations: torch.Tensor) -> torch.Tensor:
    """(B, J, 3, 3) local rotation matrices -> (B, J, 9) R - I."""
    eye = torch.eye(3, dtype=rotations.dtype, device=rotations.device)
    return (rotations - eye).flatten(-2)


class PoseCorrectives(nn.Module):
    """Grouped pose features -> shared ReLU layer -> sum -> linear regressor -> (B, V, 3)."""

    unit = 0.005
    """Metres per unit of the regressor's output (keeps its weights near 1 for mm-size offsets)."""

    def __init__(self, num_vertices: int, joint_names, parents, hidden: int):
        super().__init__()
        self.num_vertices = num_vertices
        self.register_buffer("groups", pose_groups(joint_names, parents))
        num_joints = len(list(joint_names))
        self.layer = nn.Linear(9 * num_joints, hidden)
        self.regressor = nn.Linear(hidden, 3 * num_vertices, bias=False)
        nn.init.zeros_(self.regressor.weight)

    def hidden(self, rotations: torch.Tensor) -> torch.Tensor:
        """(B, J, 3, 3) -> (B, hidden): the sum over groups of the shared ReLU layer's output,
        minus its value at the rest pose."""
        features = pose_features(rotations)  # (B, J, 9)
        grouped = (features[:, None] * self.groups[None, :, :, None]).flatten(-2)  # (B, 4, 9J)
        at_rest = len(GROUPS) * torch.relu(self.layer.bias)
        return torch.relu(self.layer(grouped)).sum(1) - at_rest

    def targets(self) -> torch.Tensor:
        """(hidden, V, 3) the offsets (metres, template size) each hidden unit adds per unit of its
        value: the correctives are hidden(rotations) times these (glTF morph targets)."""
        return (self.unit * self.regressor.weight.T).unflatten(-1, (self.num_vertices, 3))

    def factors(self, rotations: torch.Tensor, scale: torch.Tensor | None = None) -> torch.Tensor:
        """(B, J, 3, 3) rotations, (B,) scale (None: 1) -> (B, hidden): hidden(rotations) times
        unit times scale, what the regressor's weight (3 V, hidden) multiplies into offsets (m)."""
        return self.hidden(rotations) * (self.unit if scale is None else self.unit * scale[:, None])

    def forward(self, rotations: torch.Tensor, scale: torch.Tensor | None = None) -> torch.Tensor:
        """(B, J, 3, 3) rotations, (B,) scale (None: 1) -> offsets (B, V, 3) (m): hidden(rotations)
        times targets() times scale. (The body model's forward pass multiplies factors() by the
        regressor's weight block by block of vertices instead.)"""
        return (self.factors(rotations, scale) @ self.regressor.weight.T).unflatten(-1, (self.num_vertices, 3))

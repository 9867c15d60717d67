"""A nearest-neighbour baseline for sparse tracking: look the headset frame up among the
training frames and average the poses found (issue 27's measure of what the network adds).

    index = KnnPoser.from_training(k=64)          # the network's training split, 30 fps
    out = index(signals)                          # a SparseOutput, as SparsePoser gives: out.rotations, ...

Features of a frame (:func:`knn_features`, z-normalised over the index, Euclidean distance):
the eye height (1); the head's pitch and roll as the horizontal components of its up axis in
its heading frame (2); each wrist's position relative to the eyes and its rotation (6D) in the
head's heading frame (yaw only, swing-twist; 2 x 9); the displacement of the eyes and of each
wrist over the last 4 and 8 frames (0.13 s and 0.27 s at 30 fps), in the current heading frame
(2 x 9). 39 numbers. Within a stream's first frames the displacement is taken from its first
frame.

A frame's answer: the mean of its k nearest training frames' poses. Local joint rotations are
averaged as rotation matrices and projected back onto SO(3) (SVD, the chordal L2 mean); the
root's orientation and its position relative to the eyes are taken in each neighbour's heading
frame and turned into the query's, so the root height and the body's lean come from the
neighbours. The evaluation then anchors the body's eyes to the headset, as for the network.

Hands in HT: a hand that is not seen keeps its last seen world pose (as the "hold last hand"
row feeds the network), so its features are those of the held pose seen from the current head
(and its displacements shrink to the head's own); before a hand is first seen its features are
the index's mean (0 after z-normalisation).

Search is exact: brute-force squared distances in chunks (torch), k smallest.
"""

from __future__ import annotations

import torch

from humotion import rotations as rot
from humotion.motion import Motion
from humotion.sparse import signals as sg
from humotion.sparse.model import SparseOutput, heading, sixd_to_matrix

K = 64
LAGS = (8,)
"""Displacement lags in frames at the index's frame rate (0.27 s at 30 fps; lags 4 and 8 together
scored 0.1-0.2 cm worse on four clips of each test set)."""
HAND_FEATURES = ((3, 12), (12, 21))
"""Feature columns of the left and right wrist (position, 6D) in knn_features' layout."""


def knn_features(rotations: torch.Tensor, positions: torch.Tensor, lags=LAGS) -> tuple[torch.Tensor, torch.Tensor]:
    """Features of every frame of a stream and its heading frames.

    rotations (T, 3, 3, 3), positions (T, 3, 3): world poses of the DEVICES (eyes, wrists), metres.
    Returns (features (T, 3 + 18 + 9 * len(lags)) float32 in the module docstring's order,
    heading rotations (T, 3, 3) of the head)."""
    rotations, positions = rotations.float(), positions.float()
    yaw = heading(rotations[:, 0])                                           # (T, 3, 3)
    to_heading = yaw.transpose(-1, -2)
    head_up = (to_heading @ rotations[:, 0])[:, :, 1]                        # (T, 3) up axis
    hands = []
    for k in (1, 2):
        position = (to_heading @ (positions[:, k] - positions[:, 0])[..., None])[..., 0]
        hands.append(torch.cat([position, rot.convert(to_heading @ rotations[:, k], "matrix", "sixd")], -1))
    moves = []
    t = torch.arange(len(positions))
    for lag in lags:
        before = positions[(t - lag).clamp(min=0)]                          # (T, 3, 3)
        moves.append((to_heading[:, None] @ (positions - before)[..., None])[..., 0].flatten(1))
    features = torch.cat([positions[:, 0, 1:2], head_up[:, [0, 2]], *hands, *moves], -1)
    return features, yaw


def _project_to_rotation(m: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) nearest rotation matrices (SVD, determinant +1)."""
    u, _, vh = torch.linalg.svd(m)
    d = torch.det(u @ vh)
    u = torch.cat([u[..., :2], u[..., 2:] * d[..., None, None]], -1)
    return u @ vh


class KnnPoser:
    """k-nearest-neighbour lookup over training frames (module docstring). Called like a
    SparsePoser on an unbatched signals dict ((T, 9) components, (T, 2) visible); .fps is the
    frame rate of the indexed frames."""

    def __init__(self, features: torch.Tensor, rotations: torch.Tensor, root_offsets: torch.Tensor,
                 fps: float, k: int = K, lags=LAGS):
        """features (N, D) raw; rotations (N, 22, 3, 3) local, the root's in the head's
        heading frame; root_offsets (N, 3) the root relative to the eyes in that frame."""
        self.mean, self.std = features.mean(0), features.std(0).clamp(min=1e-6)
        self.features = (features - self.mean) / self.std
        self.rotations, self.root_offsets, self.fps, self.k = rotations, root_offsets, float(fps), k
        self.lags = tuple(lags)

    @classmethod
    def from_motions(cls, motions: list[Motion], k: int = K, lags=LAGS) -> KnnPoser:
        """The index over every frame of canonical motions (all at one frame rate); lags: the
        displacement lags in frames."""
        features, rotations, offsets = [], [], []
        for motion in motions:
            world_r, world_p = motion.world()
            r, p = sg.device_poses(world_r, world_p, sg.eye_offset(motion.skeleton))
            f, yaw = knn_features(r, p, lags)
            to_heading = yaw.transpose(-1, -2)
            local = motion.rotations_as("matrix").float().clone()
            local[:, 0] = to_heading @ local[:, 0]
            features.append(f)
            rotations.append(local)
            offsets.append((to_heading @ (motion.root_positions.float() - p[:, 0].float())[..., None])[..., 0])
        return cls(torch.cat(features), torch.cat(rotations), torch.cat(offsets), motions[0].fps, k, lags)

    @classmethod
    def from_training(cls, k: int = K, config=None, lags=LAGS) -> KnnPoser:
        """The index over the frames of the shipped default network's training data: config a
        humotion.sparse.train.TrainConfig (default: the model card's split, exclusions and 30 fps)."""
        from humotion.training import load_windows
        from humotion.sparse.train import TrainConfig

        config = config or TrainConfig(exclude=("hdm05_jointlearning", "cmu_iclone_ccskeleton"))
        windows = load_windows(config, config.train_split, config.stride)
        return cls.from_motions(windows.motions, k, lags)

    def neighbours(self, query: torch.Tensor, chunk: int = 256) -> torch.Tensor:
        """(Q, k) indices of the k nearest index frames of z-normalised queries (Q, D)."""
        squared = (self.features ** 2).sum(-1)
        found = []
        for part in query.split(chunk):
            distance = squared[None] - 2 * part @ self.features.T                 # + |q|^2, same per row
            found.append(distance.topk(self.k, dim=-1, largest=False).indices)
        return torch.cat(found)

    def device_poses(self, signals: dict) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(rotations (T, 3, 3, 3), positions (T, 3, 3), ever_seen (T, 2)) of the devices from
        signals, an unseen hand holding its last seen pose."""
        from humotion.sparse.evaluation import hold_last_seen

        visible = signals["visible"] > 0.5
        safe = {}
        for i, name in enumerate(sg.DEVICES):
            x = signals[name].float()
            seen = torch.ones(len(x), dtype=torch.bool) if i == 0 else visible[:, i - 1]
            x = torch.where(seen[:, None], torch.nan_to_num(x), x.new_tensor([1, 0, 0, 0, 1, 0, 0, 0, 0]))
            safe[name] = x
        rotations = torch.stack([sixd_to_matrix(safe[n][:, :6]) for n in sg.DEVICES], 1)
        positions = torch.stack([safe[n][:, 6:9] for n in sg.DEVICES], 1)
        return hold_last_seen(rotations, positions, visible)

    def __call__(self, signals: dict) -> SparseOutput:
        """signals: unbatched (T, ...) dict. Returns a SparseOutput of rotations (T, 22, 3, 3)
        local (root global) and root_positions (T, 3) in the world frame, metres."""
        if signals["head"].dim() != 2:
            raise ValueError("KnnPoser takes one stream: signals of shape (T, 9), not batched")
        rotations, positions, held = self.device_poses(signals)
        features, yaw = knn_features(rotations, positions, self.lags)
        query = (features - self.mean) / self.std
        for hand, (start, stop) in enumerate(HAND_FEATURES):
            never = ~held[:, hand]
            query[never, start:stop] = 0.0
            for i in range(len(self.lags)):                                          # that hand's displacements
                column = 21 + 9 * i + 3 * (hand + 1)
                query[never, column:column + 3] = 0.0
        index = self.neighbours(query)                                           # (T, k)
        local = _project_to_rotation(self.rotations[index].mean(1))             # (T, 22, 3, 3)
        local[:, 0] = yaw @ local[:, 0]
        offset = self.root_offsets[index].mean(1)
        root = positions[:, 0] + (yaw @ offset[..., None])[..., 0]
        return SparseOutput(local, root)

"""Training windows of the learned retargeter: the clips of one skeleton domain as features.

    windows = DomainWindows.from_motions(spec, motions, length=64, stride=8, fps=30.0)
    batch = windows.batch([0, 5, 9])     # dict of tensors, see DomainWindows.batch

Each clip is read once (domains.read_motion) at the training frame rate, optionally with its
mirror image as a second clip (left and right exchanged, a mirrored body), and cut where the
pelvis jumps (faster than JUMP_SPEED between two frames: the game-rig takes begin with a frame
left at another place); a window is a (clip piece, start frame) pair whose features are made
when it is fetched, in the frame of its own first frame (domains.to_features).
"""

from __future__ import annotations

import torch

from humotion.motion import Motion
from humotion.retarget.domains import Body, DomainSpec, read_motion, to_features
from humotion.retarget.rig import Rig

JUMP_SPEED = 15.0
"""Metres per second: a pelvis moving faster between two frames is a cut in the take, not motion."""


def pieces(pelvis: torch.Tensor, fps: float) -> list[tuple[int, int]]:
    """[start, end) frame ranges of a (T, 3) pelvis trajectory between its jumps."""
    jumps = torch.nonzero((pelvis[1:] - pelvis[:-1]).norm(dim=-1) * fps > JUMP_SPEED)[:, 0] + 1
    edges = [0, *jumps.tolist(), len(pelvis)]
    return list(zip(edges[:-1], edges[1:]))


class DomainWindows:
    """Windows of `length` frames at `fps`, one every `stride` frames, from motions of one domain.

    rotations / pelvis: per clip piece (T, J, 3, 3) and (T, 3) (domains.read_motion); bodies: the
    distinct bodies (domains.Body); body_of: per piece its index into bodies; index: (piece,
    start) of every window.
    """

    def __init__(self, spec: DomainSpec, length: int, fps: float):
        self.spec, self.length, self.fps = spec, length, fps
        self.rotations: list[torch.Tensor] = []
        self.pelvis: list[torch.Tensor] = []
        self.bodies: list[Body] = []
        self.body_of: list[int] = []
        self.index: list[tuple[int, int]] = []

    @classmethod
    def from_motions(cls, spec: DomainSpec, motions: list[Motion], length: int, stride: int, fps: float,
                     mirror: bool = False) -> "DomainWindows":
        """Windows of motions on skeletons of the domain (and of their mirror images when mirror)."""
        windows = cls(spec, length, fps)
        known: dict[bytes, int] = {}
        for motion in motions:
            for version in (motion, motion.mirrored()) if mirror else (motion,):
                version = version.resample(fps)
                rotations, pelvis = read_motion(version, spec)
                for start, end in pieces(pelvis, fps):
                    if end - start < length:
                        continue
                    key = version.skeleton.offsets.numpy().tobytes()
                    if key not in known:
                        known[key] = len(windows.bodies)
                        windows.bodies.append(Body.of(spec, Rig.of(version.skeleton, label=version.name)))
                    clip = len(windows.rotations)
                    windows.rotations.append(rotations[start:end])
                    windows.pelvis.append(pelvis[start:end])
                    windows.body_of.append(known[key])
                    windows.index += [(clip, s) for s in range(0, end - start - length + 1, stride)]
        if not windows.index:
            raise ValueError(f"no clip of domain {spec.describe()} is {length} frames long at {fps:g} fps")
        return windows

    def __len__(self) -> int:
        return len(self.index)

    def batch(self, items) -> dict[str, torch.Tensor]:
        """Windows `items` as features: rotations (B, T, J, 6), root (B, T, 3) (domains.to_features),
        and their bodies: offsets (B, J, 3), height and hip_height (B,) metres."""
        clips, starts = zip(*(self.index[int(i)] for i in items))
        rotations = torch.stack([self.rotations[c][s:s + self.length] for c, s in zip(clips, starts)])
        pelvis = torch.stack([self.pelvis[c][s:s + self.length] for c, s in zip(clips, starts)])
        bodies = [self.bodies[self.body_of[c]] for c in clips]
        hip = torch.tensor([b.hip_height for b in bodies])
        features, root, _, _ = to_features(rotations, pelvis, torch.stack([b.facing for b in bodies]), hip, self.fps)
        return {"rotations": features, "root": root, "offsets": torch.stack([b.offsets for b in bodies]),
                "height": torch.tensor([b.height for b in bodies]), "hip_height": hip}

"""A Gaussian pose prior G(theta; mu, Sigma) learned from motion capture (specs/video-capture.md,
E_prior of the refinement).

theta is a body pose on the canonical skeleton without its global orientation: the 21 local
joint rotations below the pelvis as rotation vectors (radians), flattened to 63 numbers.
E_prior = -log G(theta) up to a constant = 0.5 (theta - mu)^T Sigma^-1 (theta - mu), so one unit
of energy is one squared standard deviation (Mahalanobis) over all directions together.

    prior = fit_pose_prior(motions)                # canonical motions (training subjects only)
    prior.save("pose_prior.npz"); prior = PosePrior.load(path)
    energy = prior.energy(rotvecs)                 # rotvecs (..., 22, 3) -> (...)

The shipped prior (humotion/assets/capture/pose_prior.npz) is made by `humotion train prior`, or
in Python by train_prior(PriorTrainConfig()): fitted on the training subjects' mocap and saved.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from humotion import rotations as rot
from humotion.assets import ASSETS
from humotion.canonical import JOINTS
from humotion.training import DEFAULT_DATA, EVALUATION_ONLY

SHIPPED_PRIOR = ASSETS / "capture" / "pose_prior.npz"
DIMENSIONS = 3 * (len(JOINTS) - 1)


@dataclass
class PosePrior:
    """mean: (63,) radians; precision: (63, 63) the inverse covariance (radians^-2); frames: how
    many poses it was fitted on."""

    mean: torch.Tensor
    precision: torch.Tensor
    frames: int

    def energy(self, rotvecs: torch.Tensor) -> torch.Tensor:
        """(...) 0.5 * squared Mahalanobis distance of poses rotvecs (..., 22, 3) (joint 0, the
        global orientation, is ignored). Differentiable."""
        if rotvecs.shape[-2:] != (len(JOINTS), 3):
            raise ValueError(f"poses must be (..., {len(JOINTS)}, 3) rotation vectors, got {tuple(rotvecs.shape)}")
        x = rotvecs[..., 1:, :].flatten(-2) - self.mean.to(rotvecs.dtype)
        return 0.5 * ((x @ self.precision.to(rotvecs.dtype)) * x).sum(-1)

    def save(self, path: str | Path) -> None:
        np.savez(path, mean=self.mean.numpy(), precision=self.precision.numpy(), frames=self.frames)

    @classmethod
    def load(cls, path: str | Path = SHIPPED_PRIOR) -> PosePrior:
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"no pose prior at {path}: make one with `humotion train prior`")
        with np.load(path) as data:
            mean, precision = data["mean"], data["precision"]
            if mean.shape != (DIMENSIONS,) or precision.shape != (DIMENSIONS, DIMENSIONS):
                raise ValueError(f"{path}: a pose prior needs mean ({DIMENSIONS},) and precision "
                                 f"({DIMENSIONS}, {DIMENSIONS}), got {mean.shape} and {precision.shape}")
            return cls(torch.as_tensor(mean, dtype=torch.float32), torch.as_tensor(precision, dtype=torch.float32),
                       int(data["frames"]))


def fit_pose_prior(rotations: torch.Tensor, ridge: float = 1e-3) -> PosePrior:
    """The Gaussian of poses rotations: (T, 22, 4) local wxyz quaternions on the canonical skeleton
    (joint 0 ignored). ridge (radians^2) is added to the covariance's diagonal so directions the
    data never moves in (e.g. a hinge's sideways bend) stay finite but expensive."""
    if rotations.dim() != 3 or rotations.shape[1:] != (len(JOINTS), 4):
        raise ValueError(f"rotations must be (T, {len(JOINTS)}, 4) quaternions, got {tuple(rotations.shape)}")
    if len(rotations) < DIMENSIONS:
        raise ValueError(f"a pose prior needs at least {DIMENSIONS} frames, got {len(rotations)}")
    x = rot.convert(rotations[:, 1:].double(), "quat", "rotvec").flatten(1)
    mean = x.mean(0)
    covariance = torch.cov(x.T) + ridge * torch.eye(DIMENSIONS, dtype=x.dtype)
    return PosePrior(mean.float(), torch.linalg.inv(covariance).float(), len(x))


def poses_from_collection(root: str | Path, fps: float = 10.0, exclude=(), progress: bool = True) -> torch.Tensor:
    """(T, 22, 4) canonical poses of the training subjects under a mocap tree, each clip at fps and
    mirrored too (so the prior is left/right symmetric). The split is MotionCollection.split() of
    the whole tree, as for every humotion model; sources in exclude and the evaluation-only ones
    (humotion.training.EVALUATION_ONLY) are left out."""
    from tqdm.auto import tqdm

    from humotion.canonical import to_canonical
    from humotion.data import MotionCollection

    everything = MotionCollection.load(root, progress=progress)
    train = everything.filter(subjects=everything.split()["train"]).filter(exclude=(*exclude, *EVALUATION_ONLY))
    poses = []
    for clip in tqdm(train.clips, desc="poses", unit="clip", disable=not progress):
        motion = to_canonical(clip.load()).resample(fps)
        poses += [motion.rotations, motion.mirrored().rotations]
    return torch.cat(poses)


@dataclass
class PriorTrainConfig:
    """How `humotion train prior` fits the pose prior (each field's docstring is its command-line
    help): which mocap, at what rate, with what ridge, written where."""

    data_root: str = str(DEFAULT_DATA)
    """Mocap folder tree."""
    out: str = str(SHIPPED_PRIOR)
    """Output .npz file."""
    fps: float = 10.0
    """Poses sampled per second of motion."""
    exclude: tuple[str, ...] = (*EVALUATION_ONLY, "cmu_iclone_ccskeleton")
    """Leave these source folders out (repeatable; hdm05_jointlearning is evaluation-only, and
    cmu_iclone_ccskeleton holds game-rig copies of CMU takes)."""
    ridge: float = 1e-3
    """Added to the covariance's diagonal (radians^2): directions the data never moves in stay
    finite but expensive."""
    progress: bool = True
    """Show progress bars."""


def train_prior(config: PriorTrainConfig) -> PosePrior:
    """The pose prior fitted on config's mocap (poses_from_collection, then fit_pose_prior), saved
    to config.out (its folder made when missing)."""
    rotations = poses_from_collection(config.data_root, config.fps, config.exclude, config.progress)
    prior = fit_pose_prior(rotations, config.ridge)
    Path(config.out).parent.mkdir(parents=True, exist_ok=True)
    prior.save(config.out)
    return prior

"""Training the lifting network on mocap filmed by virtual cameras: ``humotion train lift --help``.

    from humotion.capture.train_lift import LiftTrainConfig, train
    summary = train(LiftTrainConfig(out_dir="runs/lift", steps=5000))

Data: the CMU sources of ../shared/data/mocap (hdm05_jointlearning is evaluation-only and left
out), split by subject (MotionCollection.split), on the canonical body at `fps`, cut into windows
of model.window + targets - 1 frames (the cached windows of humotion.training.load_windows).
Each window is mirrored at random, filmed by a random virtual camera and spoilt by the detector
noise model (humotion.capture.lift_data.make_lift_batch); the network lifts `targets` frames of
it. Validation: the validation subjects' windows, filmed and spoilt with a fixed seed, so every
validation sees the same inputs.

Loss: MPJPE in units of standing height, the mean distance between predicted and true joints
(22 joints, pelvis-relative, the pelvis itself always exact). Metrics: the same in millimetres
(times each skeleton's height) before (mpjpe_mm) and after (pa_mpjpe_mm) a Procrustes alignment
(rotation, scale, translation per frame). No bone-length or velocity terms: bone lengths are
replaced by the template's after the network (humotion.capture.joint_angles), and the temporal
window already smooths the output. Adam with the learning rate decaying by lr_decay per epoch, as
in VideoPose3D (Pavllo et al. 2019).

Output folder and resume: as every training command (humotion.training): checkpoints,
log.jsonl, lifter.pt (final weights + config, for humotion.capture.lifting.load_lifter) and
lifter_best.pt (lowest validation loss).
Several GPUs: ``torchrun --nproc_per_node=N -m humotion.capture.command --device cuda ...``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from humotion.capture.keypoints import CameraRanges, DetectorNoise
from humotion.capture.lift_data import LiftFrames, make_lift_batch
from humotion.capture.lifting import Lifter, LiftingConfig, procrustes_align, save_lifter
from humotion.training import RunConfig, Session, fit, load_run_windows

VALIDATION_SEED = 12345


@dataclass
class LiftTrainConfig(RunConfig):
    """Everything a lifting training run needs; saved in every checkpoint. The run settings (data,
    split, steps, seed, device, files) are humotion.training.RunConfig's; here also:

    targets: frames lifted per training window (the window has model.window + targets - 1
    frames); stride: frames between training windows (validation windows do not overlap their
    targets). lr_decay: learning-rate factor per epoch. mirror: chance of mirroring a window.
    arm_raise: chance of each arm being raised sideways in a window (lift_data.raise_arms).
    noise, cameras: the detector noise and virtual cameras (humotion.capture.keypoints).
    model: the network's sizes and whether it is causal.
    """

    out_dir: str = "runs/lift"
    batch_size: int = 128
    epochs: int = 60
    targets: int = 16
    """Frames lifted per training window."""
    stride: int = 8
    """Frames between training windows."""
    lr_decay: float = 0.95
    """Learning-rate factor per epoch."""
    mirror: float = 0.5
    arm_raise: float = 0.3
    """Chance of each arm being raised sideways per window."""
    noise: DetectorNoise = field(default_factory=DetectorNoise)
    cameras: CameraRanges = field(default_factory=CameraRanges)
    model: LiftingConfig = field(default_factory=LiftingConfig)

    def __post_init__(self):
        if isinstance(self.model, dict):
            self.model = LiftingConfig(**self.model)
        if isinstance(self.noise, dict):
            self.noise = DetectorNoise(**{k: tuple(v) if isinstance(v, list) else v for k, v in self.noise.items()})
        if isinstance(self.cameras, dict):
            values = {k: tuple(v) if isinstance(v, list) else v for k, v in self.cameras.items()}
            values["sizes"] = tuple(tuple(size) for size in values.get("sizes", CameraRanges.sizes))
            self.cameras = CameraRanges(**values)
        if self.targets < 1:
            raise ValueError(f"targets must be at least 1 frame, got {self.targets}")

    @property
    def length(self) -> int:
        """Frames per training window."""
        return self.model.window + self.targets - 1


def lift_loss(pred: torch.Tensor, target: torch.Tensor, target_frame: int) -> torch.Tensor:
    """MPJPE (units of standing height) of pred (B, K, 22, 3) against the frames of target
    (B, L, 22, 3) they lift: target_frame (the model's config.target) onwards."""
    return (pred - target[:, target_frame:target_frame + pred.shape[1]]).norm(dim=-1).mean()


@torch.no_grad()
def validate(model: Lifter, frames: LiftFrames, config: LiftTrainConfig, device: torch.device) -> dict[str, float]:
    """{"loss": MPJPE in height units, "mpjpe_mm", "pa_mpjpe_mm"} over every validation window,
    filmed and spoilt with VALIDATION_SEED (the same inputs at every validation), not mirrored."""
    model.eval()
    generator = torch.Generator().manual_seed(VALIDATION_SEED)
    sums = {"loss": 0.0, "mpjpe_mm": 0.0, "pa_mpjpe_mm": 0.0}
    for start in range(0, len(frames), config.batch_size):
        joints, keypoints, height = frames.window_points(range(start, min(start + config.batch_size, len(frames))))
        inputs, target = make_lift_batch(joints, keypoints, height, generator, config.noise, config.cameras, mirror=0.0)
        pred = model(inputs.to(device)).cpu()
        true = target[:, config.model.target:config.model.target + pred.shape[1]]
        metres = height[:, None, None] * 1000
        count = len(height)
        sums["loss"] += float(lift_loss(pred, target, config.model.target)) * count
        sums["mpjpe_mm"] += float(((pred - true).norm(dim=-1) * metres).mean()) * count
        sums["pa_mpjpe_mm"] += float(((procrustes_align(pred, true) - true).norm(dim=-1) * metres).mean()) * count
    return {k: v / max(len(frames), 1) for k, v in sums.items()}


def train(config: LiftTrainConfig) -> dict:
    """Train (or resume) a Lifter; returns a summary dict (step, losses, validation, files)."""
    session = Session(config)
    train_windows, val_windows = load_run_windows(session, config.stride, config.targets)
    train_frames = LiftFrames(train_windows)
    val_frames = LiftFrames(val_windows) if val_windows else None
    device = session.device
    model = Lifter(config.model).to(device)
    model.fps = config.fps
    optimizer = torch.optim.Adam(model.parameters(), lr=config.lr)
    steps_per_epoch = math.ceil(math.ceil(len(train_frames) / session.world) / config.batch_size)

    def batches(epoch: int, skip: int):
        order = session.epoch_indices(len(train_frames), epoch)
        for start in range(skip * config.batch_size, len(order), config.batch_size):
            yield make_lift_batch(*train_frames.window_points(order[start:start + config.batch_size]),
                                  session.generator, config.noise, config.cameras, config.mirror, config.arm_raise)

    def loss(model, batch):
        inputs, target = (x.to(device) for x in batch)
        return lift_loss(model(inputs), target, config.model.target), {}

    return fit(
        session, model, optimizer, steps_per_epoch=steps_per_epoch, batches=batches, loss=loss,
        validate=(lambda module: validate(module, val_frames, config, device)) if val_frames else None,
        save_weights=save_lifter, weights_name="lifter",
        describe=lambda val: (f"val {val['loss']:.4f} (MPJPE {val['mpjpe_mm']:.0f} mm, "
                              f"PA-MPJPE {val['pa_mpjpe_mm']:.0f} mm)"),
        lr_at=lambda step: config.lr * config.lr_decay ** (step / steps_per_epoch))

"""Training SparsePoser on mocap windows (the command: ``humotion train sparse --help``).

    from humotion.sparse.train import TrainConfig, train
    summary = train(TrainConfig(out_dir="runs/sparse", epochs=20))

Data: the CMU sources of ../shared/data/mocap (hdm05_jointlearning is evaluation-only and left
out), split by subject (MotionCollection.split), cut into windows of `length` frames at `fps` on
the canonical 22-joint body (the to_canonical conversion is cached, see humotion.training.load_windows).
Each training window is mirrored (p = 0.5), turned by a random yaw and scaled by s ~ U(0.85,
1.15) (offsets and root trajectory); its headset signals are synthesised from forward
kinematics, in the controller scenario (MC: hands always seen) or hand tracking (HT: hands seen
inside the headset frustum, minus random tracking losses), drawn per window for "mixed".
Your own data: ``--data`` may be a folder of AMASS .npz files (SMPL-H parameters, split by
subject folder; docs/amass.md), read with the subject's own bone lengths when ``--smplh-model``
names a SMPL-H model file (humotion.io.amass).

Output folder and resume: as every training command (humotion.training): checkpoints,
log.jsonl, sparse_poser.pt (final weights + config, small, for
:func:`humotion.sparse.model.load_sparse_model`) and sparse_poser_best.pt (best validation).
Several GPUs: ``torchrun --nproc_per_node=N -m humotion.sparse.command --device cuda ...``
(DistributedDataParallel, DistributedSampler; rank 0 writes the files).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field

import torch

from humotion.io.amass import using_body_model
from humotion.sparse.batches import AugmentedWindows, make_batch
from humotion.sparse.losses import loss_weights, predicted_world, sparse_loss
from humotion.sparse.metrics import mpjpe, mpjre
from humotion.sparse.model import SparseConfig, SparsePoser, load_sparse_model, save_sparse_model
from humotion.sparse.signals import Dropout, Frustum
from humotion.training import DEFAULT_DATA, RunConfig, Session, checkpoints, fit, learning_rate, load_run_windows

__all__ = ["TrainConfig", "train", "validate", "checkpoints", "DEFAULT_DATA"]

SCENARIO_CHOICES = ("HT", "MC", "mixed")


@dataclass
class TrainConfig(RunConfig):
    """Everything a SparsePoser training run needs; saved in every checkpoint. The run settings
    (data, split, steps, seed, device, files) are humotion.training.RunConfig's; here also the
    fields below (each field's docstring is its command-line help). weights: loss term -> weight
    (0 switches a term off). scale_range, mirror: augmentation (batches.AugmentedWindows).
    ht_fraction: the chance of HT per window in the 'mixed' scenario.
    """

    out_dir: str = "runs/sparse"
    length: int = 40
    """Window length, frames (validation windows: one per `length` frames)."""
    stride: int = 10
    """Frames between training windows."""
    scenario: str = "mixed"
    """MC: hands always seen; HT: seen inside the headset frustum; mixed: drawn per window."""
    ht_fraction: float = 0.5
    fov_deg: float = 120.0
    """Hand-tracking field of view (horizontal = vertical), degrees."""
    tracking_loss_per_s: float = 0.2
    """Random hand-tracking losses per second in HT (0: none)."""
    scale_range: tuple[float, float] = (0.85, 1.15)
    mirror: float = 0.5
    speed_range: tuple[float, float] = (1.0, 1.0)
    """Play each training window at a random speed in this range (log-uniform; 1 1: as captured, how the shipped
    networks were trained)."""
    weights: dict = field(default_factory=loss_weights)
    position_weight: float = 1.0
    """Weight of joint positions (metres) in the se3 and aux losses (1 in the reference)."""
    model: SparseConfig = field(default_factory=SparseConfig)
    workers: int = 0
    """DataLoader worker processes."""
    lr_final: float | None = None
    """Decay the learning rate from --lr to this along a cosine over the run (None: constant, how the shipped
    networks were trained)."""
    smplh_model: str | None = None
    """SMPL-H model .npz (J_regressor, v_template, shapedirs, kintree_table): AMASS subjects' bone lengths from their
    betas (None: the canonical proportions; humotion.io.amass)."""
    init_weights: str | None = None
    """Start from these SparsePoser weights (same sizes; fine-tuning; the optimizer starts afresh) instead of random
    ones; a checkpoint in the output folder still takes precedence (resume)."""

    def __post_init__(self):
        if isinstance(self.model, dict):
            self.model = SparseConfig(**self.model)
        if self.scenario not in SCENARIO_CHOICES:
            raise ValueError(f"scenario must be one of {SCENARIO_CHOICES}, got {self.scenario!r}")
        self.weights = loss_weights(**self.weights)
        if self.model.mask_token == "fixed":
            self.weights["forecast"] = 0.0  # a fixed token forecasts nothing

    @property
    def frustum(self) -> Frustum:
        return Frustum(self.fov_deg, self.fov_deg)

    @property
    def dropout(self) -> Dropout | None:
        return Dropout(self.tracking_loss_per_s) if self.tracking_loss_per_s > 0 else None

    def ht_probability(self) -> float:
        return {"HT": 1.0, "MC": 0.0}.get(self.scenario, self.ht_fraction)


# -- validation ----------------------------------------------------------------------------

@torch.no_grad()
def validation_means(model, windows, config: TrainConfig, device: torch.device, measure) -> dict[str, float]:
    """measure(model, batch, inputs, target) -> {name: value} averaged over every validation window
    (weighted by batch size), in MC and in HT (frustum visibility without random losses), as
    {'MC/loss': ..., 'HT/mpjpe': ..., 'loss': the mean of the MC and HT losses}. Shared by the
    network's and the AvatarPoser-style peer's training (humotion.sparse.peers)."""
    model.eval()
    results: dict[str, float] = {}
    loader = torch.utils.data.DataLoader(windows, batch_size=config.batch_size, shuffle=False)
    with torch.no_grad():
        for scenario in ("MC", "HT"):
            sums: dict[str, float] = {}
            count = 0
            for batch in loader:
                inputs, target = make_batch(batch, scenario_ht=scenario == "HT", frustum=config.frustum, dropout=None,
                                            fps=config.fps, device=device)
                n = len(batch["eye"])
                for k, v in measure(model, batch, inputs, target).items():
                    sums[k] = sums.get(k, 0.0) + float(v) * n
                count += n
            results.update({f"{scenario}/{k}": v / max(count, 1) for k, v in sums.items()})
    results["loss"] = (results["MC/loss"] + results["HT/loss"]) / 2
    model.train()
    return results


def validate(model: SparsePoser, windows, config: TrainConfig, device: torch.device) -> dict[str, float]:
    """Loss terms, MPJPE (cm), MPJRE (deg), root position error (cm) and root-relative MPJPE (cm)
    on every validation window (:func:`validation_means`)."""
    def measure(model, batch, inputs, target):
        pred = model(inputs, aux=True)
        total, terms = sparse_loss(pred, target, config.weights, config.position_weight)
        _, positions = predicted_world(pred, target)
        true = target["world_positions"]
        return {"loss": total, **terms,
                "mpjpe": mpjpe(positions, true), "mpjre": mpjre(pred.rotations, target["rotations"]),
                "root": mpjpe(positions[..., :1, :], true[..., :1, :]),
                "mpjpe_rootrel": mpjpe(positions - positions[..., :1, :], true - true[..., :1, :])}

    return validation_means(model, windows, config, device, measure)


@dataclass
class RunData:
    """A run's windows and how training batches are drawn from them (module train and peers).

    batches(epoch, skip): a loader over the epoch's windows from batch `skip` on. training_batch(batch):
    (inputs, target) of a batch of windows with the run's scenarios, frustum and dropout."""

    train_set: AugmentedWindows
    val_set: AugmentedWindows | None
    steps_per_epoch: int
    batches: Callable[[int, int], Iterable[dict]]
    training_batch: Callable[[dict], tuple[dict, dict]]


def run_data(config: TrainConfig, session: Session) -> RunData:
    """The training and validation windows of config's run (AMASS files read with its SMPL-H model)."""
    with using_body_model(config.smplh_model):
        train_windows, val_windows = load_run_windows(session, config.stride, config.length)
    train_set = AugmentedWindows(train_windows, config.scale_range, config.mirror, augment=True,
                                 speed_range=tuple(config.speed_range))
    val_set = AugmentedWindows(val_windows, augment=False) if val_windows else None

    def batches(epoch: int, skip: int):
        indices = session.epoch_indices(len(train_set), epoch)[skip * config.batch_size:]
        return torch.utils.data.DataLoader(train_set, batch_size=config.batch_size, sampler=indices,
                                           num_workers=config.workers)

    def training_batch(batch):
        return make_batch(batch, scenario_ht=config.ht_probability(), frustum=config.frustum, dropout=config.dropout,
                          fps=config.fps, device=session.device, generator=session.generator)

    steps_per_epoch = math.ceil(math.ceil(len(train_set) / session.world) / config.batch_size)
    return RunData(train_set, val_set, steps_per_epoch, batches, training_batch)


# -- training ------------------------------------------------------------------------------

def initial_weights(config: TrainConfig) -> SparsePoser:
    """The network in config.init_weights; ValueError when its sizes are not config.model's."""
    initial = load_sparse_model(config.init_weights)
    ours, theirs = asdict(config.model), asdict(initial.config)
    differ = [k for k in ours if k not in SparseConfig.TRAINING_ONLY and ours[k] != theirs[k]]
    if differ:
        raise ValueError(f"{config.init_weights} is a different network: "
                         + ", ".join(f"{k} {theirs[k]} (this run: {ours[k]})" for k in differ))
    return initial


def train(config: TrainConfig) -> dict:
    """Train (or resume) a SparsePoser; returns a summary dict (step, losses, validation, files)."""
    session = Session(config)
    data = run_data(config, session)
    device = session.device
    model = SparsePoser(config.model).to(device)
    if config.init_weights:
        model.load_state_dict(initial_weights(config).state_dict())
    optimizer = torch.optim.Adam(model.parameters(), lr=config.lr)

    def loss(model, batch):
        inputs, target = data.training_batch(batch)
        return sparse_loss(model(inputs, aux=bool(config.weights["aux"])), target, config.weights, config.position_weight)

    steps_per_epoch, val_set = data.steps_per_epoch, data.val_set
    total = config.steps if config.steps is not None else config.epochs * steps_per_epoch
    summary = fit(
        session, model, optimizer, steps_per_epoch=steps_per_epoch, batches=data.batches, loss=loss,
        lr_at=None if config.lr_final is None else (lambda step: learning_rate(step, total, config.lr, config.lr_final, 0)),
        validate=(lambda module: validate(module, val_set, config, device)) if val_set is not None else None,
        save_weights=lambda module, path, **extra: save_sparse_model(module, path, fps=config.fps, **extra),
        weights_name="sparse_poser",
        describe=lambda val: (f"val {val['loss']:.4f} (MC MPJPE {val['MC/mpjpe']:.1f} cm, "
                              f"HT MPJPE {val['HT/mpjpe']:.1f} cm)"),
        find_unused_parameters=not all(config.weights[t] for t in ("forecast", "aux")))
    return summary

"""Training SparsePoser on mocap windows: ``python -m humotion.sparse.train --help``.

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
Several GPUs: ``torchrun --nproc_per_node=N -m humotion.sparse.train --device cuda ...``
(DistributedDataParallel, DistributedSampler; rank 0 writes the files).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field

import click
import torch

from humotion.io.amass import load_body_model, using_body_model
from humotion.io.errors import MotionFileError
from humotion.sparse.batches import AugmentedWindows, make_batch
from humotion.sparse.losses import TERMS, loss_weights, predicted_world, sparse_loss
from humotion.sparse.metrics import mpjpe, mpjre
from humotion.sparse.model import TOKEN_GRADIENTS, SparseConfig, SparsePoser, load_sparse_model, save_sparse_model
from humotion.sparse.signals import Dropout, Frustum
from humotion.options import echo_summary, run_options, run_settings
from humotion.training import DEFAULT_DATA, RunConfig, Session, checkpoints, fit, learning_rate, load_run_windows

__all__ = ["TrainConfig", "train", "validate", "checkpoints", "train_sparse_command", "DEFAULT_DATA"]

SCENARIO_CHOICES = ("HT", "MC", "mixed")


@dataclass
class TrainConfig(RunConfig):
    """Everything a SparsePoser training run needs; saved in every checkpoint. The run settings
    (data, split, steps, seed, device, files) are humotion.training.RunConfig's; here also:

    length (frames), stride (frames between training windows; validation uses length).
    scenario: 'HT', 'MC' or 'mixed' (per window, HT with probability ht_fraction).
    fov_deg: headset camera field of view (horizontal = vertical, degrees); tracking_loss_per_s:
    rate of random hand-tracking losses in HT (0: none). scale_range, mirror, speed_range:
    augmentation (batches.AugmentedWindows; speed (1, 1): none, how the shipped networks were
    trained). weights: loss term -> weight (0 switches a term off). position_weight: the weight of
    positions in the se3 and aux transform errors (losses; 1 in the reference, metres).
    model: the network's sizes.
    workers: DataLoader worker processes. lr_final: None keeps the learning rate at lr (how the
    shipped networks were trained), a number decays it from lr to lr_final along a cosine over
    the run (tried: model card). smplh_model: a SMPL-H model .npz giving AMASS subjects their own
    bone lengths from their betas (None: the canonical proportions; humotion.io.amass).
    init_weights: a SparsePoser weights file of the same sizes to start from (fine-tuning; the
    optimizer starts afresh); a checkpoint in out_dir still takes precedence (resume).
    """

    out_dir: str = "runs/sparse"
    length: int = 40
    stride: int = 10
    scenario: str = "mixed"
    ht_fraction: float = 0.5
    fov_deg: float = 120.0
    tracking_loss_per_s: float = 0.2
    scale_range: tuple[float, float] = (0.85, 1.15)
    mirror: float = 0.5
    speed_range: tuple[float, float] = (1.0, 1.0)
    weights: dict = field(default_factory=loss_weights)
    position_weight: float = 1.0
    model: SparseConfig = field(default_factory=SparseConfig)
    workers: int = 0
    lr_final: float | None = None
    smplh_model: str | None = None
    init_weights: str | None = None

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
                "mpjpe": mpjpe(positions, true), "mpjre": mpjre(pred["rotations"], target["rotations"]),
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


# -- command line --------------------------------------------------------------------------

@click.command("sparse", context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@run_options(out_dir="runs/sparse", epochs=20, batch_size=64, lr=1e-3)
@click.option("--lr-final", type=float, help="Decay the learning rate from --lr to this along a cosine  [default: constant].")
@click.option("--length", default=40, show_default=True, help="Window length, frames.")
@click.option("--fps", default=30.0, show_default=True)
@click.option("--stride", default=10, show_default=True, help="Frames between training windows.")
@click.option("--scenario", type=click.Choice(SCENARIO_CHOICES), default="mixed", show_default=True,
              help="MC: hands always seen; HT: seen inside the headset frustum; mixed: drawn per window.")
@click.option("--fov", "fov_deg", default=120.0, show_default=True, help="Hand-tracking field of view, degrees.")
@click.option("--tracking-loss", "tracking_loss_per_s", default=0.2, show_default=True,
              help="Random hand-tracking losses per second in HT (0: none).")
@click.option("--speed", "speed_range", nargs=2, type=float, default=(1.0, 1.0), show_default=True,
              help="Play each training window at a random speed in this range (log-uniform; 1 1: as captured).")
@click.option("--position-weight", default=1.0, show_default=True,
              help="Weight of joint positions (metres) in the se3 and aux losses.")
@click.option("--ablate-loss", multiple=True, type=click.Choice(TERMS[1:]), help="Switch a loss term off (repeatable).")
@click.option("--mask-token", type=click.Choice(("adaptive", "fixed")), default="adaptive", show_default=True)
@click.option("--token-gradient", type=click.Choice(TOKEN_GRADIENTS), default="detached", show_default=True,
              help="detached: the mask token and forecaster learn from the encoder without training it; "
                   "full: they train it too (an ablation).")
@click.option("--hidden", default=128, show_default=True, help="GRU / transformer width.")
@click.option("--embed", default=32, show_default=True, help="Embedding size per input part.")
@click.option("--feedforward", type=int, help="Transformer feed-forward width  [default: 2 x hidden].")
@click.option("--decoder", type=int, help="Decoder MLP width  [default: 2 x hidden].")
@click.option("--init", "init_weights", type=click.Path(exists=True, dir_okay=False),
              help="Start from these weights (same sizes; fine-tuning) instead of random ones.")
@click.option("--workers", default=0, show_default=True, help="DataLoader worker processes.")
@click.option("--smplh-model", type=click.Path(exists=True, dir_okay=False),
              help="SMPL-H model .npz (J_regressor, v_template, shapedirs, kintree_table): AMASS subjects' bone "
                   "lengths from their betas  [default: canonical proportions].")
def train_sparse_command(ablate_loss, mask_token, token_gradient, hidden, embed, feedforward, decoder, **options):
    """Train the headset-to-full-body model (SparsePoser) on the CMU mocap windows.

    \b
    Examples:
      humotion train sparse --out runs/sparse --epochs 20
      humotion train sparse --steps 200 --max-clips 20 --out /tmp/quick
      humotion train sparse --ablate-loss se3 --ablate-loss aux --out runs/no_se3_aux
      humotion train sparse --hidden 64 --embed 16 --out runs/narrow     # a smaller, faster network
      torchrun --nproc_per_node=4 -m humotion.sparse.train --device cuda --batch-size 256
      humotion train sparse --data ~/AMASS --smplh-model smplh/neutral/model.npz   # docs/amass.md
    """
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    config_model = SparseConfig(embed=embed, hidden=hidden, mask_token=mask_token, token_gradient=token_gradient,
                                feedforward=feedforward or 2 * hidden, decoder=decoder or 2 * hidden)
    if options.get("init_weights"):
        try:
            initial_weights(TrainConfig(model=config_model, init_weights=options["init_weights"]))   # checked before any work
        except ValueError as error:
            raise click.ClickException(str(error)) from None
    if options.get("smplh_model"):
        try:
            load_body_model(options["smplh_model"])      # checked once, before any work
        except MotionFileError as error:
            raise click.ClickException(str(error)) from None
    config = TrainConfig(weights=loss_weights(ablate=ablate_loss), **run_settings(options), model=config_model, **options)
    echo_summary(train(config))


if __name__ == "__main__":
    train_sparse_command()

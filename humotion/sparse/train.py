"""Training SparsePoser on mocap windows: ``python -m humotion.sparse.train --help``.

    from humotion.sparse.train import TrainConfig, train
    summary = train(TrainConfig(out_dir="runs/sparse", epochs=20))

Data: the CMU sources of ../shared/data/mocap (hdm05_jointlearning is evaluation-only and left
out), split by subject (MotionCollection.split), cut into windows of `length` frames at `fps` on
the canonical 22-joint body (the to_canonical conversion is cached, see :func:`load_windows`).
Each training window is mirrored (p = 0.5), turned by a random yaw and scaled by s ~ U(0.85,
1.15) (offsets and root trajectory); its headset signals are synthesised from forward
kinematics, in the controller scenario (MC: hands always seen) or hand tracking (HT: hands seen
inside the headset frustum, minus random tracking losses), drawn per window for "mixed".

Output folder: checkpoint-<step>.pt (model, optimizer, step, config, best validation loss, RNG
states; the newest 3 kept) every `checkpoint_every` steps and at the end, log.jsonl (one JSON
line per logged step and per validation), sparse_poser.pt (final weights + config, small, for
:func:`humotion.sparse.model.load_sparse_model`) and sparse_poser_best.pt (best validation).
A run restarts from the newest checkpoint in its folder unless resume=False.
Several GPUs: ``torchrun --nproc_per_node=N -m humotion.sparse.train --device cuda ...``
(DistributedDataParallel, DistributedSampler; rank 0 writes the files).
"""

from __future__ import annotations

import json
import logging
import math
import os
import random
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import click
import numpy as np
import torch
import torch.distributed as dist
from tqdm.auto import tqdm

from humotion.sparse.batches import DEFAULT_DATA, AugmentedWindows, load_windows, make_batch
from humotion.sparse.losses import TERMS, loss_weights, predicted_world, sparse_loss
from humotion.sparse.metrics import mpjpe, mpjre
from humotion.sparse.model import SparseConfig, SparsePoser, save_sparse_model
from humotion.sparse.signals import Dropout, Frustum

log = logging.getLogger("humotion.sparse")

SCENARIO_CHOICES = ("HT", "MC", "mixed")


@dataclass
class TrainConfig:
    """Everything a training run needs; saved in every checkpoint.

    data_root: mocap folder tree. sources / exclude: top-level folders to keep / drop.
    train_split / val_split: split names of MotionCollection.split(seed=split_seed) (None: every
    clip for training / no validation). max_clips: first N clips of the split only (quick runs).
    length (frames), fps, stride (frames between training windows; validation uses length).
    scenario: 'HT', 'MC' or 'mixed' (per window, HT with probability ht_fraction).
    fov_deg: headset camera field of view (horizontal = vertical, degrees); tracking_loss_per_s:
    rate of random hand-tracking losses in HT (0: none). scale_range, mirror: augmentation.
    weights: loss term -> weight (0 switches a term off). mask_token: 'adaptive' or 'fixed'.
    steps: stop after this many optimizer steps (None: `epochs` epochs). checkpoint_every: steps.
    device: 'cpu' or 'cuda'. threads: torch CPU threads (None: torch's default; 1 is fastest on a
    busy shared machine). cache_dir: windows cache (None: humotion's default cache).
    """

    data_root: str = str(DEFAULT_DATA)
    sources: tuple[str, ...] | None = None
    exclude: tuple[str, ...] = ("hdm05_jointlearning",)
    split_seed: int = 0
    train_split: str | None = "train"
    val_split: str | None = "val"
    max_clips: int | None = None
    length: int = 40
    fps: float = 30.0
    stride: int = 10
    batch_size: int = 64
    lr: float = 1e-3
    grad_clip: float = 1.0
    epochs: int = 20
    steps: int | None = None
    scenario: str = "mixed"
    ht_fraction: float = 0.5
    fov_deg: float = 120.0
    tracking_loss_per_s: float = 0.2
    scale_range: tuple[float, float] = (0.85, 1.15)
    mirror: float = 0.5
    weights: dict = field(default_factory=loss_weights)
    model: SparseConfig = field(default_factory=SparseConfig)
    seed: int = 0
    out_dir: str = "runs/sparse"
    checkpoint_every: int = 500
    keep_checkpoints: int = 3
    log_every: int = 10
    resume: bool = True
    device: str = "cpu"
    threads: int | None = None
    workers: int = 0
    cache_dir: str | None = None
    progress: bool = True

    def __post_init__(self):
        if isinstance(self.model, dict):
            self.model = SparseConfig(**self.model)
        if self.scenario not in SCENARIO_CHOICES:
            raise ValueError(f"scenario must be one of {SCENARIO_CHOICES}, got {self.scenario!r}")
        self.weights = loss_weights(**self.weights)
        if self.model.mask_token == "fixed" and self.weights["forecast"]:
            self.weights["forecast"] = 0.0  # a fixed token forecasts nothing

    @property
    def frustum(self) -> Frustum:
        return Frustum(self.fov_deg, self.fov_deg)

    @property
    def dropout(self) -> Dropout | None:
        return Dropout(self.tracking_loss_per_s) if self.tracking_loss_per_s > 0 else None

    def ht_probability(self) -> float:
        return {"HT": 1.0, "MC": 0.0}.get(self.scenario, self.ht_fraction)

    @classmethod
    def from_dict(cls, values: dict) -> "TrainConfig":
        names = {f.name for f in fields(cls)}
        values = {k: tuple(v) if isinstance(v, list) else v for k, v in values.items() if k in names}
        return cls(**values)


# -- distributed ---------------------------------------------------------------------------

def _setup_distributed(config: TrainConfig) -> tuple[int, int, torch.device]:
    """(rank, world size, device); initialises torch.distributed when WORLD_SIZE > 1 (torchrun)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    device = torch.device(config.device)
    if world <= 1:
        return 0, 1, device
    cuda = device.type == "cuda"
    if not dist.is_initialized():
        dist.init_process_group("nccl" if cuda else "gloo")
    if cuda:
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
        torch.cuda.set_device(device)
    return dist.get_rank(), world, device


def _barrier(world: int) -> None:
    if world > 1:
        dist.barrier()


# -- checkpoints ---------------------------------------------------------------------------

def checkpoints(out_dir: Path) -> list[Path]:
    """The folder's checkpoint files, oldest step first."""
    return sorted(out_dir.glob("checkpoint-*.pt"), key=lambda p: int(p.stem.split("-")[1]))


def _save_checkpoint(out_dir: Path, model, optimizer, step: int, config: TrainConfig, best_val: float,
                     generator: torch.Generator) -> Path:
    module = getattr(model, "module", model)
    path = out_dir / f"checkpoint-{step}.pt"
    tmp = path.with_suffix(".tmp")
    torch.save({"model": {"config": asdict(module.config), "state_dict": module.state_dict()},
                "optimizer": optimizer.state_dict(), "step": step, "config": asdict(config), "best_val": best_val,
                "rng": {"torch": torch.get_rng_state(), "batch": generator.get_state()}}, tmp)
    os.replace(tmp, path)
    for old in checkpoints(out_dir)[:-config.keep_checkpoints]:
        old.unlink()
    return path


def _write_log(out_dir: Path, record: dict) -> None:
    with open(out_dir / "log.jsonl", "a") as f:
        f.write(json.dumps(record) + "\n")


# -- validation ----------------------------------------------------------------------------

@torch.no_grad()
def validate(model: SparsePoser, windows, config: TrainConfig, device: torch.device) -> dict[str, float]:
    """Loss terms, MPJPE (cm), MPJRE (deg), root position error (cm) and root-relative MPJPE (cm)
    on every validation window, in MC and in HT (frustum visibility without random losses), as
    {'MC/loss': ..., 'HT/mpjpe': ..., 'loss': the mean of the MC and HT losses}."""
    model.eval()
    results: dict[str, float] = {}
    loader = torch.utils.data.DataLoader(windows, batch_size=config.batch_size, shuffle=False)
    for scenario in ("MC", "HT"):
        sums: dict[str, float] = {}
        count = 0
        for batch in loader:
            inputs, target = make_batch(batch, scenario_ht=scenario == "HT", frustum=config.frustum, dropout=None,
                                        fps=config.fps, device=device)
            pred = model(inputs, aux=True)
            total, terms = sparse_loss(pred, target, config.weights)
            _, positions = predicted_world(pred, target)
            n = len(batch["eye"])
            true = target["world_positions"]
            values = {"loss": float(total), **{k: float(v) for k, v in terms.items()},
                      "mpjpe": mpjpe(positions, true), "mpjre": mpjre(pred["rotations"], target["rotations"]),
                      "root": mpjpe(positions[..., :1, :], true[..., :1, :]),
                      "mpjpe_rootrel": mpjpe(positions - positions[..., :1, :], true - true[..., :1, :])}
            for k, v in values.items():
                sums[k] = sums.get(k, 0.0) + v * n
            count += n
        results.update({f"{scenario}/{k}": v / max(count, 1) for k, v in sums.items()})
    results["loss"] = (results["MC/loss"] + results["HT/loss"]) / 2
    model.train()
    return results


# -- training ------------------------------------------------------------------------------

def _seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def _epoch_indices(n: int, epoch: int, config: TrainConfig, rank: int, world: int) -> list[int]:
    if world > 1:
        sampler = torch.utils.data.DistributedSampler(range(n), world, rank, shuffle=True, seed=config.seed)
        sampler.set_epoch(epoch)
        return list(sampler)
    return torch.randperm(n, generator=torch.Generator().manual_seed(config.seed + epoch)).tolist()


def train(config: TrainConfig) -> dict:
    """Train (or resume) a SparsePoser; returns a summary dict (step, losses, validation, files)."""
    rank, world, device = _setup_distributed(config)
    if config.threads:
        torch.set_num_threads(config.threads)
    _seed_everything(config.seed + rank)
    out_dir = Path(config.out_dir)
    if rank == 0:
        out_dir.mkdir(parents=True, exist_ok=True)
    show = config.progress and rank == 0

    start = time.perf_counter()
    if rank != 0:
        _barrier(world)  # rank 0 builds the windows cache first
    train_windows = load_windows(config, config.train_split, config.stride, progress=show)
    val_windows = (load_windows(config, config.val_split, config.length, progress=show, allow_empty=True)
                   if config.val_split else None)
    if rank == 0:
        _barrier(world)
    data_seconds = time.perf_counter() - start
    if show:
        tqdm.write(f"data: {len(train_windows)} training windows, {len(val_windows or [])} validation windows "
                   f"({data_seconds:.0f} s)")
    train_set = AugmentedWindows(train_windows, config.scale_range, config.mirror, augment=True)
    val_set = AugmentedWindows(val_windows, augment=False) if val_windows else None

    model = SparsePoser(config.model).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.lr)
    generator = torch.Generator().manual_seed(config.seed * 1000 + rank)
    step, start_step, best_val = 0, 0, math.inf
    found = checkpoints(out_dir) if config.resume and out_dir.is_dir() else []
    if found:
        state = torch.load(found[-1], map_location="cpu", weights_only=True)
        model.load_state_dict(state["model"]["state_dict"])
        optimizer.load_state_dict(state["optimizer"])
        step = start_step = state["step"]
        best_val = state["best_val"]
        torch.set_rng_state(state["rng"]["torch"])
        generator.set_state(state["rng"]["batch"])
        if show:
            tqdm.write(f"resumed from {found[-1]} at step {step}")
    if world > 1:
        model = torch.nn.parallel.DistributedDataParallel(
            model, device_ids=[device.index] if device.type == "cuda" else None,
            find_unused_parameters=not all(config.weights[t] for t in ("forecast", "aux")))
    module = getattr(model, "module", model)

    per_rank = math.ceil(len(train_set) / world)
    steps_per_epoch = math.ceil(per_rank / config.batch_size)
    total_steps = config.steps if config.steps is not None else config.epochs * steps_per_epoch
    bar = tqdm(total=total_steps, initial=step, desc="training", unit="step", disable=not show, dynamic_ncols=True)
    model.train()
    smoothed, val, tic, last_loss = None, {}, time.perf_counter(), math.nan
    while step < total_steps:
        epoch, skip = divmod(step, steps_per_epoch)
        indices = _epoch_indices(len(train_set), epoch, config, rank, world)[skip * config.batch_size:]
        loader = torch.utils.data.DataLoader(train_set, batch_size=config.batch_size, sampler=indices,
                                             num_workers=config.workers)
        for batch in loader:
            inputs, target = make_batch(batch, scenario_ht=config.ht_probability(), frustum=config.frustum,
                                        dropout=config.dropout, fps=config.fps, device=device, generator=generator)
            pred = model(inputs, aux=bool(config.weights["aux"]))
            loss, terms = sparse_loss(pred, target, config.weights)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            grad_norm = torch.nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip)
            optimizer.step()
            step += 1
            last_loss, terms = loss.item(), {k: v.item() for k, v in terms.items()}
            smoothed = last_loss if smoothed is None else 0.95 * smoothed + 0.05 * last_loss
            bar.update()
            bar.set_postfix(loss=f"{smoothed:.4f}", **{k: f"{v:.4f}" for k, v in terms.items()})
            if rank == 0 and step % config.log_every == 0:
                now = time.perf_counter()
                _write_log(out_dir, {"step": step, "epoch": epoch, "loss": last_loss, "smoothed": smoothed,
                                     **terms, "grad_norm": float(grad_norm),
                                     "steps_per_s": config.log_every / (now - tic)})
                tic = now
            if rank == 0 and step % config.checkpoint_every == 0:
                _save_checkpoint(out_dir, model, optimizer, step, config, best_val, generator)
            if step >= total_steps:
                break
        epoch_done = step % steps_per_epoch == 0 or step >= total_steps
        if epoch_done and val_set is not None:
            if rank == 0:
                val = validate(module, val_set, config, device)
                if val["loss"] < best_val:
                    best_val = val["loss"]
                    save_sparse_model(module, out_dir / "sparse_poser_best.pt", fps=config.fps, step=step, val=val)
                _write_log(out_dir, {"step": step, "epoch": epoch, "val": val})
                if show:
                    tqdm.write(f"step {step} epoch {epoch}: train {smoothed:.4f}, val {val['loss']:.4f} "
                               f"(MC MPJPE {val['MC/mpjpe']:.1f} cm, HT MPJPE {val['HT/mpjpe']:.1f} cm)")
            _barrier(world)
    bar.close()
    summary = {"step": step, "start_step": start_step, "train_loss": last_loss, "smoothed_loss": smoothed,
               "best_val": best_val if math.isfinite(best_val) else None, "val": val, "data_seconds": data_seconds}
    if rank == 0:
        summary["checkpoint"] = str(_save_checkpoint(out_dir, model, optimizer, step, config, best_val, generator))
        summary["export"] = str(out_dir / "sparse_poser.pt")
        save_sparse_model(module, summary["export"], fps=config.fps, step=step, val=val)
    _barrier(world)
    if world > 1:
        dist.destroy_process_group()
    return summary


# -- command line --------------------------------------------------------------------------

@click.command("sparse", context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.option("--data", "data_root", default=str(DEFAULT_DATA), show_default=True, help="Mocap folder tree.")
@click.option("--out", "out_dir", default="runs/sparse", show_default=True, help="Output folder (checkpoints, log, weights).")
@click.option("--epochs", default=20, show_default=True, help="Epochs over the training windows.")
@click.option("--steps", type=int, help="Stop after this many optimizer steps instead.")
@click.option("--batch-size", default=64, show_default=True)
@click.option("--lr", default=1e-3, show_default=True, help="Adam learning rate.")
@click.option("--length", default=40, show_default=True, help="Window length, frames.")
@click.option("--fps", default=30.0, show_default=True)
@click.option("--stride", default=10, show_default=True, help="Frames between training windows.")
@click.option("--scenario", type=click.Choice(SCENARIO_CHOICES), default="mixed", show_default=True,
              help="MC: hands always seen; HT: seen inside the headset frustum; mixed: drawn per window.")
@click.option("--fov", "fov_deg", default=120.0, show_default=True, help="Hand-tracking field of view, degrees.")
@click.option("--tracking-loss", "tracking_loss_per_s", default=0.2, show_default=True,
              help="Random hand-tracking losses per second in HT (0: none).")
@click.option("--source", "sources", multiple=True, help="Train on these source folders only (repeatable).")
@click.option("--exclude", multiple=True, default=("hdm05_jointlearning",), show_default=True,
              help="Leave these source folders out (repeatable; hdm05_jointlearning is evaluation-only).")
@click.option("--ablate-loss", multiple=True, type=click.Choice(TERMS[1:]), help="Switch a loss term off (repeatable).")
@click.option("--mask-token", type=click.Choice(("adaptive", "fixed")), default="adaptive", show_default=True)
@click.option("--hidden", default=128, show_default=True, help="GRU / transformer width.")
@click.option("--embed", default=32, show_default=True, help="Embedding size per input part.")
@click.option("--seed", default=0, show_default=True)
@click.option("--device", default="cpu", show_default=True, help="cpu or cuda (torchrun for several GPUs).")
@click.option("--threads", type=int, help="Torch CPU threads (1 is fastest on a busy shared machine).")
@click.option("--workers", default=0, show_default=True, help="DataLoader worker processes.")
@click.option("--checkpoint-every", default=500, show_default=True, help="Steps between checkpoints.")
@click.option("--max-clips", type=int, help="Use only the first N clips of the split (quick runs).")
@click.option("--no-resume", is_flag=True, help="Start afresh even if the output folder has checkpoints.")
def train_sparse_command(ablate_loss, mask_token, hidden, embed, no_resume, sources, exclude, **options):
    """Train the headset-to-full-body model (SparsePoser) on the CMU mocap windows.

    \b
    Examples:
      humotion train sparse --out runs/sparse --epochs 20
      humotion train sparse --steps 200 --max-clips 20 --out /tmp/quick
      humotion train sparse --ablate-loss se3 --ablate-loss aux --out runs/no_se3_aux
      torchrun --nproc_per_node=4 -m humotion.sparse.train --device cuda --batch-size 256
    """
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    config = TrainConfig(weights=loss_weights(ablate=ablate_loss), resume=not no_resume, sources=sources or None,
                         exclude=tuple(dict.fromkeys((*exclude, "hdm05_jointlearning"))),
                         model=SparseConfig(embed=embed, hidden=hidden, mask_token=mask_token), **options)
    summary = train(config)
    if int(os.environ.get("RANK", "0")) == 0:
        click.echo(json.dumps({k: v for k, v in summary.items() if k != "val"}, indent=1))


if __name__ == "__main__":
    train_sparse_command()

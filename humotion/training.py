"""What every humotion training command shares: run settings, data windows, seeds, devices,
checkpoints, the progress bar and the optimisation loop.

    session = Session(config)                                  # torchrun setup, threads, seeds, output folder
    train_windows, val_windows = load_run_windows(session, train_stride=10, val_stride=40)
    summary = fit(session, model, optimizer, steps_per_epoch=..., batches=..., loss=..., validate=...,
                  save_weights=..., weights_name="my_model")

Output folder of a run: checkpoint-<step>.pt (model config and weights, optimizer, step, run
config, best validation loss, RNG states; the newest `keep_checkpoints` kept) every
`checkpoint_every` steps and at the end; log.jsonl (one JSON line per `log_every` steps and per
validation); <weights_name>.pt (final weights) and <weights_name>_best.pt (lowest validation
loss), written by the model's own save function. A run restarts from the newest checkpoint in its
folder unless resume=False. Several processes: torchrun sets WORLD_SIZE / RANK / LOCAL_RANK and
the run uses DistributedDataParallel (gloo on CPU, nccl on GPUs); rank 0 writes the files.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import random
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Callable, Iterable, Protocol

import numpy as np
import torch
import torch.distributed as dist
from tqdm.auto import tqdm

from humotion import canonical, motion as motion_module
from humotion.atomic import atomic_file
from humotion.retarget import keyjoints
from humotion.canonical import to_canonical
from humotion.data import MotionCollection, MotionWindows, default_cache_dir, default_data_dir
from humotion.data.cache import read_motions, write_motions
from humotion.data import windows as windows_module

log = logging.getLogger("humotion.training")

DEFAULT_DATA = default_data_dir() / "mocap"
EVALUATION_ONLY = ("hdm05_jointlearning",)


@dataclass
class RunConfig:
    """Settings every training run has (each field's docstring is its command-line help); a
    model's training config adds its own fields."""

    data_root: str = str(DEFAULT_DATA)
    """Mocap folder tree."""
    sources: tuple[str, ...] | None = None
    """Train on these top-level source folders only (repeatable; None: all)."""
    exclude: tuple[str, ...] = EVALUATION_ONLY
    """Leave these source folders out (repeatable; hdm05_jointlearning is evaluation-only)."""
    split_seed: int = 0
    """Seed of MotionCollection.split."""
    train_split: str | None = "train"
    """Split name of the training clips (None: every clip)."""
    val_split: str | None = "val"
    """Split name of the validation clips (None: no validation)."""
    max_clips: int | None = None
    """Use only the first N clips of the split (quick runs)."""
    fps: float = 30.0
    """Frame rate of the training windows."""
    batch_size: int = 64
    """Training examples (windows, meshes) per optimizer step."""
    lr: float = 1e-3
    """Adam learning rate."""
    grad_clip: float = 1.0
    """Gradient norm clip."""
    epochs: int = 20
    """Epochs over the training windows."""
    steps: int | None = None
    """Stop after this many optimizer steps instead (None: `epochs` epochs)."""
    seed: int = 0
    """Seed of the run's random numbers."""
    out_dir: str = "runs/model"
    """Output folder (checkpoints, log, weights)."""
    checkpoint_every: int = 500
    """Steps between checkpoints."""
    keep_checkpoints: int = 3
    """Newest checkpoints kept."""
    log_every: int = 10
    """Steps between log lines."""
    resume: bool = True
    """Restart from the newest checkpoint in the output folder (--no-resume: start afresh)."""
    device: str = "cpu"
    """cpu or cuda (torchrun for several GPUs)."""
    threads: int | None = None
    """Torch CPU threads (None: torch's default; 1 is fastest on a busy shared machine)."""
    cache_dir: str | None = None
    """Windows cache (None: humotion's default cache)."""
    progress: bool = True
    """Show progress bars."""

    @classmethod
    def from_dict(cls, values: dict):
        """The config from a dict (e.g. a checkpoint's "config"), ignoring unknown keys."""
        names = {f.name for f in fields(cls)}
        values = {k: tuple(v) if isinstance(v, list) else v for k, v in values.items() if k in names}
        return cls(**values)


# -- data ----------------------------------------------------------------------------------

def _source_hash() -> str:
    digest = hashlib.sha1()
    for module in (canonical, keyjoints, motion_module, windows_module):  # keyjoints: to_canonical's key joints
        digest.update(Path(module.__file__).read_bytes())
    return digest.hexdigest()[:12]


class WindowsConfig(Protocol):
    """What load_windows reads: RunConfig's data fields and the windows' length (frames), which
    each model's training config defines (a field, or a property such as the lifter's)."""

    data_root: str
    sources: tuple[str, ...] | None
    exclude: tuple[str, ...]
    split_seed: int
    max_clips: int | None
    fps: float
    cache_dir: str | None

    @property
    def length(self) -> int: ...


def load_windows(config: WindowsConfig, split: str | None, stride: int, progress: bool = False,
                 allow_empty: bool = False) -> MotionWindows | None:
    """Windows of config.length frames at config.fps on the canonical body, one per `stride`
    frames, from the clips of one subject split (None: every clip) of the collection under
    config.data_root, then of config.sources minus config.exclude (the split is made on the
    whole tree first, so it does not depend on them), first config.max_clips clips.

    The canonical conversion and resampling of a whole split take a while (40-70 s for the CMU
    training split on a 2-core machine; under a second from the cache), so the windows' clips
    are kept as data-only .npz files (humotion.data.cache.write_motions: no pickle, so a file
    planted there cannot run code; caches of earlier versions, .pkl, are never opened) under
    config.cache_dir (default: humotion's cache folder / canonical_windows), keyed by the clips'
    cache entries (which change with the files and readers), the window parameters and the
    source of the conversion. A split without clips raises ValueError, or gives None when
    allow_empty."""
    collection = MotionCollection.load(config.data_root, progress=progress)
    if split is not None:
        # The split of the whole tree, so leaving sources out never moves a subject across splits.
        splits = collection.split(seed=config.split_seed)
        if split not in splits:
            raise KeyError(f"no split {split!r}; splits: {', '.join(splits)}")
        collection = collection.filter(subjects=splits[split])
    collection = collection.filter(sources=config.sources, exclude=config.exclude)
    clips = collection.clips[:config.max_clips] if config.max_clips else collection.clips
    if not clips:
        if allow_empty:
            log.warning("no clips in split %r under %s", split, config.data_root)
            return None
        raise ValueError(f"no clips in split {split!r} under {config.data_root}")
    key = hashlib.sha1("\n".join(
        [_source_hash(), f"{config.length}|{config.fps}|{stride}"]
        + [f"{c.path}|{c.frames}|{c.cache_file.name if c.cache_file else ''}" for c in clips]).encode()).hexdigest()
    folder = Path(config.cache_dir) if config.cache_dir else default_cache_dir() / "canonical_windows"
    file = folder / f"{key}.npz"
    cached = read_motions(file)           # the clips as resampled: the windows follow from them
    if cached is not None:
        return MotionWindows(cached, config.length, config.fps, stride=stride)
    start = time.perf_counter()
    windows = MotionCollection(clips).windows(config.length, config.fps, stride=stride, transform=to_canonical,
                                              progress=progress)
    log.info("built %s in %.0f s", windows, time.perf_counter() - start)
    write_motions(file, windows.motions)
    return windows


# -- one run: processes, seeds, files ------------------------------------------------------

def checkpoints(out_dir: Path) -> list[Path]:
    """The folder's checkpoint files, oldest step first."""
    return sorted(Path(out_dir).glob("checkpoint-*.pt"), key=lambda p: int(p.stem.split("-")[1]))


def unwrap(model: torch.nn.Module) -> torch.nn.Module:
    """The model inside a DistributedDataParallel wrapper (or the model itself)."""
    return getattr(model, "module", model)


class Session:
    """The bookkeeping of one training process: rank and device (torchrun), CPU threads, seeds
    (python, numpy and torch from config.seed + rank), the output folder, and `generator`, the CPU
    generator for the run's own random draws (seeded config.seed * 1000 + rank; checkpointed)."""

    def __init__(self, config: RunConfig):
        self.config = config
        self.world = int(os.environ.get("WORLD_SIZE", "1"))
        self.rank, self.device = 0, torch.device(config.device)
        if self.world > 1:
            cuda = self.device.type == "cuda"
            if not dist.is_initialized():
                dist.init_process_group("nccl" if cuda else "gloo")
            self.rank = dist.get_rank()
            if cuda:
                self.device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
                torch.cuda.set_device(self.device)
        if config.threads:
            torch.set_num_threads(config.threads)
        random.seed(config.seed + self.rank)
        np.random.seed(config.seed + self.rank)
        torch.manual_seed(config.seed + self.rank)
        self.generator = torch.Generator().manual_seed(config.seed * 1000 + self.rank)
        self.out_dir = Path(config.out_dir)
        if self.rank == 0:
            self.out_dir.mkdir(parents=True, exist_ok=True)
        self.show = config.progress and self.rank == 0

    def barrier(self) -> None:
        if self.world > 1:
            dist.barrier()

    def close(self) -> None:
        self.barrier()
        if self.world > 1:
            dist.destroy_process_group()

    def echo(self, message: str) -> None:
        """Print a line above the progress bar (rank 0, progress on)."""
        if self.show:
            tqdm.write(message)

    def log(self, record: dict) -> None:
        """Append one JSON line to log.jsonl (rank 0 only)."""
        if self.rank == 0:
            with open(self.out_dir / "log.jsonl", "a") as f:
                f.write(json.dumps(record) + "\n")

    def epoch_indices(self, n: int, epoch: int) -> list[int]:
        """This process's order of the n training items in an epoch (a fixed shuffle per seed and
        epoch, so a resumed run sees the same order; shared out between processes)."""
        if self.world > 1:
            sampler = torch.utils.data.DistributedSampler(range(n), self.world, self.rank, shuffle=True,
                                                          seed=self.config.seed)
            sampler.set_epoch(epoch)
            return list(sampler)
        return torch.randperm(n, generator=torch.Generator().manual_seed(self.config.seed + epoch)).tolist()

    def save_checkpoint(self, model, optimizer, step: int, best_val: float) -> Path:
        """checkpoint-<step>.pt in the output folder; older ones beyond keep_checkpoints go."""
        module = unwrap(model)
        path = self.out_dir / f"checkpoint-{step}.pt"
        with atomic_file(path) as file:
            torch.save({"model": {"config": asdict(module.config), "state_dict": module.state_dict()},
                        "optimizer": optimizer.state_dict(), "step": step, "config": asdict(self.config),
                        "best_val": best_val,
                        "rng": {"torch": torch.get_rng_state(), "batch": self.generator.get_state()}}, file)
        for old in checkpoints(self.out_dir)[:-self.config.keep_checkpoints]:
            old.unlink()
        return path

    def resume(self, model, optimizer) -> tuple[int, float]:
        """(step, best validation loss) of the newest checkpoint, whose weights, optimizer and RNG
        states are loaded; (0, inf) when there is none or config.resume is False."""
        found = checkpoints(self.out_dir) if self.config.resume and self.out_dir.is_dir() else []
        if not found:
            return 0, math.inf
        state = torch.load(found[-1], map_location="cpu", weights_only=True)
        model.load_state_dict(state["model"]["state_dict"])
        optimizer.load_state_dict(state["optimizer"])
        torch.set_rng_state(state["rng"]["torch"])
        self.generator.set_state(state["rng"]["batch"])
        self.echo(f"resumed from {found[-1]} at step {state['step']}")
        return state["step"], state["best_val"]


def load_run_windows(session: Session, train_stride: int,
                     val_stride: int) -> tuple[MotionWindows, MotionWindows | None]:
    """A run's training windows (config.train_split, one per train_stride frames) and validation
    windows (config.val_split, one per val_stride frames; None without a validation split or
    clips in it), rank 0 building the windows cache while other processes wait."""
    config = session.config
    start = time.perf_counter()
    if session.rank != 0:
        session.barrier()
    train = load_windows(config, config.train_split, train_stride, progress=session.show)
    val = (load_windows(config, config.val_split, val_stride, progress=session.show, allow_empty=True)
           if config.val_split else None)
    if session.rank == 0:
        session.barrier()
    session.echo(f"data: {len(train)} training windows, {len(val or [])} validation windows "
                 f"({time.perf_counter() - start:.0f} s)")
    return train, val


# -- the optimisation loop -----------------------------------------------------------------

def fit(session: Session, model: torch.nn.Module, optimizer: torch.optim.Optimizer, *, steps_per_epoch: int,
        batches: Callable[[int, int], Iterable], loss: Callable[[torch.nn.Module, object], tuple],
        validate: Callable[[torch.nn.Module], dict] | None, save_weights: Callable[..., None], weights_name: str,
        describe: Callable[[dict], str] = lambda val: f"val {val['loss']:.4f}",
        lr_at: Callable[[int], float] | None = None, find_unused_parameters: bool = False) -> dict:
    """Train `model` (on session.device, not yet wrapped) from its newest checkpoint on.

    steps_per_epoch: optimizer steps in one epoch of this process. The run stops after
    config.steps steps, else config.epochs epochs.
    batches(epoch, skip): the epoch's batches after the first `skip` ones (skip > 0 on resume).
    loss(model, batch): (scalar loss tensor, {term: tensor or float}) for one batch; model may be
    the DistributedDataParallel wrapper.
    validate(module): {"loss": ..., other metrics} on the validation data (rank 0, at the end of
    every epoch and of the run); None: no validation. describe(val): its summary line.
    save_weights(module, path, step=..., val=...): writes a small weights file; called for
    <weights_name>_best.pt (lowest validation loss) and <weights_name>.pt (the end).
    lr_at(step): learning rate for the step (None: the optimizer's own, fixed).
    Returns {"step", "start_step", "train_loss", "smoothed_loss", "best_val", "val", "checkpoint",
    "export"} (the last two on rank 0).
    """
    config = session.config
    step, best_val = session.resume(model, optimizer)
    start_step = step
    if session.world > 1:
        model = torch.nn.parallel.DistributedDataParallel(
            model, device_ids=[session.device.index] if session.device.type == "cuda" else None,
            find_unused_parameters=find_unused_parameters)
    module = unwrap(model)
    total_steps = config.steps if config.steps is not None else config.epochs * steps_per_epoch
    bar = tqdm(total=total_steps, initial=step, desc="training", unit="step", disable=not session.show,
               dynamic_ncols=True)
    model.train()
    smoothed, val, tic, last_loss = None, {}, time.perf_counter(), math.nan
    while step < total_steps:
        epoch, skip = divmod(step, steps_per_epoch)
        for batch in batches(epoch, skip):
            if lr_at is not None:
                for group in optimizer.param_groups:
                    group["lr"] = lr_at(step)
            value, terms = loss(model, batch)
            optimizer.zero_grad(set_to_none=True)
            value.backward()
            grad_norm = torch.nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip)
            optimizer.step()
            step += 1
            last_loss = value.item()
            terms = {k: v.item() if torch.is_tensor(v) else float(v) for k, v in terms.items()}
            smoothed = last_loss if smoothed is None else 0.95 * smoothed + 0.05 * last_loss
            bar.update()
            bar.set_postfix(loss=f"{smoothed:.4f}", **{k: f"{v:.4f}" for k, v in terms.items()})
            if step % config.log_every == 0:
                now = time.perf_counter()
                session.log({"step": step, "epoch": epoch, "loss": last_loss, "smoothed": smoothed, **terms,
                             "grad_norm": float(grad_norm), "lr": optimizer.param_groups[0]["lr"],
                             "steps_per_s": config.log_every / (now - tic)})
                tic = now
            if session.rank == 0 and step % config.checkpoint_every == 0:
                session.save_checkpoint(model, optimizer, step, best_val)
            if step >= total_steps:
                break
        epoch_done = step % steps_per_epoch == 0 or step >= total_steps
        if epoch_done and validate is not None:
            if session.rank == 0:
                val = validate(module)
                module.train()
                if val["loss"] < best_val:
                    best_val = val["loss"]
                    save_weights(module, session.out_dir / f"{weights_name}_best.pt", step=step, val=val)
                session.log({"step": step, "epoch": epoch, "val": val})
                session.echo(f"step {step} epoch {epoch}: train {smoothed:.4f}, {describe(val)}")
            session.barrier()
    bar.close()
    summary = {"step": step, "start_step": start_step, "train_loss": last_loss, "smoothed_loss": smoothed,
               "best_val": best_val if math.isfinite(best_val) else None, "val": val}
    if session.rank == 0:
        summary["checkpoint"] = str(session.save_checkpoint(model, optimizer, step, best_val))
        summary["export"] = str(session.out_dir / f"{weights_name}.pt")
        save_weights(module, summary["export"], step=step, val=val)
    session.close()
    return summary


def learning_rate(step: int, total: int, lr: float, final: float, warmup: int) -> float:
    """Linear warm-up over `warmup` steps (0: none), then cosine decay from lr to final at step total."""
    if step < warmup:
        return lr * (step + 1) / warmup
    progress = min((step - warmup) / max(total - warmup, 1), 1.0)
    return final + 0.5 * (lr - final) * (1 + math.cos(math.pi * progress))

"""Training data for SparsePoser: canonical-body windows, augmentation, synthetic headset batches.

    windows = load_windows(config, "train", stride=10)        # cached canonical windows
    dataset = AugmentedWindows(windows)                       # mirror / yaw / body scale per item
    inputs, target = make_batch(batch, scenario_ht=0.5, frustum=Frustum(), dropout=Dropout(), fps=30)

The canonical conversion (humotion.canonical.to_canonical) and resampling of a whole split take
a while (40-70 s for the CMU training split on a 2-core machine; 0.7 s from the cache), so the
MotionWindows are pickled under the cache folder, keyed by the clips' cache entries (which
change with the files and readers), the window parameters and the source of the conversion.
"""

from __future__ import annotations

import hashlib
import logging
import math
import pickle
import time
from dataclasses import replace
from pathlib import Path

import torch

from humotion import canonical, motion as motion_module
from humotion.canonical import to_canonical
from humotion.data import MotionCollection, MotionWindows, default_cache_dir
from humotion.data import windows as windows_module
from humotion.data.augment import mirror, rotate_yaw
from humotion.sparse import signals as sg
from humotion.sparse.losses import targets

log = logging.getLogger("humotion.sparse")

DEFAULT_DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "mocap"


def _source_hash() -> str:
    digest = hashlib.sha1()
    for module in (canonical, motion_module, windows_module):
        digest.update(Path(module.__file__).read_bytes())
    return digest.hexdigest()[:12]


def load_windows(config, split: str | None, stride: int, progress: bool = False,
                 allow_empty: bool = False) -> MotionWindows | None:
    """Windows of config.length frames at config.fps on the canonical body, one per `stride`
    frames, from the clips of one subject split (None: every clip) of the collection under
    config.data_root, then of config.sources minus config.exclude (the split is made on the
    whole tree first, so it does not depend on them), first config.max_clips clips.
    Cached under config.cache_dir (default: humotion's cache folder / sparse_windows).
    A split without clips raises ValueError, or gives None when allow_empty."""
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
    folder = Path(config.cache_dir) if config.cache_dir else default_cache_dir() / "sparse_windows"
    file = folder / f"{key}.pkl"
    if file.exists():
        try:
            with open(file, "rb") as f:
                return pickle.load(f)
        except Exception as error:  # damaged entry: rebuild it
            log.info("ignoring unreadable windows cache %s (%s)", file, error)
    start = time.perf_counter()
    windows = MotionCollection(clips).windows(config.length, config.fps, stride=stride, transform=to_canonical,
                                              progress=progress)
    log.info("built %s in %.0f s", windows, time.perf_counter() - start)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tmp = file.with_suffix(f".{id(windows)}.tmp")
        with open(tmp, "wb") as f:
            pickle.dump(windows, f, protocol=pickle.HIGHEST_PROTOCOL)
        tmp.replace(file)
    except OSError as error:
        log.warning("cannot write windows cache %s (%s)", file, error)
    return windows


class AugmentedWindows(torch.utils.data.Dataset):
    """Training items from canonical MotionWindows, randomly augmented when augment=True.

    Augmentation (drawn from torch's global RNG, so DataLoader workers differ): mirror with
    probability `mirror`, a yaw about the world origin uniform in [-pi, pi), and a body scale s
    uniform in scale_range (every offset and the root trajectory times s).
    Items: rotations (T, 22, 4) wxyz local, root_positions (T, 3) metres, offsets (22, 3) metres,
    eye (3,) the headset's position in the head frame (signals.eye_offset), metres.
    """

    def __init__(self, windows: MotionWindows, scale_range: tuple[float, float] = (0.85, 1.15),
                 mirror: float = 0.5, augment: bool = True):
        self.windows, self.scale_range, self.mirror, self.augment = windows, scale_range, mirror, augment

    def __len__(self) -> int:
        return len(self.windows)

    def __getitem__(self, i: int) -> dict:
        motion = self.windows.window(i)
        if self.augment:
            if float(torch.rand(())) < self.mirror:
                motion = mirror(motion)
            motion = rotate_yaw(motion, (float(torch.rand(())) * 2 - 1) * math.pi)
            low, high = self.scale_range
            s = low + (high - low) * float(torch.rand(()))
            motion = replace(motion, skeleton=motion.skeleton.scaled(s), root_positions=motion.root_positions * s)
        return {"rotations": motion.rotations, "root_positions": motion.root_positions,
                "offsets": torch.as_tensor(motion.skeleton.offsets, dtype=torch.float32),
                "eye": sg.eye_offset(motion.skeleton)}


def make_batch(batch: dict, scenario_ht: float | bool, frustum: sg.Frustum = sg.Frustum(),
               dropout: sg.Dropout | None = None, fps: float = 30.0, device: torch.device | str = "cpu",
               generator: torch.Generator | None = None) -> tuple[dict, dict]:
    """(model inputs, loss targets) for a collated batch of AugmentedWindows items.

    scenario_ht: probability that a window is in the HT scenario (hands seen inside the frustum,
    minus random `dropout` losses), else MC (always seen); True / False for all windows.
    Inputs are the headset signals with unseen hands hidden (signals.hide_unseen); targets are
    losses.targets(...) with the true hand signals as target["hands"] (B, T, 2, 9).
    generator: the CPU generator for the scenario and tracking-loss draws.
    """
    rotations, root = batch["rotations"].to(device), batch["root_positions"].to(device)
    offsets, eye = batch["offsets"].to(device), batch["eye"].to(device)
    target = targets(rotations, root, offsets)
    device_r, device_p = sg.device_poses(target["world_rotations"], target["world_positions"], eye)
    b = rotations.shape[0]
    p = float(scenario_ht)
    ht = torch.full((b,), p >= 1) if p in (0.0, 1.0) else torch.rand(b, generator=generator) < p
    visible = torch.ones(device_p.shape[:-2] + (2,), dtype=torch.bool, device=device_p.device)
    if ht.any():
        seen = sg.simulate_visibility(device_r, device_p, "HT", frustum, dropout, fps, generator)
        visible = torch.where(ht.to(visible.device)[:, None, None], seen, visible)
    signals = sg.pose_signals(device_r, device_p, visible)
    target["hands"] = torch.stack([signals["left"], signals["right"]], dim=-2)
    return sg.hide_unseen(signals), target

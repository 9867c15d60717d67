"""Training data for SparsePoser: canonical-body windows, augmentation, synthetic headset batches.

    windows = load_windows(config, "train", stride=10)        # cached canonical windows (humotion.training)
    dataset = AugmentedWindows(windows)                       # mirror / yaw / body scale per item
    dataset = AugmentedWindows(windows, speed_range=(0.8, 1.25))   # and a playback speed per item
    inputs, target = make_batch(batch, scenario_ht=0.5, frustum=Frustum(), dropout=Dropout(), fps=30)
"""

from __future__ import annotations

import math
from dataclasses import replace

import torch

from humotion.data import MotionWindows
from humotion.data.augment import mirror, rotate_yaw
from humotion.motion import Motion
from humotion.sparse import signals as sg
from humotion.sparse.losses import targets
from humotion.training import DEFAULT_DATA, load_windows

__all__ = ["AugmentedWindows", "make_batch", "load_windows", "DEFAULT_DATA"]


class AugmentedWindows(torch.utils.data.Dataset):
    """Training items from canonical MotionWindows, randomly augmented when augment=True.

    Augmentation (drawn from torch's global RNG, so DataLoader workers differ): a playback speed
    v log-uniform in speed_range (the window's frames taken every v source frames from its clip,
    slerp / linear between frames: v = 1.25 plays the motion 25 % faster; the window moves back
    in its clip when the faster span would run past the clip's end; not drawn at all when the
    range is (1, 1)), mirror with probability `mirror`, a yaw about the world origin uniform in
    [-pi, pi), and a body scale s uniform in scale_range (every offset and the root trajectory
    times s).
    Items: rotations (T, 22, 4) wxyz local, root_positions (T, 3) metres, offsets (22, 3) metres,
    eye (3,) the headset's position in the head frame (signals.eye_offset), metres.
    """

    def __init__(self, windows: MotionWindows, scale_range: tuple[float, float] = (0.85, 1.15),
                 mirror: float = 0.5, augment: bool = True, speed_range: tuple[float, float] = (1.0, 1.0)):
        if not 0 < speed_range[0] <= speed_range[1]:
            raise ValueError(f"speed_range must be two positive numbers, low <= high; got {speed_range}")
        self.windows, self.scale_range, self.mirror, self.augment = windows, scale_range, mirror, augment
        self.speed_range = speed_range

    def __len__(self) -> int:
        return len(self.windows)

    def at_speed(self, i: int, speed: float) -> Motion:
        """Window i played `speed` times as fast: `length` frames at the windows' rate, frame k at
        source time k * speed from the window's start (moved back to fit in its clip; a clip
        too short for the span is played as fast as it allows)."""
        clip, start = self.windows.index[i]
        motion, n = self.windows.motions[clip], self.windows.length
        last = motion.num_frames - 1
        speed = min(speed, last / max(n - 1, 1))
        span = math.ceil((n - 1) * speed - 1e-9)
        start = min(start, last - span)
        piece = motion[start:start + span + 1]
        return replace(piece, fps=piece.fps * speed).resample(piece.fps)[:n]

    def __getitem__(self, i: int) -> dict:
        motion = self.windows.window(i)
        if self.augment:
            low, high = self.speed_range
            if low != high:
                motion = self.at_speed(i, math.exp(math.log(low) + (math.log(high) - math.log(low)) * float(torch.rand(()))))
            if float(torch.rand(())) < self.mirror:
                motion = mirror(motion)
            motion = rotate_yaw(motion, (float(torch.rand(())) * 2 - 1) * math.pi)
            low, high = self.scale_range
            s = low + (high - low) * float(torch.rand(()))
            motion = replace(motion, skeleton=motion.skeleton.scaled(s), root_positions=motion.root_positions * s)
        return {"rotations": motion.rotations, "root_positions": motion.root_positions,
                "offsets": motion.skeleton.offsets,
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

"""Fixed-length training windows cut from a collection's clips, as a torch Dataset.

Every clip is loaded, transformed (optional) and resampled once; a window is indexed by
(clip, start frame) and sliced on demand, so memory is one copy of the motion at the target rate.
"""

from __future__ import annotations

import logging
from typing import Callable, Sequence

import torch
from tqdm.auto import tqdm

from humotion.motion import Motion

log = logging.getLogger("humotion.data")


class MotionWindows(torch.utils.data.Dataset):
    """Windows of `length` frames at `fps` from clips on one skeleton.

    clips: objects with .load() -> Motion (collection Clips) or Motions.
    stride: frames between window starts (default length: windows do not overlap).
    transform: Motion -> Motion applied to each whole clip before resampling (e.g. a conversion
        to a canonical skeleton, or a fixed speed change).
    augment: Motion -> Motion applied to each window when it is fetched (mirror, yaw; it must keep
        the frame count, so speed changes belong in transform).
    Items are dicts of float32 tensors: rotations (N, J, 4) local wxyz quaternions,
    root_positions (N, 3) metres, offsets (J, 3) rest offsets in metres, clip (index into
    .motions), start (first frame at `fps`), plus joint_offsets (N, J, 3) when a clip animates
    offsets. as_motion=True gives Motions instead. Clips shorter than a window are left out.
    Raises ValueError when the clips (after transform) are on different skeletons.
    """

    def __init__(self, clips: Sequence, length: int, fps: float, *, stride: int | None = None,
                 transform: Callable[[Motion], Motion] | None = None,
                 augment: Callable[[Motion], Motion] | None = None, as_motion: bool = False,
                 progress: bool = False):
        if length < 1:
            raise ValueError(f"window length must be at least 1 frame, got {length}")
        self.length, self.fps, self.stride = int(length), float(fps), int(stride or length)
        if self.stride < 1:
            raise ValueError(f"stride must be at least 1 frame, got {stride}")
        self.augment, self.as_motion = augment, as_motion
        self.motions: list[Motion] = []
        self.index: list[tuple[int, int]] = []
        skeletons: dict[tuple, str] = {}
        too_short = 0
        for clip in tqdm(clips, desc="resampling clips", unit="clip", disable=not progress):
            motion = clip if isinstance(clip, Motion) else clip.load()
            if transform is not None:
                motion = transform(motion)
            tree = (motion.skeleton.names, motion.skeleton.parents)
            skeletons.setdefault(tree, f"{getattr(clip, 'path', motion.name)}")
            if len(skeletons) > 1:
                described = "; ".join(f"{len(t[0])} joints (e.g. {where})" for t, where in skeletons.items())
                raise ValueError(
                    "windows would mix skeletons that cannot be stacked: " + described + ". Keep one skeleton "
                    "(collection.windows(..., signature=...); see collection.signatures()) or pass a transform "
                    "that maps every clip onto one skeleton (e.g. a canonical-skeleton conversion).")
            motion = motion.resample(self.fps)
            if motion.num_frames < self.length:
                too_short += 1
                continue
            starts = range(0, motion.num_frames - self.length + 1, self.stride)
            self.index += [(len(self.motions), s) for s in starts]
            self.motions.append(motion)
        self.has_joint_offsets = any(m.joint_offsets is not None for m in self.motions)
        if too_short:
            log.info("left out %d clips shorter than %d frames at %g fps", too_short, self.length, self.fps)

    def __len__(self) -> int:
        return len(self.index)

    @property
    def num_joints(self) -> int:
        return self.motions[0].skeleton.num_joints if self.motions else 0

    def window(self, i: int) -> Motion:
        """Window i as a Motion (before augmentation)."""
        clip, start = self.index[i]
        return self.motions[clip][start:start + self.length]

    def __getitem__(self, i: int):
        motion = self.window(i)
        if self.augment is not None:
            motion = self.augment(motion)
            if motion.num_frames != self.length:
                raise ValueError(f"augment changed the window length from {self.length} to {motion.num_frames} "
                                 "frames; apply speed changes as a clip transform instead")
        if self.as_motion:
            return motion
        clip, start = self.index[i]
        item = {
            "rotations": motion.rotations,
            "root_positions": motion.root_positions,
            "offsets": motion.skeleton.offsets,
            "clip": torch.tensor(clip),
            "start": torch.tensor(start),
        }
        if self.has_joint_offsets:
            item["joint_offsets"] = (motion.joint_offsets if motion.joint_offsets is not None
                                     else item["offsets"].expand(self.length, -1, -1))
        return item

    def __repr__(self) -> str:
        return (f"MotionWindows({len(self)} windows of {self.length} frames at {self.fps:g} fps, "
                f"{len(self.motions)} clips, {self.num_joints} joints)")

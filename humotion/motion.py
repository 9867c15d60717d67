"""Motion: a skeleton moving over time, the one data type all of humotion reads and writes."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch

from humotion import rotations as rot
from humotion.skeleton import Skeleton, forward_kinematics


@dataclass(eq=False)
class Motion:
    """Local joint rotations and a root trajectory on a skeleton, sampled at fps.

    rotations: (T, J, 4) unit quaternions (w, x, y, z), each joint relative to its parent
        (joint 0's is its world orientation).
    root_positions: (T, 3) world position of joint 0, metres.
    joint_offsets: optional (T, J, 3) per-frame offsets replacing skeleton.offsets, for files
        that animate joint translations (BVH position channels on non-root joints); None when the
        skeleton's rest offsets hold on every frame.
    Tensors are float32 torch tensors; numpy arrays given here are converted.
    """

    skeleton: Skeleton
    rotations: torch.Tensor
    root_positions: torch.Tensor
    fps: float
    joint_offsets: torch.Tensor | None = None
    name: str = ""

    def __post_init__(self):
        self.rotations = torch.as_tensor(self.rotations, dtype=torch.float32)
        self.root_positions = torch.as_tensor(self.root_positions, dtype=torch.float32)
        if self.joint_offsets is not None:
            self.joint_offsets = torch.as_tensor(self.joint_offsets, dtype=torch.float32)
        frames, joints = self.rotations.shape[0], self.skeleton.num_joints
        label = f"motion {self.name!r}" if self.name else "motion"
        if self.rotations.shape != (frames, joints, 4):
            raise ValueError(f"{label}: rotations have shape {tuple(self.rotations.shape)}, expected ({frames}, {joints}, 4)")
        if self.root_positions.shape != (frames, 3):
            raise ValueError(f"{label}: root_positions have shape {tuple(self.root_positions.shape)}, expected ({frames}, 3)")
        if self.joint_offsets is not None and self.joint_offsets.shape != (frames, joints, 3):
            raise ValueError(f"{label}: joint_offsets have shape {tuple(self.joint_offsets.shape)}, expected ({frames}, {joints}, 3)")
        if not (math.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"{label}: fps must be a positive number, got {self.fps}")
        for field_name in ("rotations", "root_positions", "joint_offsets"):
            value = getattr(self, field_name)
            # The sum first: no mask as large as the motion (a big file's rotations are hundreds of
            # MB); it is non-finite whenever an element is (or the sum overflows: then the mask decides).
            if value is not None and not torch.isfinite(value.sum()):
                bad = ~torch.isfinite(value.reshape(frames, -1)).all(-1)
                if bad.any():
                    raise ValueError(f"{label}: {field_name} contain NaN or infinity (first at frame {int(bad.nonzero()[0])})")

    # -- size -----------------------------------------------------------------------------
    @property
    def num_frames(self) -> int:
        return self.rotations.shape[0]

    def __len__(self) -> int:
        return self.num_frames

    @property
    def duration(self) -> float:
        """Seconds covered: frames / fps."""
        return self.num_frames / self.fps

    def __getitem__(self, frames) -> "Motion":
        """Frames as a new Motion: motion[10:50], motion[::2] (fps divided by the step)."""
        if isinstance(frames, int):
            frames = slice(frames, frames + 1 if frames != -1 else None)
        if not isinstance(frames, slice):
            raise TypeError("index a Motion with a slice of frames, e.g. motion[10:50]")
        step = frames.step or 1
        if step < 1:
            raise ValueError("frame step must be positive")
        return replace(
            self,
            rotations=self.rotations[frames],
            root_positions=self.root_positions[frames],
            joint_offsets=None if self.joint_offsets is None else self.joint_offsets[frames],
            fps=self.fps / step,
        )

    # -- kinematics -----------------------------------------------------------------------
    def _offsets(self) -> torch.Tensor:
        if self.joint_offsets is not None:
            return self.joint_offsets
        return self.skeleton.offsets

    def world(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(world rotation matrices (T, J, 3, 3), world positions (T, J, 3) in metres)."""
        return forward_kinematics(self.rotations, self.root_positions, self._offsets(), self.skeleton.parents)

    def world_positions(self) -> torch.Tensor:
        """(T, J, 3) joint positions in metres."""
        return self.world()[1]

    def world_transforms(self) -> torch.Tensor:
        """(T, J, 4, 4) homogeneous joint-to-world transforms."""
        r, p = self.world()
        t = torch.zeros(r.shape[:-2] + (4, 4), dtype=r.dtype)
        t[..., :3, :3] = r
        t[..., :3, 3] = p
        t[..., 3, 3] = 1.0
        return t

    def end_site_positions(self) -> torch.Tensor:
        """(T, E, 3) end-site positions in metres."""
        r, p = self.world()
        parents = list(self.skeleton.end_site_parents)
        off = self.skeleton.end_site_offsets
        return p[:, parents] + (r[:, parents] @ off[..., None])[..., 0]

    # -- rotation forms -------------------------------------------------------------------
    def rotations_as(self, form: str) -> torch.Tensor:
        """Local rotations in another form: 'quat' (T, J, 4) wxyz, 'matrix' (T, J, 3, 3), 'rotvec'
        (T, J, 3) radians or 'sixd' (T, J, 6) (:mod:`humotion.rotations`); float32."""
        return rot.convert(self.rotations, "quat", form)

    # -- resampling -----------------------------------------------------------------------
    def resample(self, fps: float) -> "Motion":
        """The motion at another frame rate: slerp for rotations, linear for positions.

        Output frame k is at time k / fps; frames run while that time is within the input. At
        the motion's own frame rate, the motion itself.
        """
        if not (fps > 0):
            raise ValueError(f"fps must be positive, got {fps}")
        if fps == self.fps:
            return self
        last_time = (self.num_frames - 1) / self.fps
        count = int(math.floor(last_time * fps + 1e-6)) + 1
        source_time = torch.arange(count, dtype=torch.float64) * (self.fps / fps)
        lo = source_time.floor().long().clamp(max=self.num_frames - 1)
        hi = (lo + 1).clamp(max=self.num_frames - 1)
        t = (source_time - lo).float().clamp(0, 1)

        def lerp(x: torch.Tensor | None) -> torch.Tensor | None:
            if x is None:
                return None
            w = t.view(-1, *([1] * (x.dim() - 1)))
            return x[lo] * (1 - w) + x[hi] * w

        rotations = rot.quat_slerp(self.rotations[lo], self.rotations[hi], t[:, None].expand(-1, self.skeleton.num_joints))
        return replace(self, rotations=rotations, root_positions=lerp(self.root_positions),
                       joint_offsets=lerp(self.joint_offsets), fps=float(fps))

    # -- symmetry -------------------------------------------------------------------------
    def mirrored(self) -> "Motion":
        """Left and right swapped, reflected through the X = 0 plane (a character's left is +X).

        The world positions of the result are those of the input with x negated and each
        left joint exchanged with its right counterpart.
        """
        m = self.skeleton.mirror_indices()
        # Reflecting x maps a rotation quaternion (w, x, y, z) to (w, x, -y, -z).
        flip_q = torch.tensor([1.0, 1.0, -1.0, -1.0])
        flip_v = torch.tensor([-1.0, 1.0, 1.0])
        return replace(
            self,
            skeleton=self.skeleton.mirrored(),
            rotations=self.rotations[:, m] * flip_q,
            root_positions=self.root_positions * flip_v,
            joint_offsets=None if self.joint_offsets is None else self.joint_offsets[:, m] * flip_v,
        )

    # -- construction ---------------------------------------------------------------------
    @classmethod
    def rest(cls, skeleton: Skeleton, frames: int = 1, fps: float = 30.0) -> "Motion":
        """The skeleton standing still in its rest pose."""
        root = skeleton.offsets[0].expand(frames, 3).clone()
        return cls(skeleton, rot.quat_identity(frames, skeleton.num_joints), root, fps)

    def __repr__(self) -> str:
        label = f"{self.name!r}, " if self.name else ""
        return (f"Motion({label}{self.num_frames} frames at {self.fps:g} fps = {self.duration:.2f} s, "
                f"{self.skeleton.num_joints} joints)")

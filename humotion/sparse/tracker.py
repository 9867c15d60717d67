"""Sparse tracking in use: a live headset stream or a whole recording -> full-body motion.

:class:`SparseTracker` keeps the network's state between frames and turns one headset frame
(:class:`~humotion.sparse.recording.HeadsetFrame`: timestamp, head and hand poses) into one
body pose; its :meth:`~SparseTracker.track` runs a whole
:class:`~humotion.sparse.recording.HeadsetStream` at once (the same maths, batched over time).

The network runs at the frame rate it was trained at (``tracker.fps``): velocities are
per-frame differences, so a faster stream is thinned to that rate (the pose of the last frame
the network ran is returned in between) and a recording is resampled to it (slerp).
The body is posed on the canonical skeleton scaled to the user: a stated height, or one
estimated from the first frame's eye height (eyes sit at 0.936 of standing height).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from humotion import rotations as rot
from humotion.canonical import canonical_skeleton
from humotion.motion import Motion
from humotion.skeleton import Skeleton
from humotion.sparse import signals as sg
from humotion.sparse import solve as sv
from humotion.sparse.frame import (SHIPPED_DIR, OnnxStream, TorchStream, astuple_shallow, head_eyes, onnx_file,
                                   state_is_sound)
from humotion.sparse.gate import GateLimits, HeadsetGate, Rejections, TrackingWarning, gate_stream
from humotion.sparse.model import SparsePoser, load_sparse_model
from humotion.sparse.recording import HeadsetFrame, HeadsetStream

EYE_HEIGHT_RATIO = 0.936     # eye level / standing height (Drillis & Contini, in Winter 2009)
SHIPPED_WEIGHTS = {"default": SHIPPED_DIR / "sparse_poser.pt", "accurate": SHIPPED_DIR / "sparse_poser_accurate.pt",
                   "fast": SHIPPED_DIR / "sparse_poser.pt"}
"""The shipped networks by name (MODEL_CARD.md beside them): "default" 64 wide, about half a
millisecond per frame with ONNX Runtime; "accurate" 128 wide, 0.1-1.0 cm more accurate (a
second seed of its recipe was not) and about 1.3-1.7x the time per frame. "fast" is the
default's earlier name (it was the 64-wide network when the 128-wide one was the default)."""
DEFAULT_WEIGHTS = SHIPPED_WEIGHTS["default"]


def estimate_height(eye_height_m: float) -> float:
    """Standing height (metres) from the eye height of someone standing, clamped to 1.2-2.2 m."""
    return min(max(eye_height_m / EYE_HEIGHT_RATIO, 1.2), 2.2)


@dataclass
class TrackedPose:
    """One body pose: rotations (22, 4) local wxyz quaternions (joint 0 global), root_position
    (3,) metres, positions (22, 3) world joint positions in metres, timestamp in seconds."""

    rotations: torch.Tensor
    root_position: torch.Tensor
    positions: torch.Tensor
    timestamp: float


def load_weights(model: SparsePoser | str | Path | None) -> SparsePoser:
    """The network in eval mode (its .fps is the frame rate it was trained at): model itself, a
    weights file, a name of SHIPPED_WEIGHTS, or None for the default."""
    if isinstance(model, SparsePoser):
        return model.eval()
    path = SHIPPED_WEIGHTS.get(str(model or "default"), Path(str(model)))
    if not path.is_file():
        raise FileNotFoundError(f"no sparse-tracking weights at {path}: train them with `humotion train sparse`, "
                                f"pass the path of a .pt file, or a shipped model's name ({', '.join(SHIPPED_WEIGHTS)})")
    return load_sparse_model(path)


class SparseTracker:
    """Online full-body tracking from a headset (module docstring).

    model: a SparsePoser, a weights file, a shipped network's name ("default", "accurate": see
        SHIPPED_WEIGHTS), or None for the default.
    height: the user's standing height in metres (None: estimated from the first frame).
    anchor_head: place the root so the body's eyes are where the headset is (see
        :func:`anchor_to_head`); False keeps the network's own trajectory, which drifts.
    runtime: how update() runs. "onnx": with ONNX Runtime, faster per frame than PyTorch (the
        model card's Speed section); the shipped weights come with their ONNX file, other
        weights are exported once (half a minute) into the cache folder. "torch": in PyTorch.
        "auto" (default): ONNX when an export of these weights is at hand (shipped or cached),
        else PyTorch, so nothing is exported unasked.
    gate: limits of the plausibility gate (humotion.sparse.gate) that keeps glitched samples
        from the network: a rejected hand counts as unseen, a rejected head holds the last pose,
        then the network restarts; None switches the gate off. rejected: the counts
        (gate.Rejections) of the current stream (update) or of the last track() call.
    solve: after the network, the arms are solved so the wrists meet the tracked hands and the
        feet are locked while planted and kept above the floor (humotion.sparse.solve; its
        settings); None: the network's pose as it is.
    floor: the floor's height in metres (world Y); None: from the stream's first second, when
        the user is taken to stand (solve.running_floor).
    track() (whole recordings) always runs batched in PyTorch.
    """

    def __init__(self, model: SparsePoser | str | Path | None = None, height: float | None = None,
                 anchor_head: bool = True, runtime: str = "auto", gate: GateLimits | None = GateLimits(),
                 solve: sv.SolveSettings | None = sv.SolveSettings(), floor: float | None = None):
        if runtime not in ("auto", "onnx", "torch"):
            raise ValueError(f"runtime must be 'auto', 'onnx' or 'torch', got {runtime!r}")
        self.model = load_weights(model)
        self.fps = float(getattr(self.model, "fps", 30.0))
        self.stated_height = height
        self.anchor_head = anchor_head
        path = None if runtime == "torch" else onnx_file(self.model, anchor_head, export=runtime == "onnx")
        self.runtime = "onnx" if path else "torch"
        self._stream = OnnxStream(path) if path else TorchStream(self.model, anchor_head)
        self._gate = HeadsetGate(gate) if gate is not None else None
        self._max_root_distance = (gate or GateLimits()).max_root_distance   # the state guard's, gate or not
        self.solve_settings, self.stated_floor = solve, floor
        self.calibrated = None      # a body sized by calibrate(), kept across reset()
        self.reset()

    def reset(self) -> None:
        """Forget the stream: the next frame starts a new one (new ground origin, new state)."""
        self._started = False
        self._last_time = None
        self._pose: TrackedPose | None = None
        if self._gate is not None:
            self._gate.reset()
        self.rejected = self._gate.counts if self._gate is not None else Rejections()
        self.height = self.stated_height       # the stream's; estimated on its first frame when not stated
        self._solve_state, self._solve_body = sv.SolveState(), None
        self.skeleton = None if self.height is None else canonical_skeleton(self.height)
        if self.calibrated is not None:
            self.height, self.skeleton = self.calibrated.height(), self.calibrated

    def calibrate(self, frame: HeadsetFrame) -> Skeleton:
        """Size the body from one frame of the user standing in a T-pose, arms straight out to the
        sides, both hands tracked (its timestamp is not read): the height from the eye height
        above the floor (the stated floor, else 0), unless a height was stated; the arms (upper
        arm and forearm, in proportion) so the wrists are as far apart as the tracked ones. Kept
        for every later stream (and track()); returns the body."""
        if frame.left is None or frame.right is None:
            raise ValueError("calibrate needs both hands tracked (a T-pose, arms straight out to the sides)")
        head, left, right = frame.head, frame.left, frame.right
        eye = float(_as_numpy(head[1])[1]) - (self.stated_floor or 0.0)
        skeleton = canonical_skeleton(self.stated_height or estimate_height(eye))
        rest = skeleton.rest_positions(torch.float64).numpy()
        wrists, elbows, shoulders = ([skeleton.index(f"{side}_{joint}") for side in ("left", "right")]
                                     for joint in ("wrist", "elbow", "shoulder"))
        between = np.linalg.norm(rest[shoulders[0]] - rest[shoulders[1]])
        span = float(np.linalg.norm(_as_numpy(left[1]) - _as_numpy(right[1])))
        scale = (span - between) / (np.linalg.norm(rest[wrists[0]] - rest[wrists[1]]) - between)
        if not 0.7 < scale < 1.4:
            raise ValueError(f"calibrate: the wrists are {span:.2f} m apart, arms {scale:.2f} times the usual length "
                             "for this height: stand in a T-pose, arms straight out to the sides")
        offsets = skeleton.offsets.clone()
        offsets[elbows + wrists] *= scale
        self.calibrated = replace(skeleton, offsets=offsets)
        self.reset()
        return self.calibrated

    def update(self, frame: HeadsetFrame) -> TrackedPose:
        """One headset frame -> one body pose.

        frame: poses in humotion's frame (metres; see humotion.sparse.recording for converting
        OpenXR / Unity data), a hand None when not tracked; its timestamp in seconds, increasing.
        """
        timestamp = frame.timestamp
        if self._last_time is not None and timestamp <= self._last_time - 1e-9:
            raise ValueError(f"timestamp {timestamp} is earlier than the previous frame's {self._last_time}; "
                             "call reset() to start a new stream")
        if self._pose is not None and timestamp - self._last_time < 0.75 / self.fps:
            return TrackedPose(self._pose.rotations, self._pose.root_position, self._pose.positions, timestamp)
        # numpy throughout: a few microseconds, where small torch ops and conversions cost tens
        rotations = np.zeros((3, 3, 3), np.float32)
        positions = np.zeros((3, 3), np.float32)
        visible = np.array([frame.left is not None, frame.right is not None], np.float32)
        for i, device in enumerate((frame.head, frame.left, frame.right)):
            if device is not None:
                rotations[i], positions[i] = _as_numpy(device[0]), _as_numpy(device[1])
        verdict = self._gate.check(rotations, positions, visible, timestamp) if self._gate else None
        if verdict is not None:          # implausible samples never reach the network (humotion.sparse.gate)
            self.rejected = self._gate.counts
            if not verdict.head:
                if self._pose is None:
                    raise ValueError(f"no usable head pose yet ({'; '.join(verdict.reasons)}): the first frame "
                                     "of a stream needs a finite head position and rotation (NaN?)")
                if math.isfinite(timestamp):
                    self._last_time = timestamp
                return TrackedPose(self._pose.rotations, self._pose.root_position, self._pose.positions, timestamp)
            for k, accepted in enumerate(verdict.hands):
                if not accepted:
                    visible[k], rotations[k + 1], positions[k + 1] = 0.0, 0.0, 0.0
        elif not (np.isfinite(rotations).all() and np.isfinite(positions).all()):
            raise ValueError("headset frame holds NaN or infinity in a pose marked visible")
        if not self._started or (verdict is not None and verdict.restart):
            self._start_stream(positions)
        local, root, world = self._guarded_step(rotations, positions, visible)
        self._last_time = timestamp
        if local is None:                # the network failed even from a fresh state: hold the last pose
            return TrackedPose(self._pose.rotations, self._pose.root_position, self._pose.positions, timestamp)
        if self.solve_settings is not None:
            local, root, world = self._solve_frame(np.asarray(local), np.asarray(world), rotations, positions, visible)
        self._pose = TrackedPose(_as_tensor(local), _as_tensor(root), _as_tensor(world), timestamp)
        return self._pose

    def _solve_frame(self, local: np.ndarray, world: np.ndarray, rotations: np.ndarray, positions: np.ndarray,
                     visible: np.ndarray) -> tuple:
        """The network's pose of one frame (local (22, 4), world positions (22, 3)) with the arms
        and feet solved (humotion.sparse.solve), as (local, root, world) float32 arrays."""
        if self._solve_body is None or self._solve_body[0] is not self.skeleton:
            self._solve_body = (self.skeleton, sv.BodyGeometry.of(self.skeleton))
        local, world = sv.solve_frames(local[None], world[None], self._solve_body[1], rotations[None, 1:],
                                       positions[None, 1:], visible[None] > 0.5, positions[None, 0, 1], self.fps,
                                       self.stated_floor, self._solve_state, self.solve_settings)
        return local[0].astype(np.float32), world[0, 0].astype(np.float32), world[0].astype(np.float32)

    def _start_stream(self, positions: np.ndarray) -> None:
        """(Re)start the network's stream on this frame: the body's size on a stream's first
        frame, the ground origin under the head, a fresh state."""
        if self.skeleton is None:
            self.height = estimate_height(float(positions[0, 1]))
            self.skeleton = canonical_skeleton(self.height)
        if self._started:
            self.rejected.restarts += 1
            sv.forget_places(self._solve_state)
        self._stream.start(self.skeleton.offsets, sg.eye_offset(self.skeleton),
                           astuple_shallow(self.model.initial_state(torch.from_numpy(positions[None, 0, [0, 2]]))))
        self._started = True

    def _guarded_step(self, rotations: np.ndarray, positions: np.ndarray, visible: np.ndarray) -> tuple:
        """The network on one frame; a state gone non-finite or absurd (frame.state_is_sound) is
        re-initialised from this frame and the frame run again (None, None, None if it fails again)."""
        limit = self._max_root_distance
        for attempt in range(2):
            local, root, world = self._stream(rotations, positions, visible)
            if np.isfinite(np.asarray(world)).all() and state_is_sound(self._stream.state(), positions[0], limit):
                return local, root, world
            warnings.warn(f"the tracking network's state went {'non-finite' if not np.isfinite(np.asarray(world)).all() else 'absurd'}"
                          f"{' again' if attempt else ''}: restarted from this frame", TrackingWarning, stacklevel=3)
            self._start_stream(positions)
        return None, None, None

    def _body(self, rotations: torch.Tensor, root: torch.Tensor, head: torch.Tensor, skeleton) -> Motion:
        """The network's output (T, 22, 3, 3) and (T, 3) as a Motion, anchored to the head (T, 3)."""
        motion = Motion(skeleton, rot.matrix_to_quat(rotations), root, self.fps)
        return anchor_to_head(motion, head) if self.anchor_head else motion

    @torch.no_grad()
    def track(self, stream: HeadsetStream) -> Motion:
        """A whole recording -> Motion on the user-scaled canonical skeleton at self.fps.

        The same rules as update(): the gate (when on) judges every frame first, the network
        runs on the frames whose head it accepted, from a fresh state after each run of held
        frames or when its state breaks (counts in self.rejected)."""
        if len(stream) < 2:
            raise ValueError("a recording needs at least two frames to track")
        if self._gate is not None:
            raw_times = stream.timestamps
            stream, held, self.rejected = gate_stream(stream, self._gate.limits)
            stream = resample_stream(stream, self.fps)
            held = _resampled_flags(raw_times, held, stream.timestamps)
        else:
            stream, self.rejected = resample_stream(stream, self.fps), Rejections()
            held = torch.zeros(len(stream), dtype=torch.bool)
        first = int(torch.argmin(held.to(torch.uint8)))
        height = self.stated_height or estimate_height(float(stream.head_positions[first, 1]))
        rotations, roots = self._run_segments(stream, held)
        skeleton = self.calibrated if self.calibrated is not None else canonical_skeleton(height)
        motion = self._body(rotations, roots, stream.head_positions.float(), skeleton)
        if self.solve_settings is None:
            return motion
        return sv.solve_body(motion, stream.rotations, stream.positions, stream.visible, self.stated_floor,
                             settings=self.solve_settings)

    def _run_segments(self, stream: HeadsetStream, held: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The network over a (resampled, gated) stream: (T, 22, 3, 3) rotations and (T, 3) roots.
        Each run of unheld frames starts from a fresh state, as does a frame where the state
        breaks (root non-finite or farther than max_root_distance from the eyes); held frames
        repeat the last pose (the first run's first pose before it)."""
        limit = self._max_root_distance
        count = len(stream)
        rotations, roots = torch.zeros(count, 22, 3, 3), torch.zeros(count, 3)
        held = held.clone()
        done = torch.zeros(count, dtype=torch.bool)        # frames with a pose of their own
        heads = stream.head_positions.float()
        start, ran = 0, False
        while start < count:
            if held[start]:
                start += 1
                continue
            end = start + int(torch.cat([held[start:], torch.ones(1, dtype=torch.bool)]).to(torch.uint8).argmax())
            self.rejected.restarts += ran
            ran = True
            out = self.model(sg.hide_unseen(sg.pose_signals(stream.rotations[start:end].float(),
                                                            stream.positions[start:end].float(), stream.visible[start:end])))
            r, root = out.rotations, out.root_positions
            broken = ~torch.isfinite(r).flatten(1).all(1) | ~torch.isfinite(root).all(1)
            broken |= ~((root - heads[start:end]).norm(dim=-1) <= limit)
            good = end - start if not broken.any() else int(broken.to(torch.uint8).argmax())
            rotations[start:start + good], roots[start:start + good] = r[:good], root[:good]
            done[start:start + good] = True
            if good < end - start:
                warnings.warn(f"the tracking network's state broke at frame {start + good}: restarted from there",
                              TrackingWarning, stacklevel=3)
                if good == 0:       # broken even from a fresh state: hold the frame
                    done[start] = False
                    held[start] = True
                    good = 1
            start += good
        _hold_last(rotations, roots, ~done)
        return rotations, roots

def _resampled_flags(times: torch.Tensor, flags: torch.Tensor, new_times: torch.Tensor) -> torch.Tensor:
    """Per-frame flags (T,) bool carried to new_times as resample_stream interpolates: set where
    either neighbour that contributes to the new frame has it."""
    hi = torch.searchsorted(times, new_times).clamp(1, len(times) - 1)
    lo = hi - 1
    w = ((new_times - times[lo]) / (times[hi] - times[lo])).clamp(0, 1)
    return (flags[lo] & (w < 1 - 1e-9)) | (flags[hi] & (w > 1e-9))


def _hold_last(rotations: torch.Tensor, roots: torch.Tensor, held: torch.Tensor) -> None:
    """In place: held frames take the pose of the last frame before them that is not held (the
    first such frame's pose for held frames at the start)."""
    kept = torch.nonzero(~held).flatten()
    if len(kept) == 0:
        raise ValueError("the tracking network gave no usable pose on any frame of the recording")
    source = torch.cummax(torch.where(held, -1, torch.arange(len(held))), 0).values
    source = torch.where(source < 0, kept[0], source)
    rotations[:] = rotations[source]
    roots[:] = roots[source]


def _as_tensor(value) -> torch.Tensor:
    """A stream's output as a tensor (numpy arrays shared, not copied: each frame's are new)."""
    return value if isinstance(value, torch.Tensor) else torch.from_numpy(value)


def _as_numpy(value) -> np.ndarray:
    """A rotation or position given as a tensor, an array or a list, as a numpy array."""
    return value.detach().cpu().numpy() if isinstance(value, torch.Tensor) else np.asarray(value)


def anchor_to_head(motion: Motion, head_positions: torch.Tensor) -> Motion:
    """The motion moved, frame by frame, so its eyes are at the observed headset positions.

    The network integrates the root trajectory from frame-to-frame moves, which drifts over long
    streams (metres after a minute); the headset position is known on every frame, so shifting
    the root by (observed eyes - the body's eyes) removes the drift and leaves the pose as
    predicted. motion: on the canonical skeleton (T frames); head_positions: (T, 3) metres.
    """
    eyes = head_eyes(*motion.world(), sg.eye_offset(motion.skeleton))
    shift = torch.as_tensor(head_positions, dtype=eyes.dtype) - eyes
    return Motion(motion.skeleton, motion.rotations, motion.root_positions + shift, motion.fps, name=motion.name)


def resample_stream(stream: HeadsetStream, fps: float) -> HeadsetStream:
    """The stream at a fixed frame rate from its first timestamp: slerp for orientations, linear
    for positions; a hand counts as visible at a new frame when it was at both neighbours (or at
    the one it coincides with)."""
    times = stream.timestamps
    new_times = torch.arange(float(times[0]), float(times[-1]) + 1e-9, 1.0 / fps, dtype=torch.float64)
    hi = torch.searchsorted(times, new_times).clamp(1, len(times) - 1)
    lo = hi - 1
    w = ((new_times - times[lo]) / (times[hi] - times[lo])).clamp(0, 1)
    fields = {}
    for device in sg.DEVICES:
        r, p = getattr(stream, f"{device}_rotations"), getattr(stream, f"{device}_positions")
        q = rot.matrix_to_quat(torch.nan_to_num(r).float() + torch.isnan(r).any((-1, -2))[..., None, None] * torch.eye(3))
        fields[f"{device}_rotations"] = rot.quat_to_matrix(rot.quat_slerp(q[lo], q[hi], w.float())).double()
        p = torch.nan_to_num(p)
        fields[f"{device}_positions"] = p[lo] * (1 - w[:, None]) + p[hi] * w[:, None]
    exact_lo, exact_hi = (w < 1e-9)[:, None], (w > 1 - 1e-9)[:, None]
    visible = (stream.visible[lo] | exact_hi) & (stream.visible[hi] | exact_lo)
    for k, device in enumerate(("left", "right")):
        hidden = ~visible[:, k]
        fields[f"{device}_rotations"][hidden] = float("nan")
        fields[f"{device}_positions"][hidden] = float("nan")
    return HeadsetStream(new_times, visible=visible, **fields)

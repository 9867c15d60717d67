"""The plausibility gate: headset samples a person cannot have produced never reach the network.

Tracking glitches (a headset sample a kilometre away for one frame, NaN, a matrix that is not a
rotation) would otherwise enter the network's recurrent state and its integrated root, which
then never recover (measured before this gate: one head sample 1 km away collapsed the body to a
point 30 s later). :class:`HeadsetGate` judges each frame before the network sees it:

- a pose is *invalid* when it holds NaN or infinity, or its matrix is not a rotation
  (``R^T R`` off the identity by more than ``orthonormal_tolerance``, or a reflection);
- a pose is *implausible* when it moved farther or turned more since the device's last accepted
  pose than a person can in the time between (:class:`GateLimits`; ``slack`` absorbs tracking
  noise at high frame rates), or, for a hand, when it is out of reach of the head.

A rejected hand counts as unseen on that frame (the network handles unseen hands by design). A
rejected head is *held*: the tracker returns its last pose and does not run the network; on the
first accepted head after a held run the network restarts from that frame (``Verdict.restart``),
so the stream continues exactly as a fresh tracker started there would. A head that jumps and
then stays consistent with itself for ``rebase_s`` seconds (and ``rebase_frames`` frames) is a
user re-centering the view or teleporting: the new place is accepted as the new origin.

Every frame the gate rejects is counted (:class:`Rejections`); the tracker warns once per run of
rejected frames (:class:`TrackingWarning`).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np

DEVICE_NAMES = ("head", "left", "right")


class TrackingWarning(UserWarning):
    """A headset sample was rejected, or the tracker restarted its network."""


@dataclass(frozen=True)
class GateLimits:
    """What a person can do between two samples (SI units).

    head_speed: 12 m/s, about the top speed of the fastest sprinters (Usain Bolt's 100 m record
        peaked near 12.3 m/s); no headset wearer's eyes move faster through space.
    head_turn: 25 rad/s (about 1400 deg/s); the fastest voluntary head turns peak below about
        15 rad/s (head-movement studies report peaks of several hundred deg/s during vigorous
        motion), so this leaves a wide margin.
    hand_speed: 25 m/s; a wrist in a fast punch or a throw reaches about 10-15 m/s, an elite
        baseball pitch about 20-25 m/s at release.
    hand_turn: 60 rad/s (about 3400 deg/s), near the fastest forearm pronation of a pitch.
    reach: 1.5 m, farthest wrist from the eyes: an arm (shoulder to wrist) is about 0.34 of
        standing height, so about 0.75 m at 2.2 m tall, plus 0.35 m from eyes to shoulder and a margin.
    slack: distance (m) and angle (rad) always allowed, for tracking noise at high frame rates.
    orthonormal_tolerance: largest entry of R^T R - I accepted as a rotation (float32 data and
        quaternions read to a few digits pass).
    rebase_s, rebase_frames: a head jump that stays consistent with itself this long (both) is
        accepted as a new origin (re-centering, teleporting).
    max_root_distance: farthest the network's internal root (pelvis) may be from the eyes (m)
        before its state is judged broken and re-initialised (a pelvis is under 1 m from the eyes).
    """

    head_speed: float = 12.0
    head_turn: float = 25.0
    hand_speed: float = 25.0
    hand_turn: float = 60.0
    reach: float = 1.5
    slack: tuple[float, float] = (0.05, 0.1)
    orthonormal_tolerance: float = 0.02
    rebase_s: float = 0.25
    rebase_frames: int = 3
    max_root_distance: float = 3.0


@dataclass
class Rejections:
    """Counts since the stream started. head, left, right: frames whose pose of that device was
    rejected (head held, hand unseen); frames: frames with anything rejected; rebased: jumps
    accepted as a new origin; restarts: times the network was re-initialised (after held head
    frames, or because its state went non-finite or absurd)."""

    head: int = 0
    left: int = 0
    right: int = 0
    frames: int = 0
    rebased: int = 0
    restarts: int = 0

    def __bool__(self) -> bool:
        return bool(self.frames or self.restarts)

    def __str__(self) -> str:
        text = (f"{self.frames} frame{'s' * (self.frames != 1)} with implausible samples rejected "
                f"(head held {self.head}, left hand {self.left}, right hand {self.right})")
        if self.rebased:
            text += f", {self.rebased} head jump{'s' * (self.rebased != 1)} taken as a new origin"
        if self.restarts:
            text += f", network restarted {self.restarts} time{'s' * (self.restarts != 1)}"
        return text


@dataclass
class Verdict:
    """The gate's judgement of one frame: head accepted (False: hold the last pose), hands
    accepted (only meaningful for hands marked visible; False: treat as unseen), restart (run the
    network from a fresh state on this frame), reasons ('device: problem', for warnings)."""

    head: bool
    hands: tuple[bool, bool]
    restart: bool
    reasons: list[str] = field(default_factory=list)


def rotation_problem(matrix, tolerance: float) -> str | None:
    """Why a (3, 3) matrix (array or nested lists) is not a rotation matrix, or None when it is one."""
    return _rotation_problem(np.asarray(matrix, dtype=np.float64).tolist(), tolerance)


# The per-frame checks work on Python floats (nested lists): for 3 x 3 matrices a few float
# operations cost less than the call overhead of the numpy functions doing the same.

def _rotation_problem(m: list, tolerance: float) -> str | None:
    (a, b, c), (d, e, f), (g, h, i) = m
    if not all(map(math.isfinite, (a, b, c, d, e, f, g, h, i))):
        return "NaN or infinity in the rotation"
    gram = (a * a + d * d + g * g - 1.0, b * b + e * e + h * h - 1.0, c * c + f * f + i * i - 1.0,
            a * b + d * e + g * h, a * c + d * f + g * i, b * c + e * f + h * i)       # R^T R - I
    error = max(map(abs, gram))
    if not error <= tolerance:
        return f"not a rotation (R^T R differs from the identity by {error:.3g})"
    if a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) < 0:
        return "not a rotation (a reflection)"
    return None


def turn_angle(a, b) -> float:
    """Angle (rad) of the rotation from rotation matrix a to b ((3, 3) arrays or nested lists)."""
    a, b = np.asarray(a, dtype=np.float64).tolist(), np.asarray(b, dtype=np.float64).tolist()
    return _turn_angle(a, b)


def _turn_angle(a: list, b: list) -> float:
    (a0, a1, a2), (a3, a4, a5), (a6, a7, a8) = a
    (b0, b1, b2), (b3, b4, b5), (b6, b7, b8) = b
    trace = a0 * b0 + a1 * b1 + a2 * b2 + a3 * b3 + a4 * b4 + a5 * b5 + a6 * b6 + a7 * b7 + a8 * b8   # trace(a^T b)
    return math.acos(min(max((trace - 1.0) / 2.0, -1.0), 1.0))


class HeadsetGate:
    """Judges headset frames one by one (module docstring); keeps the last accepted pose of each
    device. counts: :class:`Rejections` since the last reset()."""

    def __init__(self, limits: GateLimits | None = None):
        self.limits = limits or GateLimits()
        self.reset()

    def reset(self) -> None:
        """Forget the stream."""
        self.counts = Rejections()
        self._good: list[tuple | None] = [None, None, None]     # per device: (rotation, position, time)
        self._candidate: tuple | None = None                     # a jumped head: (rotation, position, time, start, frames)
        self._held = False                                       # the previous frame's head was held
        self._rejecting = [False, False, False]                  # a run of rejections is going on (warn once per run)

    # -- one device --------------------------------------------------------------------------
    def _problem(self, device: int, rotation: list, position: list) -> str | None:
        """Why a device's pose is invalid (not finite, not a rotation), or None."""
        if not all(map(math.isfinite, position)):
            return "NaN or infinity in the position"
        return _rotation_problem(rotation, self.limits.orthonormal_tolerance)

    def _jump(self, device: int, rotation, position, time: float, reference: tuple | None) -> str | None:
        """Why the pose moved or turned faster than a person can since reference, or None."""
        if reference is None:
            return None
        limits = self.limits
        speed, turn = (limits.head_speed, limits.head_turn) if device == 0 else (limits.hand_speed, limits.hand_turn)
        dt = max(time - reference[2], 0.0)
        distance = math.dist(position, reference[1])
        if distance > speed * dt + limits.slack[0]:
            return f"moved {distance:.3g} m in {dt:.3g} s (limit {speed:g} m/s)"
        allowed = turn * dt + limits.slack[1]
        angle = _turn_angle(reference[0], rotation) if allowed < math.pi else 0.0
        if angle > allowed:
            return f"turned {math.degrees(angle):.0f} deg in {dt:.3g} s (limit {turn:g} rad/s)"
        return None

    # -- one frame ---------------------------------------------------------------------------
    def check(self, rotations: np.ndarray, positions: np.ndarray, visible, time: float) -> Verdict:
        """Judge one frame: rotations (3, 3, 3) and positions (3, 3) of head, left and right
        wrist (metres; a hand's values are read only when visible), visible (2,) hand flags,
        time in seconds (finite, not decreasing). Updates the counts; warns (TrackingWarning)
        once per run of rejected frames of a device."""
        reasons = []
        rotations, positions, time = rotations.tolist(), positions.tolist(), float(time)
        if not math.isfinite(time):
            reasons.append("the timestamp is not a number: the frame is ignored")
            verdict = Verdict(False, (False, False), False, reasons)
            self._held = True
            self._count(verdict, [bool(v) for v in visible])
            return verdict
        head_ok, restart = self._check_head(rotations[0], positions[0], time, reasons)
        head_position = positions[0] if head_ok else (self._good[0][1] if self._good[0] else None)
        hands = []
        for k in (1, 2):
            ok = True
            if visible[k - 1]:
                ok = self._check_hand(k, rotations[k], positions[k], time, head_position, reasons)
            hands.append(ok)
        verdict = Verdict(head_ok, (hands[0], hands[1]), restart, reasons)
        self._count(verdict, [bool(v) for v in visible])
        return verdict

    def _check_head(self, rotation, position, time: float, reasons: list) -> tuple[bool, bool]:
        """(accepted, restart) for the head."""
        problem = self._problem(0, rotation, position)
        if problem is None:
            problem = self._jump(0, rotation, position, time, self._good[0])
            if problem is not None and self._persistent_jump(rotation, position, time):
                reasons.append(f"head: jumped {math.dist(position, self._good[0][1]):.3g} m and "
                               f"stayed there {self.limits.rebase_s:g} s: taken as a new origin (re-centred or teleported)")
                self.counts.rebased += 1
                self._good = [None, None, None]      # hands are judged afresh from the new place
                problem = None
        if problem is not None:
            reasons.append(f"head: {problem}; held at its last accepted pose")
            self._held = True
            return False, False
        restart, self._held, self._candidate = self._held, False, None
        self._good[0] = (rotation, position, time)
        return True, restart

    def _persistent_jump(self, rotation, position, time: float) -> bool:
        """Track a head that jumped: True once it has stayed consistent for the rebase time."""
        candidate = self._candidate
        if candidate is None or self._jump(0, rotation, position, time, candidate) is not None:
            self._candidate = (rotation, position, time, time, 1)
            return False
        start, frames = candidate[3], candidate[4] + 1
        self._candidate = (rotation, position, time, start, frames)
        return frames >= self.limits.rebase_frames and time - start >= self.limits.rebase_s - 1e-9

    def _check_hand(self, k: int, rotation, position, time: float, head_position, reasons: list) -> bool:
        problem = self._problem(k, rotation, position)
        if problem is None and head_position is not None:
            distance = math.dist(position, head_position)
            if distance > self.limits.reach:
                problem = f"{distance:.3g} m from the head (reach {self.limits.reach:g} m)"
        if problem is None:
            problem = self._jump(k, rotation, position, time, self._good[k])
        if problem is not None:
            reasons.append(f"{DEVICE_NAMES[k]} hand: {problem}; treated as unseen")
            return False
        self._good[k] = (rotation, position, time)
        return True

    def _count(self, verdict: Verdict, visible: list[bool]) -> None:
        rejected = [not verdict.head, visible[0] and not verdict.hands[0], visible[1] and not verdict.hands[1]]
        counts = self.counts
        counts.head += rejected[0]
        counts.left += rejected[1]
        counts.right += rejected[2]
        counts.frames += any(rejected)
        starting = [r and not was for r, was in zip(rejected, self._rejecting)]
        self._rejecting = rejected
        if any(starting) or any(r.startswith("head: jumped") for r in verdict.reasons):
            warnings.warn("implausible headset sample: " + "; ".join(verdict.reasons), TrackingWarning, stacklevel=4)


def gate_stream(stream, limits: GateLimits | None = None):
    """The gate run over a whole recording, frame by frame, as SparseTracker.update runs it.

    stream: a humotion.sparse.recording.HeadsetStream. Returns (the stream with rejected hands
    unseen (NaN) and held heads at their last accepted pose, held (T,) bool: frames whose head
    was held, on which the network does not run (frames before the first usable head are held
    at it), Rejections). One TrackingWarning sums the rejections up. Raises ValueError when no
    frame has a usable head pose.
    """
    import torch

    from humotion.sparse.recording import HeadsetStream

    gate = HeadsetGate(limits)
    rotations, positions = stream.rotations.numpy().copy(), stream.positions.numpy().copy()
    visible, times = stream.visible.numpy().copy(), stream.timestamps.numpy()
    held = np.zeros(len(times), dtype=bool)
    first_reasons: list[str] = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", TrackingWarning)
        for t in range(len(times)):
            verdict = gate.check(rotations[t], positions[t], visible[t], float(times[t]))
            first_reasons = first_reasons or verdict.reasons
            if not verdict.head:
                held[t] = True
                if gate._good[0] is not None:
                    rotations[t, 0], positions[t, 0] = gate._good[0][0], gate._good[0][1]
            for k, accepted in enumerate(verdict.hands):
                if not accepted or not visible[t, k]:
                    visible[t, k], rotations[t, k + 1], positions[t, k + 1] = False, np.nan, np.nan
    if held.all():
        raise ValueError(f"no frame of the recording has a usable head pose ({first_reasons[0]})")
    first = int(np.argmin(held))
    rotations[:first, 0], positions[:first, 0] = rotations[first, 0], positions[first, 0]
    if gate.counts:
        warnings.warn(f"{gate.counts}; first: {first_reasons[0]}", TrackingWarning, stacklevel=3)
    r, p = torch.from_numpy(rotations), torch.from_numpy(positions)
    cleaned = HeadsetStream(stream.timestamps, r[:, 0], p[:, 0], r[:, 1], p[:, 1], r[:, 2], p[:, 2],
                            torch.from_numpy(visible))
    return cleaned, torch.from_numpy(held), gate.counts

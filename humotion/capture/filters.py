"""Smoothing 2D keypoints over time: the One-Euro filter (Casiez, Roussel & Vogel, CHI 2012).

A One-Euro filter is a first-order low-pass filter whose cutoff frequency rises with speed: slow
movement is smoothed hard (jitter disappears), fast movement hardly at all (little lag). For a
sample x_t arriving Te seconds after the previous one:

    alpha(Te, fc) = 1 / (1 + tau / Te),   tau = 1 / (2 pi fc)
    dx_t  = (x_t - x^_{t-1}) / Te,        dx^_t = dx^_{t-1} + alpha(Te, d_cutoff) (dx_t - dx^_{t-1})
    fc    = min_cutoff + beta |dx^_t|,    x^_t  = x^_{t-1}  + alpha(Te, fc) (x_t - x^_{t-1})

Here each keypoint is one filter over its (x, y) position, and |dx^| is the norm of its filtered
velocity, so both coordinates of a point share one cutoff. Te comes from the timestamps, per
keypoint: a keypoint that was held (see below) for a while takes the whole gap as its Te.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class OneEuroConfig:
    """Settings of the One-Euro keypoint filter (each field's docstring says what it does; the
    `humotion capture` options --filter-cutoff and --filter-beta are made from min_cutoff's and beta's)."""

    enabled: bool = True
    """False passes keypoints through untouched."""
    min_cutoff: float = 1.0
    """One-Euro cutoff at rest, Hz: lower removes more jitter from still keypoints, adds lag."""
    beta: float = 0.02
    """One-Euro speed coefficient, Hz per (pixel/s), how fast the cutoff rises with speed: higher follows
    fast moves with less lag, lets more jitter through while moving. Pixels: tune for the video's resolution."""
    d_cutoff: float = 1.0
    """Hz, the cutoff of the low-pass filter on the velocity that drives the cutoff."""
    min_confidence: float = 0.0
    """A keypoint of this confidence or lower does not update its filter: it keeps its last filtered
    position and is reported with confidence 0."""

    def __post_init__(self):
        if not (self.min_cutoff > 0 and self.d_cutoff > 0):
            raise ValueError(f"min_cutoff and d_cutoff must be positive (Hz), got {self.min_cutoff}, {self.d_cutoff}")
        if not self.beta >= 0:
            raise ValueError(f"beta must be zero or positive, got {self.beta}")


def smoothing_factor(dt: np.ndarray | float, cutoff: np.ndarray | float) -> np.ndarray:
    """alpha = 1 / (1 + tau / dt), tau = 1 / (2 pi cutoff): dt seconds, cutoff Hz, numbers or
    arrays of any shapes that broadcast; float64 in their broadcast shape."""
    tau = 1.0 / (2.0 * np.pi * np.asarray(cutoff, dtype=np.float64))
    return 1.0 / (1.0 + tau / np.asarray(dt, dtype=np.float64))


class OneEuroFilter:
    """A One-Euro filter over K points (usually one person's (21, 2) keypoints); see the module doc.

    Call it once per frame with strictly increasing timestamps; reset() forgets the past (for a
    new take, or a person seen again after a long time).
    """

    def __init__(self, config: OneEuroConfig | None = None):
        self.config = config if config is not None else OneEuroConfig()
        self.reset()

    def reset(self) -> None:
        """Forget every past sample: the next call returns its input."""
        self._value: np.ndarray | None = None  # (K, D) filtered positions
        self._velocity: np.ndarray | None = None  # (K, D) filtered velocities, units per second
        self._updated_at: np.ndarray | None = None  # (K,) seconds of each point's last update, NaN before
        self._last_timestamp: float | None = None

    def __call__(
        self, keypoints: np.ndarray, confidence: np.ndarray, timestamp: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Filter one frame.

        keypoints: (K, D) positions (pixels for 2D keypoints). confidence: (K,) in [0, 1].
        timestamp: seconds, greater than the previous call's.
        Returns the filtered keypoints (K, D) float32 and their confidence (K,) float32: the input's,
        or 0 for a keypoint held at its last filtered position (confidence <= min_confidence). A
        keypoint never seen with enough confidence is returned as given, with confidence 0.
        """
        keypoints = np.asarray(keypoints, dtype=np.float64)
        confidence = np.asarray(confidence, dtype=np.float32)
        if keypoints.ndim != 2 or confidence.shape != keypoints.shape[:1]:
            raise ValueError(
                f"expected keypoints (K, D) and confidence (K,), got {keypoints.shape} and {confidence.shape}"
            )
        if not self.config.enabled:
            return keypoints.astype(np.float32), confidence.copy()
        if self._last_timestamp is not None and not timestamp > self._last_timestamp:
            raise ValueError(f"timestamps must increase: got {timestamp} s after {self._last_timestamp} s")
        if self._value is None:
            self._value = keypoints.copy()
            self._velocity = np.zeros_like(keypoints)
            self._updated_at = np.full(len(keypoints), np.nan)
        elif self._value.shape != keypoints.shape:
            raise ValueError(f"expected keypoints {self._value.shape} as before, got {keypoints.shape}; reset() first")
        self._last_timestamp = float(timestamp)

        observed = confidence > self.config.min_confidence
        seen_before = ~np.isnan(self._updated_at)
        self._value[~seen_before] = keypoints[~seen_before]  # starts from its first sample
        moving = observed & seen_before
        if moving.any():
            self._step(moving, keypoints[moving], timestamp - self._updated_at[moving])
        self._updated_at[observed] = timestamp
        return self._value.astype(np.float32), np.where(observed, confidence, np.float32(0.0))

    def _step(self, points: np.ndarray, samples: np.ndarray, dt: np.ndarray) -> None:
        """One filter update of the given points: samples (N, D), dt (N,) seconds since their last."""
        config, value, velocity = self.config, self._value[points], self._velocity[points]
        raw_velocity = (samples - value) / dt[:, None]
        velocity += smoothing_factor(dt, config.d_cutoff)[:, None] * (raw_velocity - velocity)
        cutoff = config.min_cutoff + config.beta * np.linalg.norm(velocity, axis=1)
        value += smoothing_factor(dt, cutoff)[:, None] * (samples - value)
        self._value[points], self._velocity[points] = value, velocity

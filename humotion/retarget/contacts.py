"""Foot contacts, and the foot-skating and contact-preservation measures of retargeting.

A foot point (ankle or toes) touches the ground when it is both near its lowest height of the
surrounding second and a half (not of the whole clip: CMU floors are not level, a planted ankle
rises by 5 cm over a 3 s walk) and slow. Thresholds are for a 1.70 m figure and scale with
its height.
"""

from __future__ import annotations

import torch

REFERENCE_HEIGHT = 1.70  # metres: the thresholds below are for a figure this tall
CONTACT_HEIGHT = 0.05    # metres above the local floor
CONTACT_SPEED = 0.30     # metres per second
FLOOR_WINDOW = 1.5       # seconds over which the local floor is the lowest height


def speeds(points: torch.Tensor, fps: float, horizontal: bool = False) -> torch.Tensor:
    """(T, K) speed of (T, K, 3) points in metres per second (central differences; X-Z plane
    only when horizontal)."""
    if points.shape[0] < 2:
        return torch.zeros(points.shape[:2], dtype=points.dtype)
    velocity = torch.gradient(points, dim=0)[0] * fps
    if horizontal:
        velocity = velocity[..., [0, 2]]
    return velocity.norm(dim=-1)


def foot_contacts(points: torch.Tensor, fps: float, figure_height: float = REFERENCE_HEIGHT) -> torch.Tensor:
    """(T, K) bool: which of the (T, K, 3) foot points (metres, Y up) touch the ground per frame."""
    scale = figure_height / REFERENCE_HEIGHT
    height = points[..., 1].T[:, None]                                  # (K, 1, T)
    window = max(1, int(FLOOR_WINDOW * fps)) | 1                        # odd
    floor = -torch.nn.functional.max_pool1d(-height, window, stride=1, padding=window // 2)
    low = (height - floor)[:, 0].T < CONTACT_HEIGHT * scale
    return low & (speeds(points, fps) < CONTACT_SPEED * scale)


def foot_skating(points: torch.Tensor, contacts: torch.Tensor, fps: float) -> float:
    """Mean horizontal speed (metres per second) of (T, K, 3) foot points over the (T, K) frames
    marked in contact; 0 when none is."""
    if not contacts.any():
        return 0.0
    return float(speeds(points, fps, horizontal=True)[contacts].mean())


def contacts_kept(source: torch.Tensor, target: torch.Tensor) -> float:
    """Share of the source's (T, K) contacts where the target's (T, K) contacts hold too."""
    if not source.any():
        return 1.0
    return float((target & source).sum() / source.sum())


def floor_height(points: torch.Tensor) -> float:
    """Height of the floor a motion stands on, metres: the 5th percentile over frames of the
    lowest of its points (T, K, 3) (robust to a few frames through the floor; a take that is
    mostly in the air reads too high)."""
    return float(torch.quantile(points[..., 1].amin(-1).double(), 0.05))

"""Checks of the body model's inputs: numbers made tensors of the model's dtype and device, their
shapes and batch sizes checked. Each failure is a ValueError naming the parameter:

    shape = checked("shape", shape, (body.config.shape_latent,), body.template)   # (B, shape_latent)
    batch = batch_size(shape=shape, pose=rotations)                               # 1 or the larger B
"""

from __future__ import annotations

import math

import numpy as np
import torch


def all_finite(values: torch.Tensor) -> bool:
    """Whether every number of `values` (a float tensor of any shape) is finite: from their sum,
    unless the sum overflows, and only then by a test of each (the sum is the cheaper of the two)."""
    return math.isfinite(values.sum().item()) or bool(torch.isfinite(values).all())


def checked_tensor(name: str, value, like: torch.Tensor) -> torch.Tensor:
    """value (numbers, an array or a tensor, any shape) as a tensor of the same shape and of the
    dtype and device of `like` (the model's template); ValueError naming the parameter `name` for
    non-numbers, NaN or infinity."""
    if not torch.is_tensor(value):
        try:
            value = torch.as_tensor(np.asarray(value, dtype=np.float32))
        except (TypeError, ValueError) as error:
            raise ValueError(f"{name} must be numbers, got {type(value).__name__}") from error
    if not value.is_floating_point():
        value = value.float()
    if not all_finite(value):
        raise ValueError(f"{name} contains NaN or infinite values")
    return value.to(dtype=like.dtype, device=like.device)


def checked(name: str, value, shape: tuple[int, ...], like: torch.Tensor) -> torch.Tensor:
    """value, (B, *shape) or (*shape), as a (B, *shape) tensor like `like`; a single unbatched value
    becomes batch 1;
    ValueError naming the parameter for a wrong shape (and as in :func:`checked_tensor`)."""
    value = checked_tensor(name, value, like)
    if tuple(value.shape[-len(shape):]) != shape or value.dim() not in (len(shape), len(shape) + 1):
        expected = ", ".join(str(s) for s in shape)
        raise ValueError(f"{name} must be (B, {expected}), got {tuple(value.shape)}")
    return value if value.dim() == len(shape) + 1 else value[None]


def batch_size(**inputs: torch.Tensor | None) -> int:
    """The batch size B of named inputs (each (B, ...) or (1, ...), or None): the largest; ValueError
    naming an input whose batch size is neither 1 nor B."""
    sizes = {k: len(v) for k, v in inputs.items() if v is not None}
    batch = max(sizes.values(), default=1)
    for name, size in sizes.items():
        if size not in (1, batch):
            others = ", ".join(f"{k} {n}" for k, n in sizes.items())
            raise ValueError(f"{name} has batch size {size}, which matches neither 1 nor {batch} ({others})")
    return batch

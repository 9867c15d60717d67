"""What the body model derives from its weights for inference and keeps between calls: the dense
and blocked skinning weights, the shape decoder's summed products, the neutral expression's
decoding, the torch path's cuts of the weights into blocks and the compiled path's float16 copies
of the big weight matrices.

    derived = DerivedTensors()
    weights = derived.get("skin", [skin.logits], skin)            # skin() once, while logits are unchanged
    half = derived.float16_bits("shape", weight, batch)           # (R, K) uint16 or None
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
import torch

from humotion.body.cpu_posing import half_bits, uses_float16
from humotion.body.skinning import needs_gradient


class DerivedTensors:
    """Values computed from tensors, one under each key, recomputed when one of the tensors has
    changed (another storage or device, or changed in place: torch's version counter) and
    computed afresh, not kept, while a gradient is wanted through them (training). A changed
    tensor's value replaces the old one. (functools.lru_cache keys on the arguments' identity,
    so it would miss the in-place updates of an optimiser step and keep every version.)"""

    def __init__(self):
        self._kept: dict[str, tuple[tuple, Any]] = {}

    def get(self, key: str, tensors: list[torch.Tensor], compute: Callable[[], Any]) -> Any:
        """compute(), reused while `tensors` (any shape) are unchanged and no gradient is wanted
        through them."""
        if needs_gradient(*tensors):
            return compute()
        stamp = tuple((t.data_ptr(), t._version, t.device) for t in tensors)
        hit = self._kept.get(key)
        if hit is not None and hit[0] == stamp:
            return hit[1]
        value = compute()
        self._kept[key] = (stamp, value)
        return value

    def float16_bits(self, name: str, weight: torch.Tensor, batch: int) -> np.ndarray | None:
        """The compiled path's float16 copy (:func:`humotion.body.cpu_posing.half_bits`) of a big
        weight matrix (R, K) for a product with `batch` bodies: made on first use and kept; None
        where the products stay in float32 (:func:`humotion.body.cpu_posing.uses_float16`) or
        float16 does not hold the matrix."""
        if not uses_float16(batch):
            return None
        return self.get(f"float16/{name}", [weight], lambda: half_bits(weight))

    def kept(self, prefix: str = "") -> dict[str, Any]:
        """The values kept now under keys that start with prefix ("float16/": the float16 copies)."""
        return {key: value for key, (_, value) in self._kept.items() if key.startswith(prefix)}

    def clear(self) -> None:
        """Forget every kept value."""
        self._kept.clear()

"""Shared numerical optimisation: L-BFGS on a scalar energy, as the refinements use it."""

from __future__ import annotations

from typing import Callable, Sequence

import torch


def minimise_lbfgs(parameters: Sequence[torch.Tensor], energy: Callable[[], torch.Tensor], iterations: int) -> None:
    """Minimise energy(), a scalar tensor, over parameters (tensors of any shape with
    requires_grad, changed in place) with L-BFGS: history 10, learning rate 1, strong Wolfe line
    search, at most `iterations` steps."""
    optimizer = torch.optim.LBFGS(list(parameters), lr=1.0, history_size=10, max_iter=iterations,
                                  line_search_fn="strong_wolfe")

    def closure() -> torch.Tensor:
        optimizer.zero_grad()
        value = energy()
        value.backward()
        return value

    optimizer.step(closure)

"""Shared numerical optimisation: L-BFGS on a scalar energy, as the refinements use it."""

from __future__ import annotations

from typing import Callable, Sequence

import torch


def minimise_lbfgs(parameters: Sequence[torch.Tensor], energy: Callable[[], torch.Tensor], iterations: int) -> None:
    """Minimise energy(), a scalar tensor differentiable (autograd) in parameters (tensors of any
    shape with requires_grad, changed in place), with :func:`minimise_lbfgs_with_gradient`."""
    parameters = list(parameters)

    def evaluate() -> tuple[float, list[torch.Tensor]]:
        value = energy()
        gradients = torch.autograd.grad(value, parameters, allow_unused=True, materialize_grads=True)
        return float(value.detach()), list(gradients)

    minimise_lbfgs_with_gradient(parameters, evaluate, iterations)


def minimise_lbfgs_with_gradient(parameters: Sequence[torch.Tensor],
                                 evaluate: Callable[[], tuple[float, Sequence[torch.Tensor]]], iterations: int) -> None:
    """Minimise an energy over parameters (tensors of any shape, changed in place) with L-BFGS:
    history 10, learning rate 1, strong Wolfe line search, at most `iterations` steps.
    evaluate() returns the energy at the parameters' current values and its gradient, one tensor
    like each parameter."""
    parameters = list(parameters)
    optimizer = torch.optim.LBFGS(parameters, lr=1.0, history_size=10, max_iter=iterations,
                                  line_search_fn="strong_wolfe")

    def closure() -> float:
        value, gradients = evaluate()
        for parameter, gradient in zip(parameters, gradients):
            parameter.grad = gradient
        return value

    optimizer.step(closure)

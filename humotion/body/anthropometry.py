"""Anthropometry of the body model, as Anny measures bodies: the height, volume, weight and BMI
of rest meshes, and the shape latent of a body of a given height and weight.

    measured = measure(rest_vertices, body.faces, body.volume_scale)   # {"height", "weight", "bmi"}: (B,) each
    shape = shape_from_measurements(body, height=[1.80], weight=[75.0])   # (1, shape_latent)

(:class:`~humotion.body.model.BodyModel` offers both as methods.) Metres, kilograms, kg / m^2.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from humotion.body.checks import checked_tensor

if TYPE_CHECKING:
    from humotion.body.model import BodyModel

DENSITY = 980.0
"""kg / m^3 of the body (Anny's anthropometry: mass = volume x 980)."""


def mesh_height(vertices: torch.Tensor) -> torch.Tensor:
    """(B, V, 3) -> (B,) vertical extent (m): Anny's height of a rest mesh."""
    heights = vertices[..., 1]   # contiguous for the forward pass's planar meshes
    return heights.amax(-1) - heights.amin(-1)   # faster than torch.aminmax (bench/body_products.py)


def mesh_volume(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """(B, V, 3), (faces, 3) -> (B,) enclosed volume (m^3) by the divergence theorem."""
    v0, v1, v2 = (vertices[:, faces[:, k]] for k in range(3))
    return (torch.linalg.cross(v0, v1, dim=-1) * v2).sum(-1).sum(-1).abs() / 6.0


def measure(rest_vertices: torch.Tensor, faces: torch.Tensor, volume_scale: torch.Tensor) -> dict[str, torch.Tensor]:
    """Height (m), weight (kg: volume x DENSITY x volume_scale) and BMI (kg / m^2), (B,) each, of
    rest meshes (B, V, 3) with faces (faces, 3); volume_scale () calibrates a mesh's volume to the
    full-resolution mesh's (the body model's buffer of that name)."""
    height = mesh_height(rest_vertices)
    weight = mesh_volume(rest_vertices, faces) * DENSITY * volume_scale
    return {"height": height, "weight": weight, "bmi": weight / height.square()}


def measurement_features(height: torch.Tensor, weight: torch.Tensor, stats: torch.Tensor) -> torch.Tensor:
    """height (B,) (m), weight (B,) (kg) -> (B, 4) inputs of the measurement regressor: 1,
    standardised height and weight, and their product; stats (2, 2): the mean and standard
    deviation of height (row 0) and weight (row 1) over the training bodies."""
    h = (height - stats[0, 0]) / stats[0, 1]
    w = (weight - stats[1, 0]) / stats[1, 1]
    return torch.stack([torch.ones_like(h), h, w, h * w], dim=-1)


def shape_from_measurements(body: BodyModel, height, weight, iterations: int = 30, prior: float = 0.01) -> torch.Tensor:
    """Shape latents (B, shape_latent) of bodies with the given heights (m) and weights (kg),
    each (B,) or a number: the body model's measurement regressor's latent for them (trained on
    the training bodies' measurements), then optimised (L-BFGS, `iterations` at most) until the
    decoded mesh measures them, staying near the regressor's latent (prior weight). ValueError
    for a height, weight or BMI outside the ranges the model was trained on."""
    height = checked_measure("height", height, body.height_range, "m", body.template)
    weight = checked_measure("weight", weight, body.weight_range, "kg", body.template)
    if height.shape != weight.shape:
        if len(height) == 1 or len(weight) == 1:
            height, weight = torch.broadcast_tensors(height, weight)
        else:
            raise ValueError(f"height has {len(height)} values but weight {len(weight)}")
    bmi = weight / height.square()
    low, high = body.bmi_range.tolist()
    bad = (bmi < low) | (bmi > high)
    if bad.any():
        i = int(bad.nonzero()[0])
        raise ValueError(f"weight={weight[i]:.1f} kg at height={height[i]:.2f} m is a BMI of {bmi[i]:.1f}, "
                         f"outside the model's range [{low:.1f}, {high:.1f}]")
    start = measurement_features(height, weight, body.measurement_stats) @ body.measurement_regressor
    latent = start.clone().requires_grad_(True)
    optimizer = torch.optim.LBFGS([latent], lr=1.0, max_iter=iterations, line_search_fn="strong_wolfe")

    def closure():
        optimizer.zero_grad()
        measured = measure(body.decode_shape(latent), body.faces, body.volume_scale)
        loss = (((measured["height"] - height) / 0.005).square() + ((measured["weight"] - weight) / 0.5).square()
                + prior * (latent - start).square().sum(-1)).sum()
        loss.backward()
        return loss

    with torch.enable_grad():
        optimizer.step(closure)
    return latent.detach()


def checked_measure(name: str, value, bounds: torch.Tensor, unit: str, like: torch.Tensor) -> torch.Tensor:
    """value (a number or (B,)) as a (B,) tensor like `like`; ValueError naming the parameter for
    a value outside bounds (2,) (low, high, in `unit`) or as in :func:`~humotion.body.checks.checked_tensor`."""
    value = checked_tensor(name, value, like).reshape(-1)
    low, high = bounds.tolist()
    bad = (value < low) | (value > high)
    if bad.any():
        raise ValueError(f"{name}={float(value[bad][0]):g} {unit} is outside the model's range "
                         f"[{low:.2f}, {high:.2f}] {unit}")
    return value

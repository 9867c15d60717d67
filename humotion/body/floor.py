"""Feet on the floor through a whole motion: the body's vertical offset per frame from its feet's
contacts with the floor.

    offsets, contacts = floor_offsets(heights, points, fps)   # (T,) m to add to the root's height

A motion retargeted onto another body stands on the floor where the source did only up to the
differences between the two bodies (leg proportions, foot shape, ankle heights), and those
differences change with the pose: with only the first frame's ankles put on the floor, a walk's
lowest vertex sinks below the floor and rises above it by centimetres over the clip. Here each
foot's lowest vertex and centre are followed (:func:`lowest_foot_points`); a foot is in contact
(:func:`floor_contacts`) on frames where it moves slowly with its lowest vertex near the floor, for
a tenth of a second at least; on a frame with a contact the offset puts the lowest foot vertex on
y = 0; between contacts (a jump, a step off a box) the offset is interpolated linearly, so a foot
in the air stays in the air; the offsets are then smoothed (:func:`floor_offsets`). A motion with
no contact keeps a zero offset.
"""

from __future__ import annotations

import numpy as np
import torch

from humotion.body.skinning import linear_blend_skinning, skinning_transforms


def foot_vertices(weights: torch.Tensor, joint_names, parents, threshold: float = 0.5) -> list[np.ndarray]:
    """[left, right] vertex indices skinned mostly (weight of the foot bone's subtree above
    threshold) to foot.L / foot.R; weights (V, J)."""
    names, parents = list(joint_names), [int(p) for p in parents]
    out = []
    for side in ("L", "R"):
        subtree = {names.index(f"foot.{side}")}
        for j, p in enumerate(parents):
            if p in subtree:
                subtree.add(j)
        share = weights[:, sorted(subtree)].sum(1)
        out.append(np.flatnonzero(np.asarray(share) > threshold))
    return out


def lowest_foot_points(model, rest_vertices: torch.Tensor, rest_joints: torch.Tensor, rotations: torch.Tensor,
                       translation: torch.Tensor, chunk: int = 512) -> torch.Tensor:
    """(T, 2, 2, 3): per frame and foot (left, right), the foot's lowest vertex and the mean of its
    vertices, of a body posed by the model's skinning (pose correctives left out: they move the
    feet by millimetres): rest_vertices (V, 3), rest_joints (J, 3), rotations (T, J, 3, 3) local
    rig rotations, translation (T, 3) of the root from its rest position; metres."""
    weights = model.skinning_weights().detach()
    feet = foot_vertices(weights, model.joint_names, model.parents)
    index = torch.as_tensor(np.concatenate(feet))
    side = torch.as_tensor(np.repeat([0, 1], [len(f) for f in feet]))
    out = []
    with torch.no_grad():
        for start in range(0, len(rotations), chunk):
            R, t = rotations[start:start + chunk], translation[start:start + chunk]
            A, b, _ = skinning_transforms(rest_joints, model.parents, R, t)
            posed = linear_blend_skinning(rest_vertices[index], weights[index], A, b)   # (f, n, 3)
            points = []
            for k in (0, 1):
                mine = posed[:, side == k]
                low = mine[..., 1].argmin(1)
                points.append(torch.stack([mine[torch.arange(len(mine)), low], mine.mean(1)], 1))
            out.append(torch.stack(points, 1))
    return torch.cat(out)


def floor_contacts(points: np.ndarray, fps: float, speed: float = 1.0, near: float = 0.05,
                   hold: float = 0.1, window: float = 1.0) -> np.ndarray:
    """(T, 2) bool: frames where each foot (points (T, 2, 2, 3), m: its lowest vertex and its
    centre, :func:`lowest_foot_points`) is in contact with the floor: its centre moves slower than
    `speed` m/s horizontally (central differences; a stance foot rolls from heel to toe, a
    swinging one moves several times faster), its lowest vertex lies within `near` m of the
    floor level nearby in time (the lowest foot vertex within `window` seconds around the frame:
    the floor the source's placement gives drifts over a clip), and both hold for `hold` seconds
    at least."""
    points = np.asarray(points, dtype=np.float64)
    count = len(points)
    if count < 2:
        return np.ones((count, 2), dtype=bool)
    velocity = np.gradient(points[:, :, 1], axis=0) * fps
    slow = np.linalg.norm(velocity[..., [0, 2]], axis=-1) < speed
    heights = points[:, :, 0, 1]
    lower = heights.min(1)
    reach = max(1, int(round(window * fps / 2)))
    floor = np.array([lower[max(0, f - reach):f + reach + 1].min() for f in range(count)])
    contact = slow & (heights < floor[:, None] + near)
    run = min(max(1, int(round(hold * fps))), count)   # a motion shorter than `hold`: all of it
    for k in (0, 1):   # drop runs shorter than `hold`
        f = 0
        while f < count:
            if not contact[f, k]:
                f += 1
                continue
            end = f
            while end < count and contact[end, k]:
                end += 1
            if end - f < run:
                contact[f:end, k] = False
            f = end
    return contact


def floor_offsets(points: np.ndarray, fps: float, smooth: float = 0.05, **contact_options) -> tuple[np.ndarray, np.ndarray]:
    """(offsets (T,) m, contacts (T, 2) bool) for the feet's points (T, 2, 2, 3) before the offsets
    (:func:`lowest_foot_points`, m, y up). On a frame with a contact the offset puts the lower
    foot's lowest vertex on y = 0 (the foot in contact, or the other one landing below it); between
    contact frames it is interpolated linearly (a foot in the air stays in the air), but never
    leaves a foot below the floor; then it is smoothed (Gaussian, `smooth` s)."""
    points = np.asarray(points, dtype=np.float64)
    contacts = floor_contacts(points, fps, **contact_options)
    count = len(points)
    lowest = points[:, :, 0, 1].min(1)
    known = contacts.any(1)
    if not known.any():
        return np.zeros(count), contacts
    frames = np.arange(count)
    offsets = np.maximum(-np.interp(frames, frames[known], lowest[known]), -lowest)
    sigma = smooth * fps
    if sigma > 0.3 and count > 1:
        radius = int(np.ceil(3 * sigma))
        kernel = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
        padded = np.pad(offsets, radius, mode="edge")
        offsets = np.convolve(padded, kernel / kernel.sum(), mode="valid")
    return offsets, contacts

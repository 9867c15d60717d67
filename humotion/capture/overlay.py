"""Drawing 2D skeletons over video frames, to see what the detector and the tracker found.

Bones (`KEYPOINT_BONES`) are lines and joints dots, both in a colour per person id; line widths and
dots scale with the person's size (the height of their keypoint box: :func:`marker_sizes`), so a
small person's limbs stay visible; a dot's size grows with its keypoint's confidence, and
keypoints below a confidence threshold are left out.
Tracked people get a label with their id at the top of their keypoint box.
"""

from __future__ import annotations

import math
from typing import Sequence

import cv2
import numpy as np

from humotion.capture.detection import KEYPOINT_BONES, Detection, keypoint_box
from humotion.capture.people import TrackedPerson
from humotion.io.video import check_image

PALETTE: tuple[tuple[int, int, int], ...] = (
    (230, 25, 75), (60, 180, 75), (0, 130, 200), (245, 130, 48), (145, 30, 180),
    (70, 240, 240), (240, 50, 230), (210, 245, 60), (0, 128, 128), (170, 110, 40),
)  # fmt: skip
"""RGB colours of people, by id modulo its length (well apart from each other and from skin tones)."""


def person_color(person_id: int) -> tuple[int, int, int]:
    """The RGB colour a person's skeleton is drawn in."""
    return PALETTE[person_id % len(PALETTE)]


def draw_people(
    image: np.ndarray, people: Sequence[TrackedPerson | Detection], min_confidence: float = 0.3
) -> np.ndarray:
    """A copy of image ((H, W, 3) uint8 RGB) with each person's 2D skeleton drawn on it.

    people: TrackedPersons (coloured and labelled by id) or Detections (coloured by their place in
    the list, unlabelled), keypoints in pixels of this image. min_confidence: keypoints below it,
    and bones touching them, are not drawn.
    """
    canvas = check_image(image).copy()
    scale = max(1, round(min(canvas.shape[:2]) / 300))  # largest label size, for the image size (less for small people)
    for index, person in enumerate(people):
        tracked = isinstance(person, TrackedPerson)
        color = person_color(person.id if tracked else index)
        shown = (person.confidence >= min_confidence) & np.isfinite(person.keypoints).all(axis=1)
        limit = 4 * max(canvas.shape)  # cv2 needs int coordinates; far-off points are clipped
        points = np.clip(np.round(person.keypoints), -limit, limit).astype(np.int32)
        box_height = float(np.ptp(person.keypoints[shown, 1])) if shown.sum() > 1 else 0.0
        line, dot = marker_sizes(box_height)
        for a, b in KEYPOINT_BONES:
            if shown[a] and shown[b]:
                cv2.line(canvas, tuple(points[a]), tuple(points[b]), color, line, cv2.LINE_AA)
        for point, confidence in zip(points[shown], person.confidence[shown]):
            cv2.circle(canvas, tuple(point), max(1, round(dot * (0.5 + float(confidence)))), color, -1, cv2.LINE_AA)
        if tracked and shown.any():
            _draw_label(canvas, f"id {person.id}", points[shown], color, min(scale, max(1, round(box_height / 150))))
    return canvas


def marker_sizes(box_height: float) -> tuple[int, int]:
    """(line width, dot radius at confidence 0.5) in pixels for a person whose keypoint box is
    box_height pixels tall: 1 and 1 up to 100 px, then growing in proportion (3 and 2 at 300 px)."""
    return max(1, round(box_height / 100)), max(1, round(box_height / 150))


def _draw_label(canvas: np.ndarray, text: str, points: np.ndarray, color: tuple[int, int, int], scale: int) -> None:
    """Write text in white on a box of the person's colour, above the points ((N, 2) int pixels)."""
    x0, y0, _, _ = keypoint_box(points, np.ones(len(points)))
    font_scale = 0.5 * scale
    (width, height), baseline = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, font_scale, scale)
    left, bottom = int(x0), max(int(y0) - 4 * scale, height + baseline)
    cv2.rectangle(canvas, (left, bottom - height - baseline), (left + width, bottom), color, -1)
    cv2.putText(canvas, text, (left, bottom - baseline), cv2.FONT_HERSHEY_SIMPLEX, font_scale,
                (255, 255, 255), scale, cv2.LINE_AA)


def draw_floor(image: np.ndarray, camera, pose, spacing: float = 1.0, extent: float = 20.0,
               color: tuple[int, int, int] = (255, 220, 0)) -> np.ndarray:
    """A copy of image ((H, W, 3) uint8 RGB) with the floor of a camera pose drawn on it: a grid of
    lines `spacing` metres apart out to `extent` metres (world frame of
    humotion.capture.camera.CameraPose, floor y = 0) and the horizon as a dashed line, to see
    whether the estimated floor lies on the one in the picture. camera: the intrinsics
    (humotion.capture.keypoints.VirtualCamera); pose: a CameraPose."""
    import torch

    canvas = check_image(image).copy()
    seen = pose.camera_in_world(camera)
    steps = torch.arange(-extent, extent + 1e-6, spacing)
    along = torch.linspace(-extent, extent, 400)
    lines = [torch.stack([torch.full_like(along, x), torch.zeros_like(along), along], 1) for x in steps]
    lines += [torch.stack([along, torch.zeros_like(along), torch.full_like(along, z)], 1) for z in steps]
    for line in lines:
        pixels, depth = seen.project(line)
        front = (depth > 0.3).numpy()
        points = np.clip(np.round(pixels.numpy()), -1e4, 1e4).astype(np.int32)
        for a, b, ok in zip(points[:-1], points[1:], front[:-1] & front[1:]):
            if ok:
                cv2.line(canvas, tuple(a), tuple(b), color, 1, cv2.LINE_AA)
    # the horizon: points at the camera's height, far away in every direction ahead
    far = torch.stack([torch.cos(a) * torch.tensor([1.0, 0.0, 0.0]) + torch.sin(a) * torch.tensor([0.0, 0.0, -1.0])
                       for a in torch.linspace(0.1, math.pi - 0.1, 60)]) * 1e4 + torch.tensor([0.0, pose.height, 0.0])
    pixels, depth = seen.project(far)
    points = np.round(pixels.numpy()).astype(np.int32)
    for k, (a, b) in enumerate(zip(points[:-1], points[1:])):
        if k % 2 == 0 and depth[k] > 0 and depth[k + 1] > 0 and np.abs(np.concatenate([a, b])).max() < 1e5:
            cv2.line(canvas, tuple(a), tuple(b), (255, 255, 255), 2, cv2.LINE_AA)
    return canvas

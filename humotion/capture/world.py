"""The world frame of captured people, shared by the offline pipeline (humotion.capture.pipeline)
and live capture (humotion.capture.live): Y up, the camera at the origin looking along -Z, so a
person facing the camera faces +Z (the pipeline then places the floor at y = 0 and the camera at
its height; live capture puts the floor under the lowest foot seen so far)."""

from __future__ import annotations

import torch

from humotion.canonical import JOINTS

CAMERA_TO_WORLD = torch.diag(torch.tensor([1.0, -1.0, -1.0]))   # half a turn about x: y down -> Y up
"""(3, 3) camera axes (OpenCV: x right, y down, z forward) -> world axes, for row vectors as p @ M.T."""
FEET = [JOINTS.index(j) for j in ("left_ankle", "right_ankle", "left_foot", "right_foot")]
"""Indices of the canonical joints that stand on the floor."""

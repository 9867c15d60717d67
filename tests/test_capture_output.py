"""Capture's output details: a still image gets overlay.png; overlay markers scale with the person."""

from pathlib import Path

import numpy as np
import pytest
import torch

from humotion.capture.lifting import Lifter, LiftingConfig
from humotion.capture.overlay import draw_people, marker_sizes
from humotion.capture.pipeline import CaptureConfig, capture
from humotion.capture.refine import CaptureRefineConfig
from humotion.capture.detection import KEYPOINTS, Detection

PHOTO = Path(__file__).resolve().parents[2] / "shared" / "data" / "images" / "yogait_cc0" / "tadasana_tada1.jpg"


def test_a_still_image_gets_an_overlay_image(tmp_path):
    from humotion.capture.detection import MediaPipePoseDetector

    if not PHOTO.is_file():
        pytest.skip("test photos missing")
    torch.manual_seed(0)
    with MediaPipePoseDetector(max_people=1) as detector:
        config = CaptureConfig(refine=CaptureRefineConfig(iterations=2, photo_iterations=2))
        result = capture(PHOTO, tmp_path, config, detector=detector,
                         lifter=Lifter(LiftingConfig(channels=16, levels=2)).eval(), progress=False)
    assert tmp_path / "overlay.png" in result.files and (tmp_path / "overlay.png").is_file()
    assert not (tmp_path / "overlay.mp4").exists()
    assert not [p.name for p in tmp_path.rglob("*") if p.suffix in (".tmp", ".partial")]   # written atomically


def test_markers_grow_with_the_person_and_stay_thin_on_small_people():
    assert marker_sizes(100) == (1, 1) and marker_sizes(50) == (1, 1)
    assert marker_sizes(400) == (4, 3)

    def drawn_pixels(tall: float) -> int:
        keypoints = np.zeros((len(KEYPOINTS), 2), np.float32) + 200
        keypoints[:, 1] += np.linspace(-tall / 2, tall / 2, len(KEYPOINTS))
        person = Detection(keypoints, np.ones(len(KEYPOINTS), np.float32), 1.0, (190.0, 150.0, 210.0, 250.0))
        image = np.zeros((600, 400, 3), np.uint8)
        return int((draw_people(image, [person]) != 0).any(-1).sum())

    # a person 100 px tall: lines 1 px wide, so the drawing covers about its length, not a blob
    assert drawn_pixels(100) < 6 * 100

"""PeopleFinder between pose-model runs: optical flow carries a followed person's keypoints (known
answer: a textured frame panned by a known number of pixels per frame)."""

import cv2
import numpy as np
import pytest

from humotion.capture.detection import Detection, keypoint_box
from humotion.capture.follow import PeopleFinder
from humotion.capture.people import PeopleTracker

PAN = 3  # pixels per frame, to the right
BODY = np.array([[0, -80], [-5, -85], [5, -85], [-10, -82], [10, -82], [-25, -60], [25, -60], [-35, -30], [35, -30],
                 [-40, 0], [40, 0], [-15, 0], [15, 0], [-17, 45], [17, 45], [-18, 90], [18, 90],
                 [-18, 90], [18, 90], [-18, 90], [18, 90]], np.float32)  # (21, 2) pixels about the hips


def textured(width: int = 640, height: int = 480) -> np.ndarray:
    noise = np.random.default_rng(0).integers(0, 256, (height, width, 3), dtype=np.uint8)
    return cv2.GaussianBlur(noise, (0, 0), 2.0)


class PannedPersonDetector:
    """A person standing on the texture at (300, 250) in frame 0, moving PAN px per frame with it;
    counts the crops it is asked to look at."""

    def __init__(self):
        self.frame, self.crops = 0, 0

    def truth(self) -> np.ndarray:
        return BODY + np.array([300 + PAN * self.frame, 250], np.float32)

    def person(self) -> Detection:
        confidence = np.r_[np.full(17, 0.9), np.zeros(4)].astype(np.float32)
        keypoints = self.truth()
        return Detection(keypoints, confidence, 0.9, keypoint_box(keypoints, confidence, 0.2))

    def detect(self, image):
        return [self.person()]

    def detect_regions(self, image, regions):
        return [self.person()]

    def refine(self, image, detections):
        return list(detections)

    def detect_near(self, image, boxes):
        self.crops += len(boxes)
        return [self.person() for _ in boxes]


def follow(fps: float, detect_every: int, frames: int = 12) -> tuple[PannedPersonDetector, list[float]]:
    """Run the finder over a panned texture; returns the detector and, per frame, the largest
    distance (pixels) of a confident reported keypoint from the truth."""
    detector, texture = PannedPersonDetector(), textured()
    finder = PeopleFinder(detector, PeopleTracker(), appearance=False, scan_interval=100.0, detect_every=detect_every)
    errors = []
    for frame in range(frames):
        detector.frame = frame
        people = finder(np.roll(texture, PAN * frame, axis=1), frame / fps)
        assert [p.id for p in people] == [0]
        seen = people[0].detection
        errors.append(float(np.linalg.norm(seen.keypoints - detector.truth(), axis=1)[seen.confidence > 0].max()))
    return detector, errors


def test_between_model_runs_optical_flow_carries_the_keypoints_with_the_image():
    detector, errors = follow(30.0, detect_every=2)
    assert detector.crops == 5            # the model on frames 2, 4 ... 10; flow on 1, 3 ... 11 (frame 0: found by the scan)
    assert max(errors) < 0.5              # carried keypoints land where the person moved (3 px a frame)


@pytest.mark.parametrize("fps, detect_every", [(10.0, 2), (30.0, 1)])
def test_the_model_runs_every_frame_at_low_frame_rates_or_when_asked(fps, detect_every):
    detector, errors = follow(fps, detect_every)
    assert detector.crops == 11 and max(errors) < 1e-4


def test_a_frame_of_another_size_runs_the_model_instead_of_the_flow():
    detector, texture = PannedPersonDetector(), textured()
    finder = PeopleFinder(detector, PeopleTracker(), appearance=False, scan_interval=100.0)
    finder(texture, 0.0)
    detector.frame = 1
    people = finder(np.ascontiguousarray(np.roll(texture, PAN, axis=1)[:400, :600]), 1 / 30)   # cropped: no flow
    assert [p.id for p in people] == [0] and detector.crops == 1

"""2D human pose detection on single images: the detector interface, shared helpers, and the MediaPipe (BlazePose) detector.

Every detector returns people in humotion's detector-agnostic 2D layout `KEYPOINTS`: the 17 COCO
keypoints then the 4 COCO-WholeBody foot points (heels, big toes). Positions are pixels of the input
image, x right and y down, and follow each detector's own definition of a point (BlazePose's hips,
for instance, sit a little differently from COCO's). "left" is the person's left.

Two detectors ship: `humotion.capture.movenet.MoveNetDetector` (MoveNet MultiPose + Lightning,
top-down: everyone in the frame from about 50 px tall; the default of `humotion capture`), and
`MediaPipePoseDetector` below, for one person who fills the frame. `MediaPipePoseDetector` runs
Google's BlazePose GHUM 3D "full" models
(Apache-2.0) through MediaPipe's Tasks `PoseLandmarker`, from a bundle shipped in
humotion/assets/capture (built by scripts/make_pose_task.py; see MODEL_CARD.md there). It needs no
network. Each call is independent (IMAGE mode); following people across frames is a separate step.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from humotion.assets import ASSETS
from humotion.io.video import check_image, quiet_native_logs

KEYPOINTS: tuple[str, ...] = (
    "nose", "left_eye", "right_eye", "left_ear", "right_ear",
    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
    "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle",
    "left_heel", "right_heel", "left_big_toe", "right_big_toe",
)  # fmt: skip
"""humotion's 2D keypoint layout (21 points): COCO's 17, then COCO-WholeBody's heels and big toes."""

KEYPOINT_BONES: tuple[tuple[int, int], ...] = tuple(
    (KEYPOINTS.index(a), KEYPOINTS.index(b)) for a, b in (
        ("nose", "left_eye"), ("nose", "right_eye"), ("left_eye", "left_ear"), ("right_eye", "right_ear"),
        ("left_shoulder", "right_shoulder"), ("left_hip", "right_hip"),
        ("left_shoulder", "left_hip"), ("right_shoulder", "right_hip"),
        ("left_shoulder", "left_elbow"), ("left_elbow", "left_wrist"),
        ("right_shoulder", "right_elbow"), ("right_elbow", "right_wrist"),
        ("left_hip", "left_knee"), ("left_knee", "left_ankle"),
        ("right_hip", "right_knee"), ("right_knee", "right_ankle"),
        ("left_ankle", "left_heel"), ("left_ankle", "left_big_toe"), ("left_heel", "left_big_toe"),
        ("right_ankle", "right_heel"), ("right_ankle", "right_big_toe"), ("right_heel", "right_big_toe"),
    )
)  # fmt: skip
"""The 2D skeleton drawn over `KEYPOINTS`: pairs of keypoint indices joined by a line."""

MAX_PEOPLE = 20
"""Most people followed (and reported by a multi-person detector) at once, by default. The cost
grows with the people actually there; the capture model card has the crowd bench that chose it."""

POSE_TASK_PATH: Path = ASSETS / "capture" / "pose_landmarker_full.task"
"""The shipped MediaPipe Tasks bundle (BlazePose detector + full landmark model)."""

# BlazePose's 33 landmarks -> KEYPOINTS (its "foot_index" is the tip of the big toe).
_BLAZEPOSE_INDEX = np.array([0, 2, 5, 7, 8, 11, 12, 13, 14, 15, 16, 23, 24, 25, 26, 27, 28, 29, 30, 31, 32])


@dataclass
class Detection:
    """One person found in one image.

    keypoints: (21, 2) float32, pixels (x right, y down), in `KEYPOINTS` order; may lie outside the
        image for body parts the detector places beyond its border.
    confidence: (21,) float32 in [0, 1], how far to trust each keypoint (0 for a keypoint the detector
        does not provide).
    score: confidence in [0, 1] that this is a person.
    box: (x0, y0, x1, y1) pixels, the extent of the keypoints (see `keypoint_box`).
    appearance: None, or a normalised colour histogram of the person's torso
        (humotion.capture.people.torso_histogram), which the tracker compares to tell people apart.
    """

    keypoints: np.ndarray
    confidence: np.ndarray
    score: float
    box: tuple[float, float, float, float]
    appearance: np.ndarray | None = None


def keypoint_box(
    keypoints: np.ndarray, confidence: np.ndarray, min_confidence: float = 0.5
) -> tuple[float, float, float, float]:
    """(x0, y0, x1, y1) pixels around the keypoints (K, 2), pixels, whose confidence (K,) is at
    least min_confidence (all if none is)."""
    sure = confidence >= min_confidence
    points = keypoints[sure] if sure.any() else keypoints
    x0, y0 = points.min(axis=0)
    x1, y1 = points.max(axis=0)
    return float(x0), float(y0), float(x1), float(y1)


def body_box(keypoints: np.ndarray, confidence: np.ndarray, min_confidence: float = 0.2
             ) -> tuple[float, float, float, float]:
    """(x0, y0, x1, y1) pixels around the whole person, estimated from their keypoints (K, 2),
    pixels, with confidence (K,): the keypoint box (keypoints of at least min_confidence) raised
    by 0.1 of its height for the top of the head above the eyes and ears, lowered by 0.05 for the
    soles below the ankles, and widened by 0.05 of its height on each side (hands and clothes
    beyond the wrists and shoulders). These shares are rough adult proportions, meant for
    comparing with boxes drawn around people by hand."""
    x0, y0, x1, y1 = keypoint_box(keypoints, confidence, min_confidence)
    h = max(y1 - y0, x1 - x0, 1.0)
    return x0 - 0.05 * h, y0 - 0.1 * h, x1 + 0.05 * h, y1 + 0.05 * h


@runtime_checkable
class PoseDetector(Protocol):
    """Anything that finds people in one RGB image, e.g. `MediaPipePoseDetector`."""

    name: str

    def detect(self, image: np.ndarray) -> list[Detection]:
        """People in image ((H, W, 3) uint8 RGB), in `KEYPOINTS` layout; an empty list if none."""
        ...


class MediaPipePoseDetector:
    """BlazePose GHUM 3D (full) through MediaPipe Tasks' PoseLandmarker, CPU, offline.

    max_people: most people reported per image.
    min_detection_confidence: score the person detector needs before a person is considered.
    min_presence_confidence: score the landmark model needs to confirm a person is there.
    model_path: the .task bundle; default the one shipped with humotion (`POSE_TASK_PATH`).

    Keypoint confidence is BlazePose's landmark visibility (not occluded) times its presence (inside
    the image). MediaPipe's Tasks API does not report a person score, so `score` is the mean
    keypoint confidence of a person who passed both thresholds above. Use as a context manager, or
    call close(), to free the native graph early; it is also freed when the detector is collected.
    """

    name = "mediapipe-blazepose-full"

    def __init__(
        self,
        max_people: int = 4,
        min_detection_confidence: float = 0.5,
        min_presence_confidence: float = 0.5,
        model_path: str | Path | None = None,
    ):
        model_path = Path(model_path) if model_path is not None else POSE_TASK_PATH
        if not model_path.is_file():
            raise FileNotFoundError(
                f"pose model bundle not found: {model_path}. It ships with humotion in "
                "humotion/assets/capture; rebuild it with scripts/make_pose_task.py (see its docstring) "
                "or reinstall humotion."
            )
        if max_people < 1:
            raise ValueError(f"max_people must be at least 1, got {max_people}")
        import mediapipe as mp  # imported here: it pulls in OpenCV and matplotlib (over a second)
        from mediapipe.tasks.python import BaseOptions, vision

        self._mp = mp
        self.model_path = model_path
        options = vision.PoseLandmarkerOptions(
            base_options=BaseOptions(model_asset_path=str(model_path)),  # a local file: nothing is downloaded
            running_mode=vision.RunningMode.IMAGE,
            num_poses=max_people,
            min_pose_detection_confidence=min_detection_confidence,
            min_pose_presence_confidence=min_presence_confidence,
        )
        with quiet_native_logs():  # TFLite's "INFO: Created ... delegate", absl's W0000 lines
            self._landmarker = vision.PoseLandmarker.create_from_options(options)
        # Close at collection or at exit, while mediapipe's modules are still alive.
        self._finalizer = weakref.finalize(self, self._landmarker.close)

    def detect(self, image: np.ndarray) -> list[Detection]:
        """People in image ((H, W, 3) uint8 RGB), in `KEYPOINTS` layout; an empty list if none."""
        image = check_image(image)
        if not self._finalizer.alive:
            raise RuntimeError(f"{self.name} detector was closed")
        height, width = image.shape[:2]
        with quiet_native_logs():
            result = self._landmarker.detect(self._mp.Image(image_format=self._mp.ImageFormat.SRGB, data=image))
        detections = []
        for landmarks in result.pose_landmarks:
            chosen = [landmarks[i] for i in _BLAZEPOSE_INDEX]
            keypoints = np.array([(p.x * width, p.y * height) for p in chosen], dtype=np.float32)
            visibility = np.array([p.visibility or 0.0 for p in chosen], dtype=np.float32)
            presence = np.array([p.presence or 0.0 for p in chosen], dtype=np.float32)
            confidence = np.clip(visibility * presence, 0.0, 1.0)
            detections.append(
                Detection(keypoints, confidence, float(confidence.mean()), keypoint_box(keypoints, confidence))
            )
        return detections

    def close(self) -> None:
        """Free the native MediaPipe graph; detect() cannot be called afterwards."""
        self._finalizer()

    def __enter__(self) -> MediaPipePoseDetector:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

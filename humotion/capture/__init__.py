"""Video capture: 3D motion of people filmed by one ordinary camera (specs/video-capture.md).

    from humotion.capture import capture
    result = capture("clip.mp4", "out/")            # per person: BVH, glTF; capture.json; overlay.mp4

Stages, one module each: detection (2D keypoints in humotion's `KEYPOINTS` layout; `PoseDetector`
is the interface, `MediaPipePoseDetector` the shipped offline default), people (stable ids) and
filters (One-Euro), lifting (2D -> 3D network), template and joint_angles (bone lengths by height,
joint rotations), prior and refine (the energy minimisation), pipeline (all of it, and the files).
"""

from humotion.capture.detection import (
    KEYPOINTS,
    POSE_TASK_PATH,
    Detection,
    MediaPipePoseDetector,
    PoseDetector,
    keypoint_box,
)
from humotion.capture.pipeline import CaptureConfig, CaptureResult, capture

__all__ = ["KEYPOINTS", "POSE_TASK_PATH", "Detection", "MediaPipePoseDetector", "PoseDetector", "keypoint_box",
           "CaptureConfig", "CaptureResult", "capture"]

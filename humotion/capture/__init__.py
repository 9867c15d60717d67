"""Video capture: 3D motion of people filmed by one ordinary camera (specs/video-capture.md).

    from humotion.capture import capture
    result = capture("clip.mp4", "out/")            # per person: BVH, glTF; capture.json; overlay.mp4

Stages, one module each: detection (2D keypoints in humotion's `KEYPOINTS` layout; `PoseDetector`
is the interface, `MediaPipePoseDetector` the shipped offline default), people (stable ids) and
filters (One-Euro), lifting (2D -> 3D network), template and joint_angles (bone lengths by height,
joint rotations), height (heights relative to a reference person on the same floor), prior and
refine (the energy minimisation), pipeline (all of it, and the files).
"""

from humotion.capture.detection import (
    KEYPOINTS,
    POSE_TASK_PATH,
    Detection,
    MediaPipePoseDetector,
    PoseDetector,
    keypoint_box,
)
__all__ = ["KEYPOINTS", "POSE_TASK_PATH", "Detection", "MediaPipePoseDetector", "PoseDetector", "keypoint_box",
           "CaptureConfig", "CaptureResult", "capture"]


def __getattr__(name: str):
    """The pipeline's names, imported on first use (it loads OpenCV, scipy and the 3D stages)."""
    if name in ("CaptureConfig", "CaptureResult", "capture"):
        from humotion.capture import pipeline

        return getattr(pipeline, name)
    raise AttributeError(f"module 'humotion.capture' has no attribute {name!r}")

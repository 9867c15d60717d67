"""Video capture: people's 2D poses in camera images (detection), as a step towards 3D motion.

`PoseDetector` is the interface any 2D detector meets; `MediaPipePoseDetector` is the default one
(BlazePose, shipped model, offline). Keypoints use humotion's layout `KEYPOINTS`.
"""

from humotion.capture.detection import (
    KEYPOINTS,
    POSE_TASK_PATH,
    Detection,
    MediaPipePoseDetector,
    PoseDetector,
    keypoint_box,
)

__all__ = ["KEYPOINTS", "POSE_TASK_PATH", "Detection", "MediaPipePoseDetector", "PoseDetector", "keypoint_box"]

"""Live capture: people in 3D frame by frame, as a camera delivers them (the spec's online mode).

Per tracked person, each frame: the causal lifter (humotion.capture.lifting.LiveLifter, which
sees only the frames so far), the template at the given height and bone-length correction (steps
3-6 of the spec), and the root placed by reprojection alone, of the twelve limb joints that are
keypoints themselves (shoulders to ankles). Joint angles (a sequential per-joint solve, slow on
one frame at a time) and the refinement (it needs whole segments) run after the stream ends
(humotion.capture.pipeline). A person missing from a frame starts afresh when seen again.

World frame as in humotion.capture.pipeline (Y up, the camera at the origin looking along -Z),
with the floor under the lowest foot seen so far.

    live = LiveCapture(default_camera(640, 480), height_m=1.75)
    joints = live.update(tracker.update(detector.detect(image), time))   # {person id: (22, 3) metres}
"""

from __future__ import annotations

import torch

from humotion.canonical import JOINTS
from humotion.capture.detection import KEYPOINTS
from humotion.capture.joint_angles import correct_bone_lengths
from humotion.capture.keypoints import VirtualCamera
from humotion.capture.lifting import LIVE_WEIGHTS, Lifter, LiveLifter, load_lifter
from humotion.capture.people import TrackedPerson
from humotion.capture.pipeline import CAMERA_TO_WORLD, FEET
from humotion.capture.refine import initial_root
from humotion.capture.template import DEFAULT_HEIGHT, template_skeleton

LIMB_JOINTS = [f"{side}_{joint}" for joint in ("shoulder", "elbow", "wrist", "hip", "knee", "ankle")
               for side in ("left", "right")]
"""Joints that are keypoints of the same name (humotion.capture.keypoints)."""
_JOINT_INDEX = [JOINTS.index(name) for name in LIMB_JOINTS]
_KEYPOINT_INDEX = [KEYPOINTS.index(name) for name in LIMB_JOINTS]


class LiveCapture:
    """Online 3D joints of every tracked person (module docstring).

    camera: the camera's intrinsics (humotion.capture.pipeline.default_camera).
    height_m: everyone's standing height (the template's); heights: {person id: metres} for
    people of another height. lifter: a causal Lifter (default: the shipped live weights), shared
    by everyone; each person keeps their own window of frames.
    """

    def __init__(self, camera: VirtualCamera, height_m: float = DEFAULT_HEIGHT, lifter: Lifter | None = None,
                 heights: dict[int, float] | None = None):
        self.camera, self.height_m, self.heights = camera, height_m, dict(heights or {})
        self.lifter = lifter if lifter is not None else load_lifter(LIVE_WEIGHTS)
        self.floor: float | None = None
        self._streams: dict[int, LiveLifter] = {}

    @torch.no_grad()
    def update(self, people: list[TrackedPerson]) -> dict[int, torch.Tensor]:
        """{person id: (22, 3) joints in metres, world frame} for this frame's people."""
        streams = {p.id: self._streams.get(p.id) or LiveLifter(self.lifter) for p in people}
        self._streams = streams          # whoever is missing now starts afresh next time
        out = {}
        for person in people:
            keypoints = torch.as_tensor(person.keypoints, dtype=torch.float32)[None]
            confidence = torch.as_tensor(person.confidence, dtype=torch.float32)[None]
            height = self.heights.get(person.id, self.height_m)
            lifted = streams[person.id].push(keypoints[0], confidence[0])[None] * height
            joints = correct_bone_lengths(lifted, template_skeleton(height))       # (1, 22, 3), pelvis at 0
            root = initial_root(joints[:, _JOINT_INDEX], keypoints[:, _KEYPOINT_INDEX],
                                confidence[:, _KEYPOINT_INDEX], self.camera)
            out[person.id] = (joints[0] + root) @ CAMERA_TO_WORLD.T
        if out:
            lowest = min(float(j[FEET, 1].min()) for j in out.values())
            self.floor = lowest if self.floor is None else min(self.floor, lowest)
            out = {i: j - torch.tensor([0.0, self.floor, 0.0]) for i, j in out.items()}
        return out

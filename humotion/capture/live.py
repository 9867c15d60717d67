"""Live capture: people in 3D frame by frame, as a camera delivers them (the spec's online mode).

Per tracked person, each frame: the causal lifter (humotion.capture.lifting.LiveLifter, which
sees only the frames so far), the template at the given height and bone-length correction (steps
3-6 of the spec), and the root placed by reprojection alone, of the twelve limb joints that are
keypoints themselves (shoulders to ankles). The refinement (it needs whole segments) runs after
the stream ends (humotion.capture.pipeline). Joint angles, for VMC output (VmcOutput), come from
these joints by the pipeline's own solve (humotion.capture.joint_angles), in a thread of their
own. A person missing from a frame starts afresh when seen again.

World frame: humotion.capture.world (Y up, the camera at the origin looking along -Z), with the
floor under the lowest foot seen so far.

    live = LiveCapture(default_camera(640, 480), height_m=1.75)
    joints = live.update(tracker.update(detector.detect(image), time))   # {person id: (22, 3) metres}
"""

from __future__ import annotations

import threading
import time

import torch

from humotion.canonical import JOINTS
from humotion.capture.detection import KEYPOINTS
from humotion.capture.joint_angles import correct_bone_lengths, positions_to_rotations
from humotion.capture.keypoints import VirtualCamera
from humotion.capture.lifting import LIVE_WEIGHTS, Lifter, LiveLifter, load_lifter, person_centred
from humotion.capture.people import TrackedPerson
from humotion.capture.refine import initial_root
from humotion.capture.template import DEFAULT_HEIGHT, template_skeleton
from humotion.capture.world import CAMERA_TO_WORLD, FEET

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
            centred, turn = person_centred(keypoints, confidence, self.camera)      # as capture lifts
            lifted = streams[person.id].push(centred[0], confidence[0])[None] @ turn * height
            joints = correct_bone_lengths(lifted, template_skeleton(height))       # (1, 22, 3), pelvis at 0
            root = initial_root(joints[:, _JOINT_INDEX], keypoints[:, _KEYPOINT_INDEX],
                                confidence[:, _KEYPOINT_INDEX], self.camera)
            out[person.id] = (joints[0] + root) @ CAMERA_TO_WORLD.T
        if out:
            lowest = min(float(j[FEET, 1].min()) for j in out.values())
            self.floor = lowest if self.floor is None else min(self.floor, lowest)
            out = {i: j - torch.tensor([0.0, self.floor, 0.0]) for i, j in out.items()}
        return out


class VmcOutput:
    """Live capture's body as VMC (humotion.live.vmc): a sink for the people LiveCapture gives
    each frame (``show(people, image)``, as humotion.viewer.live.LiveView takes them), for
    ``humotion capture 0 --live --vmc HOST:PORT``.

    One body is sent, the person with the lowest id in the frame (the one followed longest). Its
    joint rotations come from its live 3D joints by the offline pipeline's joint-angle solve
    (humotion.capture.joint_angles.positions_to_rotations, on the template skeleton of the
    person's height: height_m, or heights[id]); the Hips bone carries the pelvis's place, with
    where that person was first seen (across the floor) as the origin, so the avatar starts at
    the receiver's origin and moves as the person moves. The solve runs in a thread of its own
    on the newest frame only (a few to tens of milliseconds a frame, depending on the machine):
    the capture loop never waits for it, and a frame that a newer one replaced before it was
    solved is not sent (counted in ``skipped``). /VMC/Ext/T is seconds since the first frame.
    """

    def __init__(self, address: tuple[str, int], height_m: float = DEFAULT_HEIGHT,
                 heights: dict[int, float] | None = None, clock=time.monotonic):
        from humotion.live.vmc import VmcSender

        self.height_m, self.heights, self.clock = height_m, dict(heights or {}), clock
        self.sender = VmcSender(address)
        self.sent = self.skipped = 0
        self._start, self._origin = None, None          # the first frame's time; (person id, pelvis x/z)
        self._newest = None                             # (person id, (22, 3) joints, t) waiting to be solved
        self._wake = threading.Condition()
        self._stopped = False
        self._thread = threading.Thread(target=self._run, name="vmc output", daemon=True)
        self._thread.start()

    def show(self, people: dict[int, torch.Tensor], image=None) -> None:
        """This frame's people ({id: (22, 3) joints, metres, world frame}); image is ignored."""
        if not people:
            return
        person = min(people)
        now = self.clock()
        self._start = now if self._start is None else self._start
        with self._wake:
            if self._newest is not None:
                self.skipped += 1
            self._newest = (person, torch.as_tensor(people[person], dtype=torch.float32).clone(), now - self._start)
            self._wake.notify()

    def _run(self) -> None:
        while True:
            with self._wake:
                while self._newest is None and not self._stopped:
                    self._wake.wait()
                if self._stopped:
                    return
                (person, joints, t), self._newest = self._newest, None
            self._send(person, joints, t)

    @torch.no_grad()
    def _send(self, person: int, joints: torch.Tensor, t: float) -> None:
        skeleton = template_skeleton(self.heights.get(person, self.height_m))
        rotations, root = positions_to_rotations(joints, skeleton)
        if self._origin is None or self._origin[0] != person:
            self._origin = (person, root[[0, 2]].clone())
        root = root.clone()
        root[[0, 2]] -= self._origin[1]
        self.sender.send(rotations.numpy(), root.numpy(), t, skeleton.offsets.numpy())
        self.sent += 1

    def stop(self) -> None:
        """Send the frame still waiting, then close the socket."""
        with self._wake:
            waiting, self._newest = self._newest, None
            self._stopped = True
            self._wake.notify()
        self._thread.join()
        if waiting is not None:
            self._send(*waiting)
        self.sender.close()


class LiveOutputs:
    """Several live sinks (LiveView, VmcOutput) as one: ``show`` and ``stop`` go to each in turn."""

    def __init__(self, *outputs):
        self.outputs = outputs

    def show(self, people: dict[int, torch.Tensor], image=None) -> None:
        """This frame's people ({id: (22, 3) joints, metres, world frame}) and image ((H, W, 3)
        uint8 RGB or None) to each output."""
        for output in self.outputs:
            output.show(people, image)

    def stop(self) -> None:
        for output in self.outputs:
            output.stop()

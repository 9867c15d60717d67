"""Live capture: the online 3D people equal the offline causal lifting frame by frame, restart
after a gap, and show up in the live browser view."""

import numpy as np
import pytest
import torch

from humotion.canonical import JOINTS, to_canonical
from humotion.capture.detection import KEYPOINTS
from humotion.capture.joint_angles import correct_bone_lengths
from humotion.capture.keypoints import VirtualCamera, body_keypoints_3d
from humotion.capture.lifting import LIVE_WEIGHTS, lift_sequence, load_lifter
from humotion.capture.live import LIMB_JOINTS, LiveCapture
from humotion.capture.people import TrackedPerson
from humotion.capture.pipeline import CAMERA_TO_WORLD, FEET, default_camera
from humotion.capture.refine import initial_root
from humotion.capture.template import template_skeleton
from humotion.io import load_motion


@pytest.fixture(scope="module")
def causal():
    """The shipped live (causal) lifting weights."""
    return load_lifter(LIVE_WEIGHTS)


@pytest.fixture(scope="module")
def filmed(mocap):
    """A held-out subject's 1 s walk 4 m in front of a 640x480 camera: pixels (T, 21, 2)."""
    motion = to_canonical(load_motion(mocap / "cmu_visdoom_mocapplayer" / "amc" / "07_01-walk.amc")).resample(30.0)[30:60]
    centre = motion.root_positions.mean(0)
    camera = VirtualCamera.looking_at(centre + torch.tensor([0.0, 0.3, 4.0]), centre, 60.0, 640, 480)
    world_r, world_p = motion.world()
    pixels, _ = camera.project(body_keypoints_3d(world_r, world_p, motion.skeleton))
    return pixels


def people(pixels, person_id=0):
    return [TrackedPerson(person_id, p.numpy(), np.ones(21, np.float32), None) for p in pixels]


def test_live_joints_equal_the_offline_causal_fit(filmed, causal):
    camera = default_camera(640, 480)
    live = LiveCapture(camera, 1.8, causal)
    online = torch.stack([live.update([person])[0] for person in people(filmed)])          # (T, 22, 3)
    skeleton = template_skeleton(1.8)
    confidence = torch.ones(filmed.shape[:2])
    joints = correct_bone_lengths(lift_sequence(causal, filmed, confidence) * 1.8, skeleton)
    limbs, keypoints = [JOINTS.index(n) for n in LIMB_JOINTS], [KEYPOINTS.index(n) for n in LIMB_JOINTS]
    root = initial_root(joints[:, limbs], filmed[:, keypoints], confidence[:, keypoints], camera)
    offline = (joints + root[:, None]) @ CAMERA_TO_WORLD.T
    shift = online - offline            # the floor, under the lowest foot so far: a height shift per frame
    assert torch.allclose(shift, shift[:, :1].expand_as(shift), atol=1e-4) and shift[..., [0, 2]].abs().max() < 1e-4
    feet_so_far = offline[:, FEET, 1].amin(1).cummin(0).values
    assert torch.allclose(shift[:, 0, 1], -feet_so_far, atol=1e-4)
    bones = (online[:, 1:] - online[:, template_skeleton().parents[1:]]).norm(dim=-1)
    assert torch.allclose(bones, torch.as_tensor(np.linalg.norm(skeleton.offsets[1:], axis=1), dtype=torch.float32), atol=1e-4)
    assert float(online[:, FEET, 1].min()) == pytest.approx(0.0, abs=1e-6)
    assert (online[:, JOINTS.index("head"), 1] > online[:, 0, 1]).all()   # Y up


def test_a_person_seen_again_starts_afresh(filmed, causal):
    camera = default_camera(640, 480)
    live = LiveCapture(camera, 1.65, causal)
    tracked = people(filmed)
    for person in tracked[:10]:
        live.update([person])
    assert live.update([]) == {}                              # nobody in this frame
    again = live.update([tracked[20]])[0]
    fresh = LiveCapture(camera, 1.65, causal)
    fresh.floor = live.floor
    assert torch.allclose(again, fresh.update([tracked[20]])[0], atol=1e-6)
    two = live.update([tracked[21], people(filmed[21:22] + torch.tensor([200.0, 0.0]), person_id=5)[0]])
    assert set(two) == {0, 5} and (two[5][:, 0].mean() > two[0][:, 0].mean())     # further right in the picture


def test_live_view_shows_who_is_there_now(filmed, causal):
    from humotion.viewer.live import LiveView

    live = LiveCapture(default_camera(640, 480), 1.65, causal)
    view = LiveView(port=0)
    try:
        image = np.zeros((480, 640, 3), np.uint8)
        view.show(live.update(people(filmed[:1]) + people(filmed[:1] + 150.0, person_id=3)), image)
        assert view.shown == {0, 3} and view.url.startswith("http://")
        view.show(live.update(people(filmed[1:2], person_id=3)), image)
        assert view.shown == {3}
    finally:
        view.stop()

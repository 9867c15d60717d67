"""Live capture: the online 3D people equal the offline causal lifting frame by frame, restart
after a gap, show up in the live browser view, and go out as VMC (joint angles by the offline
solve) to a python-osc receiver, from a real video through the live path."""

import time
from pathlib import Path

import numpy as np
import pytest
import torch

from humotion import rotations as rot
from humotion.canonical import JOINTS, to_canonical
from humotion.capture.detection import KEYPOINTS
from humotion.capture.joint_angles import correct_bone_lengths, positions_to_rotations
from humotion.capture.keypoints import VirtualCamera, body_keypoints_3d
from humotion.capture.lifting import LIVE_WEIGHTS, lift_sequence, load_lifter, person_centred
from humotion.capture.live import LIMB_JOINTS, LiveCapture
from humotion.capture.people import TrackedPerson
from humotion.capture.pipeline import default_camera
from humotion.capture.refine import initial_root
from humotion.capture.template import template_skeleton
from humotion.capture.world import CAMERA_TO_WORLD, FEET
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
    crops = [person_centred(filmed[t:t + 1], confidence[t:t + 1], camera) for t in range(len(filmed))]  # frame by frame
    centred, turn = torch.cat([c for c, _ in crops]), torch.cat([r for _, r in crops])
    joints = correct_bone_lengths((lift_sequence(causal, centred, confidence) @ turn) * 1.8, skeleton)
    limbs, keypoints = [JOINTS.index(n) for n in LIMB_JOINTS], [KEYPOINTS.index(n) for n in LIMB_JOINTS]
    root = initial_root(joints[:, limbs], filmed[:, keypoints], confidence[:, keypoints], camera)
    offline = (joints + root[:, None]) @ CAMERA_TO_WORLD.T
    shift = online - offline            # the floor, under the lowest foot so far: a height shift per frame
    assert torch.allclose(shift, shift[:, :1].expand_as(shift), atol=1e-4) and shift[..., [0, 2]].abs().max() < 1e-4
    feet_so_far = offline[:, FEET, 1].amin(1).cummin(0).values
    assert torch.allclose(shift[:, 0, 1], -feet_so_far, atol=1e-4)
    bones = (online[:, 1:] - online[:, template_skeleton().parents[1:]]).norm(dim=-1)
    assert torch.allclose(bones, skeleton.offsets[1:].norm(dim=1), atol=1e-4)
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


def vmc_frames(receiver) -> list[dict]:
    """Each VMC frame heard: {"t": seconds, "bones": {name: (px, py, pz, qx, qy, qz, qw)}, "at": arrival}."""
    frames = []
    for at, address, args in receiver.heard:
        if address == "/VMC/Ext/OK":
            frames.append({"bones": {}, "at": at})
        elif address == "/VMC/Ext/T":
            frames[-1]["t"] = args[0]
        elif address == "/VMC/Ext/Bone/Pos":
            frames[-1]["bones"][args[0]] = np.array(args[1:])
    return frames


def test_vmc_output_sends_the_joint_angles_of_the_live_joints(filmed, causal):
    from test_live_vmc import Receiver

    from humotion.capture.live import VmcOutput
    from humotion.live.vmc import BONE_NAMES
    from humotion.skeleton import forward_kinematics

    live = LiveCapture(default_camera(640, 480), 1.8, causal)
    joints = [live.update([person])[0] for person in people(filmed)]
    receiver, clock = Receiver(), iter(np.arange(len(joints)) / 30.0)
    try:
        output = VmcOutput(("127.0.0.1", receiver.port), height_m=1.8, clock=lambda: next(clock))
        for i, frame in enumerate(joints):
            output.show({0: frame, 4: frame + 1.0})                    # person 0, the lowest id, is sent
            deadline = time.monotonic() + 30
            while output.sent <= i and time.monotonic() < deadline:  # each frame solved before the next
                time.sleep(0.002)
        output.stop()
        receiver.wait_for(output.sent)
        heard = vmc_frames(receiver)
    finally:
        receiver.close()
    assert output.skipped == 0 and len(heard) == len(joints)
    skeleton = template_skeleton(1.8)
    for i, frame in enumerate(heard):
        assert frame["t"] == pytest.approx(i / 30.0) and list(frame["bones"]) == list(BONE_NAMES)
        values = np.stack([frame["bones"][name] for name in BONE_NAMES])
        assert np.allclose(np.linalg.norm(values[:, 3:], axis=1), 1.0, atol=1e-5)           # unit quaternions
        # Unity's (x, y, z, w) mirrored back to humotion's (w, x, y, z): the offline pipeline's joint
        # angles of these joints, and forward kinematics on the template gives the joints again
        # within a few cm (the nearest pose the skeleton can take: its rigid hips and shoulder fans)
        q = torch.tensor(np.stack([values[:, 6], values[:, 3], -values[:, 4], -values[:, 5]], 1), dtype=torch.float32)
        expected, _ = positions_to_rotations(joints[i], skeleton)
        assert torch.allclose((q * expected).sum(-1).abs(), torch.ones(22), atol=1e-5)
        _, posed = forward_kinematics(rot.quat_to_matrix(q), torch.zeros(3), skeleton.offsets, skeleton.parents)
        error = (posed - (joints[i] - joints[i][0])).norm(dim=-1)
        assert error.median() < 0.035 and error.max() < 0.06, error
        hips = values[0, :3] * np.array([-1.0, 1.0, 1.0])                 # the pelvis, origin where first seen
        first = joints[0][0]
        assert np.allclose(hips, (joints[i][0] - torch.tensor([first[0], 0.0, first[2]])).numpy(), atol=1e-5)


VIDEO = Path(__file__).resolve().parents[2] / "shared" / "data" / "video" / "intel_one-by-one-person-detection_first40s.mp4"


def test_a_video_through_the_live_path_comes_out_as_vmc(tmp_path):
    """3 s of a real clip (Intel IoT DevKit sample-videos, CC BY 4.0: a person standing, then
    walking) through capture()'s live path, as from a camera, to a python-osc receiver."""
    from test_live_vmc import Receiver

    from humotion.capture.live import VmcOutput
    from humotion.capture.pipeline import CaptureConfig, capture
    from humotion.io.video import VideoWriter, open_frames
    from humotion.live.vmc import BONE_NAMES

    if not VIDEO.is_file():
        pytest.skip("shared videos missing")
    clip = tmp_path / "clip.mp4"
    with open_frames(VIDEO) as frames, VideoWriter(clip, fps=10.0) as writer:
        for index, _, image in frames:
            if index >= 270:
                break
            if index >= 240:
                writer.write(image)
    receiver = Receiver()
    try:
        output = VmcOutput(("127.0.0.1", receiver.port), height_m=1.75)
        started = time.monotonic()
        result = capture(clip, tmp_path / "out", CaptureConfig(height_m=1.75, refine=None), progress=False,
                         live_view=output)
        output.stop()
        took = time.monotonic() - started
        receiver.wait_for(output.sent)
        heard = vmc_frames(receiver)
    finally:
        receiver.close()
    assert result.people and len(heard) == output.sent and output.sent + output.skipped >= 25   # of 30 frames
    assert output.sent >= 5
    times = [frame["t"] for frame in heard]
    assert times == sorted(times) and times[0] == 0.0 and times[-1] < took
    # the rate: a frame per frame solved, stamped with the time it was shown; arrival keeps that pace
    arrival = [frame["at"] - heard[0]["at"] for frame in heard]
    assert np.allclose(np.diff(arrival).sum(), times[-1] - times[0], atol=0.25 + 0.1 * times[-1])
    for frame in heard:
        assert list(frame["bones"]) == list(BONE_NAMES)
        values = np.stack(list(frame["bones"].values()))
        assert np.allclose(np.linalg.norm(values[:, 3:], axis=1), 1.0, atol=1e-5)
        assert 0.6 < values[0, 1] < 1.2                                   # the hips above the floor, metres
        assert np.degrees(2 * np.arccos(np.clip(np.abs(values[:, 6]), 0, 1))).max() > 5   # a pose, not a T-pose


def test_the_capture_command_sends_vmc(tmp_path):
    """humotion capture VIDEO --vmc HOST:PORT: the same live path from the command line."""
    from click.testing import CliRunner
    from test_live_vmc import Receiver

    from humotion.cli import main
    from humotion.io.video import VideoWriter, open_frames
    from humotion.live.vmc import BONE_NAMES

    if not VIDEO.is_file():
        pytest.skip("shared videos missing")
    clip = tmp_path / "clip.mp4"
    with open_frames(VIDEO) as frames, VideoWriter(clip, fps=10.0) as writer:
        for index, _, image in frames:
            if index >= 255:
                break
            if index >= 240:
                writer.write(image)
    receiver = Receiver()
    try:
        result = CliRunner().invoke(main, ["capture", str(clip), "-o", str(tmp_path / "out"), "--no-refine",
                                           "--vmc", f"127.0.0.1:{receiver.port}"])
        receiver.wait_for(1)
        heard = vmc_frames(receiver)
    finally:
        receiver.close()
    assert result.exit_code == 0, result.output
    assert f"VMC: the body of the person followed longest to 127.0.0.1:{receiver.port}" in result.output
    assert heard and all(list(frame["bones"]) == list(BONE_NAMES) for frame in heard)
    bad = CliRunner().invoke(main, ["capture", str(clip), "-o", str(tmp_path / "out2"), "--vmc", "localhost:port"])
    assert bad.exit_code == 2 and "--vmc" in bad.output and "port must be a number" in bad.output

"""VMC output: the axes change, the messages per frame, their rate and values, heard by an OSC
receiver (python-osc's server) on 127.0.0.1."""

import math
import threading
import time

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from pythonosc.dispatcher import Dispatcher
from pythonosc.osc_server import BlockingOSCUDPServer

from humotion import rotations as rot
from humotion.canonical import JOINTS, PARENTS, canonical_skeleton
from humotion.live import vmc
from humotion.motion import Motion
from humotion.skeleton import forward_kinematics

S = math.sqrt(0.5)


class Receiver:
    """An OSC receiver on 127.0.0.1 recording (arrival time, address, arguments), one datagram
    after the other in arrival order (a thread per datagram could record them out of order)."""

    def __init__(self):
        self.heard = []
        dispatcher = Dispatcher()
        dispatcher.set_default_handler(lambda address, *args: self.heard.append((time.monotonic(), address, args)))
        self.server = BlockingOSCUDPServer(("127.0.0.1", 0), dispatcher)
        self.port = self.server.server_address[1]
        self.thread = threading.Thread(target=self.server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
        self.thread.start()

    def wait_for(self, frames: int, timeout: float = 10.0):
        """Until every bone of `frames` frames is heard (a frame spans several datagrams)."""
        end = time.monotonic() + timeout
        while time.monotonic() < end and sum(a == "/VMC/Ext/Bone/Pos" for _, a, _ in self.heard) < 22 * frames:
            time.sleep(0.01)

    def frames(self) -> list[list]:
        """The messages grouped by frame: each frame starts at its /VMC/Ext/OK."""
        out = []
        for _, address, args in self.heard:
            if address == "/VMC/Ext/OK":
                out.append([])
            out[-1].append((address, args))
        return out

    def close(self):
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture
def receiver():
    r = Receiver()
    yield r
    r.close()


def test_positions_mirror_x():
    assert vmc.unity_positions([0.3, 1.2, 0.4]).tolist() == [-0.3, 1.2, 0.4]


def test_a_turn_to_the_left_stays_a_turn_to_the_left():
    """Body yawed 90 degrees to its left (about +Y, humotion) -> -90 degrees about Unity's Y: (x, y, z, w) = (0, -s, 0, s)."""
    assert np.allclose(vmc.unity_quaternions([S, 0, S, 0]), [0, -S, 0, S])
    # the left arm lowered by 90 degrees (about +Z in humotion, +X along the arm turning down): Unity (0, 0, -s, s)
    assert np.allclose(vmc.unity_quaternions([S, 0, 0, S]), [0, 0, -S, S])
    # pitching the head down (about +X in humotion: +Z forward turns to -Y): Unity's X axis, same angle
    assert np.allclose(vmc.unity_quaternions([S, S, 0, 0]), [S, 0, 0, S])


def test_quaternion_change_is_the_mirror_of_the_matrix():
    q = torch.nn.functional.normalize(torch.randn(50, 4, dtype=torch.float64), dim=-1)
    m = torch.diag(torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64))
    xyzw = torch.as_tensor(vmc.unity_quaternions(q.numpy()))
    unity = rot.quat_to_matrix(xyzw[:, [3, 0, 1, 2]])
    assert torch.allclose(unity, m @ rot.quat_to_matrix(q) @ m, atol=1e-12)


def test_mirrored_bones_place_the_mirrored_joints():
    """Forward kinematics on the sent values (Unity's axes) gives the body's joints with x negated."""
    skeleton = canonical_skeleton(1.8)
    q = torch.nn.functional.normalize(torch.randn(22, 4, dtype=torch.float64), dim=-1)
    root = torch.tensor([0.2, 0.9, -0.4], dtype=torch.float64)
    _, world = forward_kinematics(q, root, skeleton.offsets, PARENTS)
    sent = vmc.unity_quaternions(q.numpy())[:, [3, 0, 1, 2]]
    _, unity = forward_kinematics(torch.as_tensor(sent), torch.as_tensor(vmc.unity_positions(root.numpy())),
                                  torch.as_tensor(vmc.unity_positions(skeleton.offsets.double().numpy())), PARENTS)
    assert torch.allclose(unity, world * torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64), atol=1e-9)


def test_every_canonical_joint_has_a_humanoid_bone():
    assert len(set(vmc.BONE_NAMES)) == 22 == len(JOINTS)
    assert vmc.VMC_BONES["left_shoulder"] == "LeftUpperArm" and vmc.VMC_BONES["right_collar"] == "RightShoulder"
    assert vmc.VMC_BONES["spine3"] == "UpperChest" and vmc.VMC_BONES["left_foot"] == "LeftToes"


@pytest.mark.parametrize("text, expected", [("127.0.0.1:39539", ("127.0.0.1", 39539)), ("localhost", ("localhost", 39539)),
                                            (":9000", ("127.0.0.1", 9000)), ("[::1]:9000", ("::1", 9000))])
def test_addresses_are_read(text, expected):
    assert vmc.parse_address(text) == expected


@pytest.mark.parametrize("text", ["host:port", "host:0", "host:70000", "host:"])
def test_bad_addresses_are_refused(text):
    with pytest.raises(ValueError, match="port must be a number"):
        vmc.parse_address(text)


def _motion(frames: int, fps: float) -> Motion:
    skeleton = canonical_skeleton()
    rotations = torch.zeros(frames, 22, 4)
    rotations[..., 0] = 1.0
    rotations[:, 0] = torch.tensor([S, 0, S, 0])                     # pelvis turned 90 degrees to the left
    rotations[:, JOINTS.index("left_elbow")] = torch.tensor([S, 0, 0, S])
    roots = torch.tensor([[0.1, 0.95, 0.02 * i] for i in range(frames)])
    return Motion(skeleton, rotations, roots, fps)


def test_a_receiver_hears_every_bone_each_frame_at_the_rate(receiver):
    frames, fps = 12, 40.0
    with vmc.VmcSender(("127.0.0.1", receiver.port)) as sender:
        start = time.monotonic()
        assert vmc.stream_motion(_motion(frames, fps), sender) == frames
        took = time.monotonic() - start
        assert sender.dropped == 0
    receiver.wait_for(frames)
    got = receiver.frames()
    assert len(got) == frames
    for i, frame in enumerate(got):
        bones = {args[0]: args[1:] for address, args in frame if address == "/VMC/Ext/Bone/Pos"}
        assert set(bones) == set(vmc.BONE_NAMES) and len(bones) == 22
        assert [a for a, _ in frame].count("/VMC/Ext/Bone/Pos") == 22
        assert dict(frame)["/VMC/Ext/OK"] == (1, 3, 0, 1)
        assert dict(frame)["/VMC/Ext/T"][0] == pytest.approx(i / fps)
        assert dict(frame)["/VMC/Ext/Root/Pos"] == ("root", 0, 0, 0, 0, 0, 0, 1)
        assert np.allclose(bones["Hips"], [-0.1, 0.95, 0.02 * i, 0, -S, 0, S], atol=1e-6)
        assert np.allclose(bones["LeftLowerArm"], [-0.32, 0, 0, 0, 0, -S, S], atol=1e-6)   # the left arm lies along -X
        assert np.allclose(bones["RightUpperLeg"], [0.09, -0.07, 0, 0, 0, 0, 1], atol=1e-6)
    assert (frames - 1) / fps - 0.01 <= took < (frames - 1) / fps + 0.5          # paced in real time
    arrivals = [t for t, a, _ in receiver.heard if a == "/VMC/Ext/T"]
    assert arrivals[-1] - arrivals[0] == pytest.approx((frames - 1) / fps, abs=0.15)


def test_datagrams_stay_small():
    messages = vmc.frame_messages(np.tile([1.0, 0, 0, 0], (22, 1)), np.zeros(3), canonical_skeleton().offsets.numpy(), 0.0)
    assert all(len(d) <= vmc.MAX_DATAGRAM for d in vmc.bundles(messages))


def test_track_streams_a_recording_as_vmc(receiver, tmp_path):
    from humotion.cli import main
    from humotion.sparse.recording import stream_from_motion, write_recording

    truth = _motion(45, 30.0)
    write_recording(stream_from_motion(truth, "HT", generator=torch.Generator().manual_seed(0)), tmp_path / "r.csv")
    result = CliRunner().invoke(main, ["track", str(tmp_path / "r.csv"), "--vmc", f"127.0.0.1:{receiver.port}",
                                       "--vmc-rate", "0"])
    assert result.exit_code == 0, result.output
    assert "VMC: 45 frames" in result.output
    receiver.wait_for(45)
    assert len(receiver.frames()) == 45
    assert CliRunner().invoke(main, ["track", str(tmp_path / "r.csv"), "--vmc", "x:y"]).exit_code == 2

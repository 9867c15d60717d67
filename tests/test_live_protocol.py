"""The serve messages: binary layout, change of axes both ways, malformed messages refused."""

import json
import math

import numpy as np
import pytest
import torch

from humotion import rotations as rot
from humotion.live import protocol as pr
from humotion.sparse.recording import CONVENTIONS, HeadsetFrame, hand_offset, _to_humotion


def test_binary_layout_sizes():
    assert pr.FRAME.size == 96 and pr.POSE.size == 640


@pytest.mark.parametrize("convention", list(CONVENTIONS))
@pytest.mark.parametrize("hand_frame", ["tpose", "forward"])
def test_frames_are_read_as_recordings_are(convention, hand_frame):
    """A device through the protocol lands where the recording reader puts it."""
    axes = pr.Axes(convention, hand_frame)
    gen = torch.Generator().manual_seed(1)
    q = torch.nn.functional.normalize(torch.randn(3, 4, generator=gen, dtype=torch.float64), dim=-1)
    p = torch.randn(3, 3, generator=gen, dtype=torch.float64)
    frame = pr.frame_from_binary(pr.frame_binary(2.5, [*p[0], *q[0]], [*p[1], *q[1]], [*p[2], *q[2]]), axes)
    as_json = pr.frame_from_json(json.loads(json.dumps({"t": 2.5, "head": [*p[0].tolist(), *q[0].tolist()],
                                                        "left": [*p[1].tolist(), *q[1].tolist()],
                                                        "right": [*p[2].tolist(), *q[2].tolist()]})), axes)
    for k, (binary, text) in enumerate(zip((frame.head, frame.left, frame.right), (as_json.head, as_json.left, as_json.right))):
        offset = torch.eye(3, dtype=torch.float64) if k == 0 else hand_offset(("left", "right")[k - 1], hand_frame)
        r_ref, p_ref = _to_humotion(q[k], p[k], convention, offset)
        assert np.allclose(text[0], r_ref.numpy(), atol=1e-12) and np.allclose(text[1], p_ref.numpy(), atol=1e-12)
        assert np.allclose(binary[0], r_ref.numpy(), atol=1e-6) and np.allclose(binary[1], p_ref.numpy(), atol=1e-6)
    assert frame.timestamp == as_json.timestamp == 2.5
    assert type(frame) is type(as_json) is HeadsetFrame is pr.HeadsetFrame      # the tracker's own frame type


@pytest.mark.parametrize("convention", list(CONVENTIONS))
def test_poses_go_out_in_the_connections_axes(convention):
    """Sent rotations are C R C^T of the local ones (so forward kinematics in the convention gives C p)."""
    axes = pr.Axes(convention)
    c = torch.as_tensor(CONVENTIONS[convention])
    q = torch.nn.functional.normalize(torch.randn(22, 4, dtype=torch.float64), dim=-1)
    root, positions = torch.randn(3, dtype=torch.float64), torch.randn(22, 3, dtype=torch.float64)
    pose = pr.read_pose_binary(pr.pose_binary(1.0, q.numpy(), root.numpy(), positions.numpy(), axes))
    sent = torch.as_tensor(pose["rotations"], dtype=torch.float64)
    assert torch.allclose(rot.quat_to_matrix(sent), c @ rot.quat_to_matrix(q) @ c.T, atol=1e-5)
    assert np.allclose(pose["root"], (c @ root).numpy(), atol=1e-6)
    assert np.allclose(pose["positions"], (positions @ c.T).numpy(), atol=1e-6)
    as_json = json.loads(pr.pose_json(1.0, q.numpy(), root.numpy(), positions.numpy(), axes))
    assert np.allclose(as_json["rotations"], pose["rotations"], atol=1e-5) and as_json["type"] == "pose"


S = [0, 1.6, 0, 1, 0, 0, 0]


@pytest.mark.parametrize("message, expected", [
    (b"\x00" * 10, "binary frame of 10 bytes"),
    (pr.FRAME.pack(2, 1, 0, 0, 0.0, *S, *S, *S), "version 2"),
    (pr.frame_binary(math.nan, S), "finite number"),
    (pr.frame_binary(0.0, [0, 1.6, 0, 0, 0, 0, 0]), "head quaternion has length 0"),
    (pr.frame_binary(0.0, S, [math.inf] * 7), "left needs 7 finite numbers"),
    ({"t": 0.0}, '"head"'),
    ({"t": "0", "head": S}, "t must be"),
    ({"t": True, "head": S}, "t must be"),
    ({"t": 0.0, "head": S[:6]}, "head needs 7"),
    ({"t": 0.0, "head": ["a"] * 7}, "head"),
    ({"t": 0.0, "head": S, "extra": 1}, "unknown field 'extra'"),
])
def test_malformed_frames_are_refused(message, expected):
    with pytest.raises(pr.ProtocolError, match=expected.replace("(", r"\(")):
        if isinstance(message, bytes):
            pr.frame_from_binary(message, pr.Axes())
        else:
            pr.frame_from_json(message, pr.Axes())


@pytest.mark.parametrize("text, expected", [("[1, 2]", '"type"'), ("{", "not JSON"), ('{"type": 3}', '"type"')])
def test_malformed_json_is_refused(text, expected):
    with pytest.raises(pr.ProtocolError, match=expected):
        pr.read_message(text)


@pytest.mark.parametrize("query, expected", [("convention=unreal", "convention 'unreal'"), ("height=tall", "height 'tall'"),
                                             ("height=7", "outside"), ("colour=red", "unknown field 'colour'")])
def test_bad_settings_are_refused(query, expected):
    with pytest.raises(pr.ProtocolError, match=expected):
        pr.hello_from_query(query)


def test_settings_from_query_then_hello():
    hello = pr.hello_from_query("convention=unity&height=1.8")
    assert (hello.convention, hello.height) == ("unity", 1.8)
    hello = hello.updated({"type": "hello", "version": 1, "hand_frame": "forward", "token": "abc"}, "hello")
    assert (hello.convention, hello.hand_frame, hello.height, hello.token) == ("unity", "forward", 1.8, "abc")

"""SparseTracker: online frame-by-frame use equals the offline batch path; bad frames are refused."""

from dataclasses import replace

import pytest
import torch

from humotion.assets import demo_clip_path
from humotion.canonical import JOINTS, to_canonical
from humotion.io import load_motion
from humotion.sparse.model import SparseConfig, SparsePoser
from humotion.sparse.recording import HeadsetFrame, stream_from_motion
from humotion.sparse.tracker import SparseTracker, estimate_height, resample_stream


@pytest.fixture(scope="module")
def stream():
    motion = to_canonical(load_motion(demo_clip_path()))[:45]       # 1.5 s at 30 fps
    return stream_from_motion(motion, "HT", generator=torch.Generator().manual_seed(0))


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    poser = SparsePoser(SparseConfig(embed=8, hidden=32, feedforward=64, decoder=64))
    poser.fps = 30.0
    return poser.eval()


def test_online_equals_offline(stream, model):
    assert 0 < stream.visible.float().mean() < 1  # the clip really has hands leaving the view
    tracker = SparseTracker(model)
    online = [tracker.update(frame) for frame in stream.frames()]
    offline = SparseTracker(model).track(stream)
    assert offline.num_frames == len(online)
    positions = torch.stack([p.positions for p in online])
    assert torch.allclose(positions, offline.world_positions(), atol=1e-4)
    assert tracker.height == pytest.approx(estimate_height(float(stream.head_positions[0, 1])))


def test_a_recordings_frame_is_what_update_takes(stream):
    """HeadsetStream.frame(t): frame t's time and poses, a hand not seen on it None."""
    hidden, seen = (int(torch.nonzero(flags)[0]) for flags in (~stream.visible[:, 0], stream.visible[:, 0]))
    frame = stream.frame(hidden)
    assert isinstance(frame, HeadsetFrame) and frame.timestamp == float(stream.timestamps[hidden])
    assert torch.equal(frame.head[0], stream.head_rotations[hidden])
    assert torch.equal(frame.head[1], stream.head_positions[hidden])
    assert frame.left is None and stream.frame(seen).left is not None
    assert torch.equal(stream.frame(seen).left[1], stream.left_positions[seen])
    assert [f.timestamp for f in stream.frames()] == stream.timestamps.tolist()


def test_onnx_runtime_gives_the_torch_poses(stream, model, tmp_path, monkeypatch):
    from humotion.skeleton import _depth_levels

    monkeypatch.setenv("HUMOTION_CACHE", str(tmp_path))     # the small model is exported into the cache
    _depth_levels.cache_clear()     # the export comes first: what it traces must not stay cached for PyTorch
    assert SparseTracker(model).runtime == "torch"            # "auto" exports nothing unasked
    tracker, onnx_tracker = SparseTracker(model, runtime="torch"), SparseTracker(model, runtime="onnx")
    exported = list((tmp_path / "sparse").glob("frame-*-anchored.onnx"))
    assert len(exported) == 1
    first_run = []
    for frame in stream.frames():
        torch_pose, onnx_pose = tracker.update(frame), onnx_tracker.update(frame)
        assert torch.allclose(onnx_pose.positions, torch_pose.positions, atol=1e-4)
        assert torch.allclose(onnx_pose.rotations, torch_pose.rotations, atol=1e-4)
        first_run.append(onnx_pose.positions)
    onnx_tracker.reset()                                      # a new stream rebinds fresh state buffers
    for frame, positions in zip(stream.frames(), first_run):
        assert torch.equal(onnx_tracker.update(frame).positions, positions)
    assert SparseTracker(model).runtime == "onnx"             # "auto" takes the export now at hand
    assert list((tmp_path / "sparse").iterdir()) == exported  # ... reusing the cached file
    with pytest.raises(ValueError, match="runtime"):
        SparseTracker(model, runtime="tensorflow")


def test_frame_function_quaternions_match_humotion_rotations():
    """Quaternions as humotion.rotations gives them, half turns (w = 0, sign ties) included."""
    from humotion import rotations as rot
    from humotion.rotations import matrix_to_quat_in_one_product as matrix_to_quat

    g = torch.Generator().manual_seed(0)
    turns = torch.cat([torch.randn(1000, 3, generator=g) * 2, torch.eye(3) * torch.pi, torch.zeros(1, 3)])
    matrices = rot.convert(turns, "rotvec", "matrix")
    assert torch.allclose(matrix_to_quat(matrices), rot.matrix_to_quat(matrices), atol=1e-6)


@pytest.mark.parametrize("name", ["default", "accurate", "fast"])
def test_shipped_onnx_matches_the_shipped_weights(stream, name):
    from humotion.sparse.frame import onnx_file
    from humotion.sparse.tracker import SHIPPED_WEIGHTS, load_weights

    # regenerate with `humotion export sparse [--weights accurate] -o ...` after retraining or changing the frame function
    assert onnx_file(load_weights(name)) == SHIPPED_WEIGHTS[name].with_suffix(".onnx")
    tracker, onnx_tracker = SparseTracker(name, runtime="torch"), SparseTracker(name)
    assert onnx_tracker.runtime == "onnx"
    for frame in map(stream.frame, range(10)):
        torch_pose, onnx_pose = tracker.update(frame), onnx_tracker.update(frame)
        assert torch.allclose(onnx_pose.positions, torch_pose.positions, atol=1e-4)


def test_faster_stream_is_thinned_to_the_model_rate(stream, model):
    fast = resample_stream(stream, 90.0)
    assert len(fast) == 3 * (len(stream) - 1) + 1
    tracker = SparseTracker(model, height=1.75)
    poses = [tracker.update(frame) for frame in fast.frames()]
    distinct = {p.positions.sum().item() for p in poses}
    assert len(distinct) == len(stream)  # one network step per model frame
    assert abs(tracker.skeleton.height() - 1.75) < 1e-6


def test_bad_frames_are_refused(stream, model):
    tracker = SparseTracker(model)
    first = stream.frame(0)
    tracker.update(first)
    with pytest.raises(ValueError, match="earlier than the previous frame"):
        tracker.update(replace(first, timestamp=first.timestamp - 1.0))
    head = (torch.full((3, 3), float("nan")), torch.zeros(3))
    with pytest.raises(ValueError, match="NaN"):
        SparseTracker(model).update(HeadsetFrame(0.0, head))
    with pytest.raises(FileNotFoundError, match="humotion train sparse"):
        SparseTracker("/nonexistent/weights.pt")


def test_anchoring_puts_the_eyes_on_the_headset(stream, model):
    from humotion.sparse import signals as sg
    from humotion.sparse.tracker import anchor_to_head

    free = SparseTracker(model, anchor_head=False, solve=None).track(stream)    # the network's pose as it is
    anchored = anchor_to_head(free, stream.head_positions)
    r, p = anchored.world()
    eyes = p[:, JOINTS.index("head")] + (r[:, JOINTS.index("head")] @ sg.eye_offset(anchored.skeleton).float()[:, None])[..., 0]
    assert torch.allclose(eyes, stream.head_positions.float(), atol=1e-5)
    assert torch.equal(anchored.rotations, free.rotations)  # only the root moves
    assert torch.allclose(SparseTracker(model, solve=None).track(stream).world_positions(), anchored.world_positions(),
                          atol=1e-5)


def test_shipped_weights_track_a_held_out_subject(mocap):
    """CMU subject 03 is in the test split: the shipped model clearly beats a body standing still under
    the headset (the rest pose, anchored the same way) by a wide margin."""
    from humotion.motion import Motion
    from humotion.sparse import metrics
    from humotion.sparse.tracker import anchor_to_head

    truth = to_canonical(load_motion(mocap / "cmu_cyun9601/amc/03/03_01.amc.gz")).resample(30.0)[:300]
    stream = stream_from_motion(truth, "MC")
    tracker = SparseTracker()
    predicted = tracker.track(stream)
    rest = anchor_to_head(Motion.rest(predicted.skeleton, len(stream), 30.0), stream.head_positions)
    true_p = truth.world_positions()
    error = metrics.mpjpe(predicted.world_positions(), true_p)
    baseline = metrics.mpjpe(rest.world_positions(), true_p)
    # (on the user-scaled template skeleton, not the subject's own bone lengths)
    assert error < 25.0 and error < 0.7 * baseline, (error, baseline)


def test_reset_estimates_the_next_users_height_afresh(stream, model):
    tracker = SparseTracker(model)
    tracker.update(stream.frame(0))
    first = tracker.height
    tracker.reset()
    head_rotation, head_position = stream.head_rotations[0], stream.head_positions[0] * 1.1   # a taller user
    tracker.update(HeadsetFrame(0.0, (head_rotation, head_position)))
    assert tracker.height == pytest.approx(first * 1.1, rel=1e-4)

"""The plausibility gate: glitched headset samples never reach the network, and the tracker recovers."""

import inspect
import math
import warnings
from dataclasses import replace

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from humotion.assets import demo_clip_path
from humotion.canonical import canonical_skeleton, to_canonical
from humotion.io import load_motion
from humotion.sparse.gate import GateLimits, HeadsetGate, TrackingWarning, gate_stream, rotation_problem
from humotion.sparse.model import SparseConfig, SparsePoser
from humotion.sparse.recording import HeadsetFrame, HeadsetStream, stream_from_motion
from humotion.sparse.tracker import SparseTracker

KILOMETRE = torch.tensor([1000.0, 0.0, 0.0], dtype=torch.float64)


def Tracker(model, **options):
    """A tracker giving the network's pose as it is (no arm / foot solve after it, whose own
    state -- planted feet, the floor from the first second -- is not what these tests are about)."""
    if "solve" in inspect.signature(SparseTracker).parameters:
        options.setdefault("solve", None)
    return SparseTracker(model, **options)


@pytest.fixture(scope="module")
def stream():
    """1.5 s of a CMU clip (the bundled demo clip) as a hand-tracking headset records it."""
    motion = to_canonical(load_motion(demo_clip_path()))[:45]
    return stream_from_motion(motion, "HT", generator=torch.Generator().manual_seed(0))


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    poser = SparsePoser(SparseConfig(embed=8, hidden=32, feedforward=64, decoder=64))
    poser.fps = 30.0
    return poser.eval()


@pytest.fixture(autouse=True)
def one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)        # a frame's small products: threads only add overhead on a busy machine
    yield
    torch.set_num_threads(threads)


def frame(stream, t, head_position=None, head_rotation=None, left=None):
    """Frame t of the stream, with the head's position or rotation or the left hand replaced when given."""
    original = stream.frame(t)
    head = (original.head[0] if head_rotation is None else head_rotation,
            original.head[1] if head_position is None else head_position)
    return replace(original, head=head, left=original.left if left is None else left)


def track_frames(tracker, frames):
    return torch.stack([tracker.update(f).positions for f in frames])


def as_recording(frames):
    """The frames as a HeadsetStream (a hand not tracked: NaN and not visible)."""
    unseen = (torch.full((3, 3), math.nan), torch.full((3,), math.nan))
    devices = [[f.head for f in frames], [unseen if f.left is None else f.left for f in frames],
               [unseen if f.right is None else f.right for f in frames]]
    return HeadsetStream(torch.tensor([f.timestamp for f in frames], dtype=torch.float64),
                         *(torch.stack([torch.as_tensor(pose[i], dtype=torch.float64) for pose in poses])
                           for poses in devices for i in range(2)),
                         torch.tensor([[f.left is not None, f.right is not None] for f in frames]))


def quiet(function, *args):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", TrackingWarning)
        return function(*args)


# -- the gate on its own ---------------------------------------------------------------------

def rotation_z(angle):
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


@pytest.mark.parametrize("matrix, problem", [
    (np.eye(3), None),
    (rotation_z(2.0), None),
    (np.full((3, 3), np.nan), "NaN"),
    (np.eye(3) * 1.5, "not a rotation"),
    (np.diag([1.0, 1.0, -1.0]), "reflection"),
    (np.arange(9.0).reshape(3, 3), "not a rotation"),
    (np.zeros((3, 3)), "not a rotation"),
    (np.diag([1.0, 1.0, 1.001]), None),              # float noise passes
])
def test_rotations_are_recognised(matrix, problem):
    found = rotation_problem(matrix, GateLimits().orthonormal_tolerance)
    assert (found is None) if problem is None else (problem in found)


def test_speeds_a_person_reaches_pass_and_faster_ones_do_not():
    limits = GateLimits()
    rotations = np.stack([np.eye(3)] * 3)
    head = np.array([0.0, 1.6, 0.0])

    def judge(head_step, hand_step, turn=0.0, dt=1 / 30):
        gate = HeadsetGate(limits)
        positions = np.stack([head, head + [0.3, -0.5, 0.3], head + [-0.3, -0.5, 0.3]])
        gate.check(rotations, positions, [True, True], 0.0)
        moved = positions + np.stack([head_step, hand_step, np.zeros(3)])
        turned = np.stack([rotation_z(turn), np.eye(3), np.eye(3)])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", TrackingWarning)
            verdict = gate.check(turned, moved, [True, True], dt)
        return verdict.head, verdict.hands[0]

    slack = limits.slack[0]
    assert judge([limits.head_speed / 30, 0, 0], [0, 0, 0]) == (True, True)                 # a sprinter's head
    assert judge([(limits.head_speed + 3) / 30 + slack, 0, 0], [0, 0, 0])[0] is False
    assert judge([0, 0, 0], [0.6, 0, 0]) == (True, True)                                    # an 18 m/s punch
    assert judge([0, 0, 0], [(limits.hand_speed + 3) / 30 + slack, 0, 0]) == (True, False)
    assert judge([0, 0, 0], [0, 0, 0], turn=0.5) == (True, True)                              # 15 rad/s head turn
    assert judge([0, 0, 0], [0, 0, 0], turn=2.0)[0] is False                                  # 60 rad/s
    assert judge([0, 0, 0], [0, 0, 1.5], dt=1.0) == (True, False)                             # out of reach


# -- the tracker -----------------------------------------------------------------------------

def test_a_glitched_head_sample_is_held_and_the_stream_goes_on_as_a_fresh_one(stream, model):
    """The measured failure: one head sample 1 km away. The pose is held on that frame, a warning
    says so, the network restarts on the next frame, exactly as a tracker started there would."""
    glitch = 10
    frames = [frame(stream, t, stream.head_positions[t] + KILOMETRE if t == glitch else None) for t in range(30)]
    tracker = Tracker(model, height=1.7)
    with pytest.warns(TrackingWarning, match="head: moved 1e\\+03 m"):
        poses = track_frames(tracker, frames)
    assert torch.isfinite(poses).all()
    assert torch.equal(poses[glitch], poses[glitch - 1])
    fresh = track_frames(Tracker(model, height=1.7), frames[glitch + 1:])
    assert torch.allclose(poses[glitch + 1:], fresh, atol=1e-5)
    assert (tracker.rejected.head, tracker.rejected.frames, tracker.rejected.restarts) == (1, 1, 1)


def test_garbage_hands_count_as_unseen_hands(stream, model):
    garbage = {3: (torch.full((3, 3), math.nan), torch.zeros(3)),
               4: (torch.randn(3, 3, generator=torch.Generator().manual_seed(1)), stream.left_positions[4]),
               5: (stream.head_rotations[5], stream.head_positions[5] + KILOMETRE)}
    glitched = [frame(stream, t, left=garbage.get(t)) for t in range(12)]
    unseen = [replace(f, left=None) if t in garbage else f for t, f in enumerate(glitched)]
    tracker = Tracker(model, height=1.7)
    with pytest.warns(TrackingWarning, match="left hand"):
        poses = track_frames(tracker, glitched)
    assert torch.equal(poses, track_frames(Tracker(model, height=1.7), unseen))
    assert (tracker.rejected.left, tracker.rejected.head, tracker.rejected.restarts) == (3, 0, 0)


def test_a_jump_that_persists_becomes_the_new_origin(stream, model):
    """Re-centering or teleporting in VR: the whole user moves 5 m and stays; after the rebase time
    the new place is accepted (the eyes on the headset again), well within a second."""
    shift = torch.tensor([5.0, 0.0, -3.0], dtype=torch.float64)
    jump = 10
    frames = []
    for t in range(30):
        moved = t >= jump
        left = (stream.left_rotations[t], stream.left_positions[t] + shift) if moved and stream.visible[t, 0] else None
        frames.append(frame(stream, t, stream.head_positions[t] + shift if moved else None, left=left))
    tracker = Tracker(model, height=1.7)
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always", TrackingWarning)
        poses = [tracker.update(f) for f in frames]
    assert "head: moved" in str(said[0].message) and "new origin" in str(said[-1].message)
    rebase = jump + next(i for i, p in enumerate(poses[jump:]) if not torch.equal(p.positions, poses[jump - 1].positions))
    limits = GateLimits()
    assert rebase - jump <= max(limits.rebase_frames, math.ceil(limits.rebase_s * 30)) < 30
    assert tracker.rejected.rebased == 1 and tracker.rejected.head == rebase - jump
    fresh = track_frames(Tracker(model, height=1.7), frames[rebase:])
    assert torch.allclose(torch.stack([p.positions for p in poses[rebase:]]), fresh, atol=1e-5)


def test_after_a_new_origin_the_solved_body_is_a_fresh_trackers(stream, model):
    """Planted feet and the wrists' blends refer to places of the old origin: the arm and foot
    solve forgets them when the network restarts there (else a foot is dragged from 6 m away)."""
    shift = torch.tensor([5.0, 0.0, -3.0], dtype=torch.float64)
    frames = [frame(stream, t, stream.head_positions[t] + shift * (t >= 10),
                    left=(stream.left_rotations[t], stream.left_positions[t] + shift * (t >= 10))) for t in range(30)]
    tracker = SparseTracker(model, height=1.7, floor=0.0)
    poses = quiet(lambda: [tracker.update(f) for f in frames])
    rebase = 10 + tracker.rejected.head
    fresh = track_frames(SparseTracker(model, height=1.7, floor=0.0), frames[rebase:])
    assert torch.allclose(torch.stack([p.positions for p in poses[rebase:]]), fresh, atol=1e-4)


def test_a_broken_network_state_is_reinitialised(stream, model):
    tracker = Tracker(model, height=1.7, runtime="torch")
    frames = [frame(stream, t) for t in range(8)]
    for f in frames[:4]:
        tracker.update(f)
    stream_state = tracker._stream
    for value in (math.nan, 1e6):
        state = list(stream_state.state())
        state[5] = torch.full_like(state[5], value)       # the internal root: NaN, then 1000 km away
        stream_state._state = tuple(state)
        with pytest.warns(TrackingWarning, match="restarted"):
            pose = tracker.update(frames[4 if math.isnan(value) else 5])
        assert torch.isfinite(pose.positions).all()
    assert tracker.rejected.restarts == 2 and tracker.rejected.frames == 0


def test_without_the_gate_the_state_guard_still_recovers_from_a_1_km_sample(stream, model):
    frames = [frame(stream, t, stream.head_positions[t] + KILOMETRE if t == 5 else None) for t in range(20)]
    tracker = Tracker(model, height=1.7, gate=None)
    poses = quiet(track_frames, tracker, frames)
    assert torch.isfinite(poses).all()
    fresh = track_frames(Tracker(model, height=1.7), frames[6:])
    assert torch.allclose(poses[6:], fresh, atol=1e-5)      # restarted on the glitch's frame and the one after
    assert tracker.rejected.restarts == 2 and tracker.rejected.frames == 0


def test_track_applies_the_same_rules_as_update(stream, model):
    """A recording with glitches: track() gives update()'s poses and counts."""
    frames = []
    for t in range(40):
        head = stream.head_positions[t] + KILOMETRE if t in (6, 7) else None
        rotation = torch.eye(3, dtype=torch.float64) * 2 if t == 20 else None
        left = (stream.left_rotations[t], stream.left_positions[t] + 3.0) if t == 30 else None
        frames.append(frame(stream, t, head, rotation, left))
    tracker = Tracker(model, height=1.7)
    online = quiet(track_frames, tracker, frames)
    counts = tracker.rejected
    offline = Tracker(model, height=1.7)
    with pytest.warns(TrackingWarning, match="4 frames"):
        motion = offline.track(as_recording(frames))
    assert torch.allclose(motion.world_positions(), online, atol=1e-4)
    assert offline.rejected == counts and (counts.head, counts.left, counts.restarts) == (3, 1, 2)


def test_a_recording_without_any_usable_head_is_refused(stream):
    bad = HeadsetStream(stream.timestamps[:3], torch.full((3, 3, 3), math.nan), stream.head_positions[:3],
                        stream.left_rotations[:3], stream.left_positions[:3], stream.right_rotations[:3],
                        stream.right_positions[:3], stream.visible[:3])
    with pytest.raises(ValueError, match="no frame of the recording has a usable head pose"):
        quiet(gate_stream, bad)


# -- random garbage, then valid frames -------------------------------------------------------

PREFIX, GAP, SUFFIX = 4, 12, 12      # valid frames, frames of garbage at most, valid frames after


@pytest.fixture(scope="module")
def fresh_after_gap(stream, model):
    """A fresh tracker's poses on the valid frames after the garbage (started on the first)."""
    frames = [frame(stream, t) for t in range(PREFIX + GAP, PREFIX + GAP + SUFFIX)]
    with torch.no_grad():
        torch.set_num_threads(1)
        return track_frames(Tracker(model, height=1.7), frames)


def garbage_pose(kind, value, t, i, stream):
    """A head or hand pose no person produces, on the i-th frame of garbage. The i-th jump is
    (i + 1) times value (>= 20 m, beyond anything plausible over the gap) with alternating sign,
    so no two are consistent with each other (a consistent jump is a legitimate re-centering)."""
    rotation, position = stream.head_rotations[t].clone(), stream.head_positions[t].clone()
    if kind == "nan":
        position[1] = math.nan
    elif kind == "inf":
        rotation[0, 0] = math.inf
    elif kind == "jump":
        position = position + (i + 1) * (-1) ** i * torch.tensor([value, value / 2, -value], dtype=torch.float64)
    elif kind == "scaled":
        rotation = rotation * value
    elif kind == "matrix":
        rotation = torch.randn(3, 3, generator=torch.Generator().manual_seed(int(value * 1000)), dtype=torch.float64) * 3
    return rotation, position


KINDS = ("nan", "inf", "jump", "scaled", "matrix")
garbage_frames = st.lists(st.tuples(st.sampled_from(KINDS), st.floats(20.0, 1e4),
                                    st.sampled_from(KINDS + ("none",)), st.booleans()), min_size=1, max_size=GAP)


@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(garbage=garbage_frames)
def test_after_random_garbage_the_pose_returns_to_a_fresh_trackers(stream, model, fresh_after_gap, garbage):
    """Random garbage (NaN, infinity, jumps of tens of metres to kilometres, scaled and random matrices)
    in the head and hands, then valid frames: the tracker never breaks, and once the garbage ends
    it gives what a fresh tracker started on the first valid frame gives (the gate restarts the
    network's state there), so within one second -- in fact from that first frame -- the pose is
    within 1 cm of the fresh tracker's."""
    tracker = Tracker(model, height=1.7)
    frames = [frame(stream, t) for t in range(PREFIX)]
    for i, (head_kind, value, hand_kind, hand_visible) in enumerate(garbage):
        t = PREFIX + i
        head = garbage_pose(head_kind, value, t, i, stream)
        left = None if hand_kind == "none" else garbage_pose(hand_kind, value, t, i, stream)
        right = (stream.right_rotations[t], stream.right_positions[t])            # NaN where the stream has none
        frames.append(HeadsetFrame(float(stream.timestamps[t]), head, left if hand_visible else None, right))
    valid = [frame(stream, t) for t in range(PREFIX + GAP, PREFIX + GAP + SUFFIX)]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", TrackingWarning)
        during = track_frames(tracker, frames)
        after = track_frames(tracker, valid)
    assert torch.isfinite(during).all() and torch.isfinite(after).all()
    assert tracker.rejected.head == len(garbage) and caught
    error = (after - fresh_after_gap).norm(dim=-1).max()
    assert error < 0.01, f"{error * 100:.2f} cm from a fresh tracker's pose"


# -- the track command -----------------------------------------------------------------------

@pytest.fixture(scope="module")
def weights(model, tmp_path_factory):
    from humotion.sparse.model import save_sparse_model

    path = tmp_path_factory.mktemp("weights") / "small.pt"
    save_sparse_model(model, path, fps=30.0)
    return path


def glitched_recording(stream, path):
    from humotion.sparse.recording import write_recording

    heads = stream.head_positions.clone()
    heads[10] += KILOMETRE
    glitched = HeadsetStream(stream.timestamps, stream.head_rotations, heads, stream.left_rotations,
                             stream.left_positions, stream.right_rotations, stream.right_positions, stream.visible)
    write_recording(glitched, path, convention="humotion")
    return path


def test_track_command_says_how_many_frames_it_rejected(stream, weights, tmp_path):
    from click.testing import CliRunner

    from humotion.cli import main

    path = glitched_recording(stream, tmp_path / "glitch.csv")
    result = CliRunner().invoke(main, ["track", str(path), "--convention", "humotion", "--weights", str(weights),
                                       "-o", str(tmp_path / "body.bvh")])
    assert result.exit_code == 0, result.output
    assert "1 frame with implausible samples rejected (head held 1" in result.output
    assert (tmp_path / "body.bvh").is_file()


def test_track_command_never_writes_a_nan_motion_silently(stream, weights, tmp_path, monkeypatch):
    from click.testing import CliRunner

    from humotion.cli import main
    from humotion.motion import Motion

    def broken(self, recording):
        motion = Motion.rest(canonical_skeleton(), len(recording), 30.0)
        return Motion(motion.skeleton, motion.rotations, torch.full_like(motion.root_positions, math.nan), 30.0)

    monkeypatch.setattr(SparseTracker, "track", broken)
    path = glitched_recording(stream, tmp_path / "glitch.csv")
    result = CliRunner().invoke(main, ["track", str(path), "--convention", "humotion", "--weights", str(weights),
                                       "-o", str(tmp_path / "body.bvh")])
    assert result.exit_code == 1 and "NaN" in result.output
    assert not (tmp_path / "body.bvh").exists()

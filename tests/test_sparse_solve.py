"""The solve after the sparse-tracking network (humotion.sparse.solve): two-bone IK against known
answers, then the shipped tracker on held-out CMU clips (subjects 06 and 09, in the test split) with its
wrists on the tracked hands and its feet on the floor."""

import numpy as np
import pytest
import torch

from humotion.canonical import JOINTS, to_canonical
from humotion.io import load_motion
from humotion.sparse import metrics
from humotion.sparse import solve as sv
from humotion.sparse.recording import HeadsetFrame, HeadsetStream, stream_from_motion
from humotion.sparse.tracker import SparseTracker

WRISTS = [JOINTS.index("left_wrist"), JOINTS.index("right_wrist")]


def chains(count=200, seed=0):
    g = np.random.default_rng(seed)
    root = g.normal(size=(count, 3))
    upper, lower = g.uniform(0.2, 0.4, count), g.uniform(0.2, 0.4, count)
    return g, root, upper, lower


def test_two_bone_ik_reaches_reachable_targets_exactly_and_keeps_bone_lengths():
    g, root, upper, lower = chains()
    for k in range(len(root)):
        direction = g.normal(size=3)
        distance = g.uniform(abs(upper[k] - lower[k]) + 0.01, upper[k] + lower[k] - 0.01)
        target = root[k] + direction / np.linalg.norm(direction) * distance
        middle, end = sv.two_bone_ik(root[k], target, g.normal(size=3), upper[k], lower[k])
        assert np.allclose(end, target, atol=1e-9)
        assert np.linalg.norm(middle - root[k]) == pytest.approx(upper[k], abs=1e-9)
        assert np.linalg.norm(end - middle) == pytest.approx(lower[k], abs=1e-9)


def test_two_bone_ik_stretches_toward_unreachable_targets():
    g, root, upper, lower = chains(seed=1)
    for k in range(len(root)):
        direction = g.normal(size=3)
        direction /= np.linalg.norm(direction)
        target = root[k] + direction * (upper[k] + lower[k]) * g.uniform(1.05, 3.0)
        middle, end = sv.two_bone_ik(root[k], target, g.normal(size=3), upper[k], lower[k])
        assert np.allclose(end, root[k] + direction * (upper[k] + lower[k]), atol=1e-6)   # straight, pointing at it
        assert np.linalg.norm(middle - root[k]) == pytest.approx(upper[k], abs=1e-9)


def test_the_swivel_follows_the_pole():
    root, target = np.zeros(3), np.array([0.0, -0.4, 0.0])
    for pole in ([1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [-0.6, 0.3, 0.8]):
        pole = np.array(pole)
        middle, _ = sv.two_bone_ik(root, target, pole, 0.3, 0.3)
        side = pole - pole @ np.array([0.0, -1.0, 0.0]) * np.array([0.0, -1.0, 0.0])
        bend = middle - middle @ np.array([0.0, -1.0, 0.0]) * np.array([0.0, -1.0, 0.0])
        assert np.allclose(bend / np.linalg.norm(bend), side / np.linalg.norm(side), atol=1e-9)


def test_rotation_between_turns_one_direction_onto_the_other():
    g = np.random.default_rng(2)
    pairs = [(g.normal(size=3), g.normal(size=3)) for _ in range(50)] + [(np.array([1.0, 2, 3]), -np.array([1.0, 2, 3]))]
    for a, b in pairs:
        turn = sv.rotation_between(a, b)
        assert np.allclose(turn @ turn.T, np.eye(3), atol=1e-9) and np.linalg.det(turn) == pytest.approx(1.0)
        assert np.allclose(turn @ a / np.linalg.norm(a), b / np.linalg.norm(b), atol=1e-9)


@pytest.fixture(scope="module")
def walk(mocap):
    """CMU subject 09 walking (held out from training) at 30 fps on the canonical body."""
    return to_canonical(load_motion(mocap / "cmu_sxaxmz/amc/09/09_12__walk.amc.gz")).resample(30.0)[:300]


@pytest.fixture(scope="module")
def clip(mocap):
    """10 s of CMU subject 06 (held out from training) at 30 fps on the canonical body."""
    return to_canonical(load_motion(mocap / "cmu_sxaxmz/amc/06/06_12__basketball_.amc.gz")).resample(30.0)[:300]


@pytest.fixture(scope="module")
def tracker():
    return SparseTracker(runtime="torch", floor=0.0)      # the capture's ground, as a headset's stage space gives it


def foot_figures(motion, floor=0.0):
    body = sv.BodyGeometry.of(motion.skeleton)
    positions = motion.world_positions()
    penetration, _ = metrics.penetration(positions, body.clearance, floor)
    contacts = sv.foot_contacts(positions.double().numpy(), body.clearance, floor, motion.fps)
    return penetration, metrics.skating(positions, contacts, motion.fps)


def test_controllers_hold_the_wrists_and_the_feet_stand_on_the_floor(walk, tracker):
    stream = stream_from_motion(walk, "MC")
    solved, alone = tracker.track(stream), SparseTracker(tracker.model, runtime="torch", solve=None).track(stream)
    targets = torch.stack([stream.left_positions, stream.right_positions], 1).float()
    error, _ = metrics.target_error(solved.world_positions(), targets, stream.visible)
    assert error < 1.0, error
    assert metrics.target_error(alone.world_positions(), targets, stream.visible)[0] > 3.0   # the solve did it
    penetration, (skating, contacts) = foot_figures(solved)
    assert penetration < 1.0 and contacts > 30 and skating < 3.0, (penetration, skating, contacts)


def planted_online(motion, stream, settings=sv.SolveSettings(), floor=0.0):
    """(solved world positions (F, J, 3), (F, 2) bool the feet the solve holds planted), solving
    one frame at a time as SparseTracker.update does."""
    body, state = sv.BodyGeometry.of(motion.skeleton), sv.SolveState()
    local, world_p = motion.rotations.double().numpy(), motion.world_positions().double().numpy()
    r, p, visible = stream.rotations.double().numpy(), stream.positions.double().numpy(), stream.visible.numpy()
    solved, planted = np.empty_like(world_p), np.zeros((len(local), 2), bool)
    for t in range(len(local)):
        now = slice(t, t + 1)
        _, solved[now] = sv.solve_frames(local[now], world_p[now], body, r[now, 1:], p[now, 1:], visible[now],
                                         p[now, 0, 1], motion.fps, floor, state, settings)
        planted[t] = state.locked
    return solved, planted


@pytest.mark.parametrize("raise_cm", [0.0, 2.0])
def test_feet_floating_above_the_floor_are_still_planted(walk, tracker, raise_cm):
    """The network's body on the walking take, and raised 2 cm (a network whose feet float
    higher): the solve plants the feet where the motion capture is in contact, and the solved
    feet in contact do not skate. Recall (precision) against the truth's contacts by the metrics'
    rule, the shipped network as is / raised: with the fixed 6 cm rule of before 0.40 (0.84) /
    0.00 (no foot planted), with the relative rule 0.67 (0.81) / 0.62 (0.85); the network shipped
    before the fine-tuned one: 0.39 (0.73) / 0.11 (0.81) against 0.64 (0.81) / 0.57 (0.82)."""
    stream = stream_from_motion(walk, "MC")
    alone = SparseTracker(tracker.model, runtime="torch", solve=None).track(stream)
    alone.root_positions[:, 1] += raise_cm / 100
    solved, planted = planted_online(alone, stream)
    truth = sv.foot_contacts(walk.world_positions().double().numpy(), sv.foot_clearance(walk.skeleton), 0.0, walk.fps)
    hits = (planted & truth).sum()
    assert hits / truth.sum() > 0.45 and hits / planted.sum() > 0.75, (hits / truth.sum(), hits / planted.sum())
    clearance = sv.foot_clearance(alone.skeleton)                   # the tracker's body, sized from the headset
    penetration, _ = metrics.penetration(solved, clearance, 0.0)
    skating, _ = metrics.skating(solved, sv.foot_contacts(solved, clearance, 0.0, walk.fps), walk.fps)
    assert penetration < 1.0 and skating < 1.0, (penetration, skating)


def hide(stream: HeadsetStream, side: str, frames: slice) -> HeadsetStream:
    fields = {name: getattr(stream, name).clone() for name in ("timestamps", "head_rotations", "head_positions",
                                                              "left_rotations", "left_positions", "right_rotations",
                                                              "right_positions", "visible")}
    fields[f"{side}_rotations"][frames] = float("nan")
    fields[f"{side}_positions"][frames] = float("nan")
    fields["visible"][frames, ("left", "right").index(side)] = False
    return HeadsetStream(**fields)


def test_a_hand_reentering_the_view_does_not_jump(clip, tracker):
    stream = hide(stream_from_motion(clip, "MC"), "right", slice(60, 120))
    wrist = tracker.track(stream).world_positions()[:, WRISTS[1]]
    true = clip.world_positions()[: len(wrist), WRISTS[1]]
    steps = (wrist.diff(dim=0) - true.diff(dim=0)).norm(dim=-1)[115:150]       # around re-entry at frame 120
    assert steps.max() < 0.05, steps.max()
    seen = (wrist - torch.nan_to_num(stream.right_positions.float())).norm(dim=-1)
    assert seen[150:].max() < 0.02      # blended in: on the hand again


def test_a_body_below_the_floor_is_lifted_not_sunk(clip, tracker):
    """Headset and hands lowered 1.2 m after the first second (a user lying down): the feet stay
    above the floor found in that first second (running_floor)."""
    stream = stream_from_motion(clip, "MC")
    for name in ("head_positions", "left_positions", "right_positions"):
        getattr(stream, name)[30:, 1] -= 1.2
    solved = SparseTracker(tracker.model, runtime="torch", gate=None).track(stream)
    body = sv.BodyGeometry.of(solved.skeleton)
    floor = sv.running_floor(stream.head_positions[:, 1].numpy(), body.standing_eye, 30.0)
    penetration, _ = foot_figures(solved, floor)
    assert penetration == 0.0


def test_update_frame_by_frame_gives_the_poses_of_track(clip, tracker):
    stream = stream_from_motion(clip[:90], "HT", generator=torch.Generator().manual_seed(0))
    offline = tracker.track(stream).world_positions()
    tracker.reset()
    online = [tracker.update(frame).positions for frame in stream.frames()]
    assert torch.allclose(torch.stack(online), offline, atol=1e-4)


def test_calibrate_sizes_the_arms_from_a_t_pose(tracker):
    from humotion.canonical import canonical_skeleton
    from humotion.sparse.signals import eye_offset

    body = canonical_skeleton(1.80)
    rest = body.rest_positions(torch.float64).numpy()
    head = rest[JOINTS.index("head")] + eye_offset(body).numpy()
    left, right = rest[WRISTS[0]].copy(), rest[WRISTS[1]].copy()
    reach = left - rest[JOINTS.index("left_shoulder")]
    left += 0.1 * reach
    right -= 0.1 * reach * np.array([1.0, 1.0, 1.0])      # both arms 10% longer than the template's
    calibrating = SparseTracker(tracker.model, runtime="torch")
    skeleton = calibrating.calibrate(HeadsetFrame(0.0, (np.eye(3), head), (np.eye(3), left), (np.eye(3), right)))
    assert skeleton.height() == pytest.approx(1.80, abs=0.01) and calibrating.skeleton is skeleton
    for joint in ("left_elbow", "right_wrist"):
        j = JOINTS.index(joint)
        assert np.linalg.norm(skeleton.offsets[j]) == pytest.approx(1.1 * np.linalg.norm(body.offsets[j]), rel=0.02)
    with pytest.raises(ValueError, match="T-pose"):
        calibrating.calibrate(HeadsetFrame(0.0, (np.eye(3), head), (np.eye(3), head), (np.eye(3), head)))
    with pytest.raises(ValueError, match="both hands"):
        calibrating.calibrate(HeadsetFrame(0.0, (np.eye(3), head), (np.eye(3), left)))

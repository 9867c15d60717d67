"""Classical retargeting on real takes: own skeleton, scaled copies, rest poses, foot contacts,
IK, bad input, and the `humotion retarget` command."""

import pytest
import torch
from click.testing import CliRunner

from humotion.canonical import canonical_skeleton
from humotion.cli import main
from humotion.io import load_motion
from humotion.io.asf_amc import read_asf
from humotion.motion import Motion
from humotion.retarget import (Rig, check_finite, contacts_kept, copy_rotations, foot_contacts, foot_skating,
                               retarget)
from humotion.retarget.classical import FOOT_POINTS
from humotion.retarget.ik import two_bone_ik

from test_retarget_rig import _a_pose, without


@pytest.fixture(scope="module")
def walk(mocap):
    """CMU 02_01: a 2.9 s walk on subject 02's 31-joint skeleton, 120 Hz."""
    return load_motion(mocap / "cmu_mocgui_s02/02_01.amc")


def feet(motion: Motion) -> torch.Tensor:
    return Rig.of(motion.skeleton).points(*motion.world(), FOOT_POINTS)


def test_onto_its_own_skeleton_reproduces_the_motion(walk):
    floor = Rig.of(walk.skeleton).floor_of(walk)   # the result stands on the target's floor: here the source's own
    same = retarget(walk, walk.skeleton, feet=False, floor=floor)
    assert same.skeleton is walk.skeleton and same.fps == walk.fps and same.num_frames == walk.num_frames
    assert (same.world_positions() - walk.world_positions()).norm(dim=-1).max() < 1e-3
    # With contacts kept, the legs may move a little (the capture's own slips are held); the rest stays.
    planted = retarget(walk, walk.skeleton, floor=floor)
    legs = [j for j, n in enumerate(walk.skeleton.names) if n[1:] in ("femur", "tibia", "foot", "toes")]
    others = [j for j in range(walk.skeleton.num_joints) if j not in legs]
    error = (planted.world_positions() - walk.world_positions()).norm(dim=-1)
    assert error[:, others].max() < 1e-3 and error[:, legs].max() < 0.06


def test_onto_a_scaled_copy_gives_scaled_positions(walk):
    big = retarget(walk, walk.skeleton.scaled(1.3), feet=False, floor=1.3 * Rig.of(walk.skeleton).floor_of(walk))
    assert (big.world_positions() - 1.3 * walk.world_positions()).norm(dim=-1).max() < 1.3e-3


def test_rest_poses_are_aligned_a_t_pose_stays_a_t_pose():
    t_pose = canonical_skeleton()
    standing = Motion.rest(t_pose, frames=3)
    on_a_pose = retarget(standing, _a_pose(t_pose, 45.0), feet=False)
    positions = on_a_pose.world_positions()[0]
    arm = positions[t_pose.index("left_wrist")] - positions[t_pose.index("left_shoulder")]
    assert abs(float(arm[1])) < 1e-4 and float(arm[0]) > 0.4  # arms horizontal, not lowered
    naive = copy_rotations(standing, _a_pose(t_pose, 45.0)).world_positions()[0]
    arm = naive[t_pose.index("left_wrist")] - naive[t_pose.index("left_shoulder")]
    assert float(arm[1]) < -0.2  # copying rotations keeps the target's A-pose


def test_cross_structure_onto_the_game_rig_matches_the_same_take(mocap, walk):
    game = load_motion(mocap / "cmu_iclone_ccskeleton/002_01.bvh.gz")
    rig = Rig.of(game.skeleton)
    result = retarget(walk.resample(game.fps), rig)
    assert result.skeleton.num_joints == 101 and result.fps == 60.0
    ours, truth = rig.points(*result.world(), ["pelvis", "left_wrist", "right_ankle", "head"]), \
        rig.points(*game.world(), ["pelvis", "left_wrist", "right_ankle", "head"])
    n = min(len(ours), len(truth))
    relative = (ours[:n] - ours[:n, :1]) - (truth[:n] - truth[:n, :1])  # both takes face +Z here
    assert float(relative.norm(dim=-1).mean()) < 0.08


def test_contacts_kept_and_less_skating_than_copying_rotations(walk):
    tall = walk.skeleton.scaled(1.25)
    source_contacts = foot_contacts(feet(walk), walk.fps, 1.62)
    assert 0.3 < float(source_contacts.float().mean()) < 0.8  # a walk: each foot down part of the time
    ours, naive = retarget(walk, tall), copy_rotations(walk, tall)
    skate_ours = foot_skating(feet(ours), source_contacts, walk.fps)
    skate_naive = foot_skating(feet(naive), source_contacts, walk.fps)
    assert skate_ours < 0.5 * skate_naive, (skate_ours, skate_naive)
    assert contacts_kept(source_contacts, foot_contacts(feet(ours), walk.fps, 1.62 * 1.25)) > 0.9


def test_hand_targets_are_reached(walk):
    clip = walk[:60]
    rig = Rig.of(clip.skeleton)
    wanted = rig.points(*clip.world(), ["left_wrist"])[:, 0] + torch.tensor([0.0, 0.05, 0.05])
    wanted[::2] = float("nan")  # no target on even frames
    result = retarget(clip, rig, feet=False, hand_targets={"left": wanted}, floor=rig.floor_of(clip))
    reached = rig.points(*result.world(), ["left_wrist"])[:, 0]
    assert (reached[1::2] - wanted[1::2]).norm(dim=-1).max() < 1e-3
    assert (reached[::2] - rig.points(*clip.world(), ["left_wrist"])[::2, 0]).norm(dim=-1).max() < 1e-4
    with pytest.raises(ValueError, match=r"\(60, 3\) positions, one per source frame, got shape \(30, 3\)"):
        retarget(clip, rig, hand_targets={"left": wanted[:30]})


def test_two_bone_ik_reaches_every_reachable_target():
    g = torch.Generator().manual_seed(0)
    a = torch.randn(500, 3, generator=g, dtype=torch.float64)
    b = a + torch.nn.functional.normalize(torch.randn(500, 3, generator=g, dtype=torch.float64), dim=-1) * 0.45
    c = b + torch.nn.functional.normalize(torch.randn(500, 3, generator=g, dtype=torch.float64), dim=-1) * 0.40
    target = a + torch.nn.functional.normalize(torch.randn(500, 3, generator=g, dtype=torch.float64), dim=-1) \
        * (0.1 + 0.7 * torch.rand(500, 1, generator=g, dtype=torch.float64))
    turn_a, turn_b = two_bone_ik(a, b, c, target, torch.tensor([[0.0, 0.0, 1.0]]).expand(500, 3).double())
    knee = a + (turn_a @ (b - a)[..., None])[..., 0]
    end = knee + (turn_b @ (c - b)[..., None])[..., 0]
    assert (end - target).norm(dim=-1).max() < 1e-6


def test_nan_in_the_source_names_frame_and_joint(walk):
    broken = walk[:20]
    broken.rotations = broken.rotations.clone()
    broken.rotations[7, walk.skeleton.index("lradius"), 1] = float("nan")
    with pytest.raises(ValueError, match=r"02_01: frame 7, joint 'lradius'"):
        retarget(broken, canonical_skeleton())
    with pytest.raises(ValueError, match="frame 7"):
        check_finite(broken)
    with pytest.raises(ValueError, match="02_01: the motion has no frames"):
        retarget(walk[:0], canonical_skeleton())


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def test_command_onto_a_rig_file_and_built_ins(mocap, tmp_path):
    out = tmp_path / "game.bvh"
    result = run("retarget", mocap / "cmu_mocgui_s02/02_01.amc", "--to", mocap / "cmu_iclone_ccskeleton/002_01.bvh.gz",
                 "-o", out)
    assert result.exit_code == 0, result.output
    assert "runs at 60 fps; the result keeps 120 fps" in result.output
    written = load_motion(out)
    assert written.skeleton.num_joints == 101 and written.fps == 120.0 and written.num_frames == 343
    out = tmp_path / "body.bvh"
    result = run("retarget", mocap / "cmu_iclone_ccskeleton/002_01.bvh.gz", "--to", "canonical", "--height", 1.8,
                 "--fps", 30, "-o", out)
    assert result.exit_code == 0, result.output
    body = load_motion(out)
    assert body.skeleton.num_joints == 22 and body.fps == 30.0 and body.skeleton.height() == pytest.approx(1.8, abs=1e-3)
    result = run("retarget", mocap / "cmu_mocgui_s02/02_01.amc", "--to", "cmu", "-o", tmp_path / "cmu.bvh")
    assert result.exit_code == 0 and load_motion(tmp_path / "cmu.bvh").skeleton.num_joints == 31


def test_command_errors_name_the_problem(mocap, tmp_path):
    rig = tmp_path / "no_knee.bvh"
    skeleton = without(read_asf(mocap / "cmu_fairmotion/01.asf").skeleton, "rtibia")
    from humotion.io import save_motion

    save_motion(Motion.rest(skeleton), rig)
    result = run("retarget", mocap / "cmu_mocgui_s02/02_01.amc", "--to", rig, "-o", tmp_path / "x.bvh")
    assert result.exit_code != 0 and "Traceback" not in result.output
    assert "right_knee" in result.output and "--overrides" in result.output and "no_knee.bvh" in result.output
    result = run("retarget", mocap / "cmu_mocgui_s02/02_01.amc", "--to", "nowhere", "-o", tmp_path / "x.bvh")
    assert result.exit_code != 0 and "built-in rig" in result.output

    lines = (mocap / "cmu_fairmotion/01_01.bvh").read_text().split("\n")[:400]
    motion_line = lines.index("MOTION")
    lines[motion_line + 1] = f"Frames: {len(lines) - motion_line - 3}"
    values = lines[motion_line + 10].split()
    values[5] = "nan"
    lines[motion_line + 10] = " ".join(values)
    broken = tmp_path / "broken.bvh"
    broken.write_text("\n".join(lines))
    result = run("retarget", broken, "--to", "canonical", "-o", tmp_path / "x.bvh")
    assert result.exit_code != 0 and "broken.bvh" in result.output and "NaN" in result.output


"""The learned retargeter: separation matrix, part-wise attention, shapes, a tiny training run
with checkpoints and resume, the shipped weights on a real clip, and bad input."""

import shutil

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from humotion.assets import demo_clip_path
from humotion.canonical import canonical_skeleton
from humotion.cli import main
from humotion.io import load_motion
from humotion.motion import Motion
from humotion.retarget.data import DomainWindows, pieces
from humotion.retarget.domains import DomainSpec
from humotion.retarget.learned import DEFAULT_WEIGHTS, retarget_learned
from humotion.retarget.networks import (N, MotionEncoder, RetargetConfig, RetargetNet, load_retarget_net,
                                        separation_matrix)
from humotion.retarget.parts import PARTS, membership_matrix
from humotion.retarget.rig import Rig
from humotion.retarget.train import Objective, RetargetTrainConfig, train

GAME = "cmu_iclone_ccskeleton/007_02.bvh.gz"


@pytest.fixture(scope="module")
def demo() -> Motion:
    """8 s of CMU 02_05 on the 31-joint skeleton, 30 fps (shipped with the package)."""
    return load_motion(demo_clip_path())


@pytest.fixture(scope="module")
def game(mocap) -> Motion:
    """A 2.7 s walk of CMU 07 on the 100-joint game rig, 60 fps."""
    return load_motion(mocap / GAME)


def test_separation_matrix_allows_exactly_what_membership_allows(demo):
    p = membership_matrix(Rig.of(demo.skeleton).parts)                  # (6, 32)
    u = separation_matrix(torch.as_tensor(p))
    joints = p.shape[1] - 1
    assert u.shape == (N + joints + 1,) * 2
    assert set(torch.unique(u).tolist()) == {0.0, float("-inf")}
    part_of = p[:, :-1].argmax(0)
    for row in range(N + joints + 1):
        if row < N:                                   # a part: itself, its joints, the root
            allowed = {row} | {N + j for j in range(joints) if p[row, j]} | {N + joints}
        elif row < N + joints:                        # a joint: its part, its part's joints, the root
            k = part_of[row - N]
            allowed = {int(k)} | {N + j for j in range(joints) if part_of[j] == k} | {N + joints}
        else:                                         # the root: itself
            allowed = {N + joints}
        assert {int(c) for c in torch.nonzero(u[row] == 0)} == allowed, row
    left_femur, left_humerus = demo.skeleton.index("lfemur"), demo.skeleton.index("lhumerus")
    assert u[PARTS.index("left_leg"), N + left_femur] == 0
    assert u[PARTS.index("left_leg"), N + left_humerus] == float("-inf")
    assert u[N + left_femur, N + left_humerus] == float("-inf")


def test_a_part_code_ignores_joints_of_other_parts(demo):
    torch.manual_seed(0)
    parts = tuple(int(k) for k in Rig.of(demo.skeleton).parts)
    encoder = MotionEncoder(parts, width=16, heads=2, layers=2, kernel=3).eval()
    rotations, root, codes = torch.randn(2, 10, len(parts), 6), torch.randn(2, 10, 3), torch.randn(2, N, 16)
    arm = PARTS.index("left_arm")
    members = [j for j, k in enumerate(parts) if k == arm]
    elsewhere = rotations.clone()
    elsewhere[:, :, [j for j, k in enumerate(parts) if k != arm]] += 1.0
    inside = rotations.clone()
    inside[:, :, members] += 1.0
    with torch.no_grad():
        base, moved, own = (encoder(r, root, codes) for r in (rotations, elsewhere, inside))
        tokens = encoder.attend(rotations, root, codes)
        assert torch.allclose(encoder.attend(elsewhere, root, codes)[:, :, arm], tokens[:, :, arm], atol=1e-6)
    assert torch.allclose(base[:, :, arm], moved[:, :, arm], atol=1e-6)     # after attention and convolutions
    assert not torch.allclose(base[:, :, arm], own[:, :, arm], atol=1e-3)
    assert not torch.allclose(base[:, :, PARTS.index("torso")], moved[:, :, PARTS.index("torso")], atol=1e-3)


@pytest.fixture(scope="module")
def specs(demo, game):
    return [DomainSpec.of("cmu_asf", demo.skeleton), DomainSpec.of("iclone_cc", game.skeleton)]


def test_domains_and_shapes_for_both_skeletons(specs, demo, game):
    cmu, rig = specs
    assert (cmu.num_joints, len(cmu.others), rig.num_joints, len(rig.others)) == (25, 6, 24, 76)
    assert cmu.joints[0] == "root" and rig.joints[0] == "CC_Base_Hip"
    assert "CC_Base_L_Index1" not in rig.joints and "CC_Base_L_UpperarmTwist01" not in rig.joints
    assert "CC_Base_NeckTwist02" in rig.joints                          # on the way to the head
    net = RetargetNet(RetargetConfig(domains=specs, width=16, hidden=24))
    a = DomainWindows.from_motions(cmu, [demo], length=16, stride=8, fps=30.0).batch([0, 1])
    b = DomainWindows.from_motions(rig, [game], length=16, stride=8, fps=30.0).batch([0, 1])
    assert a["rotations"].shape == (2, 16, 25, 6) and b["rotations"].shape == (2, 16, 24, 6)
    assert a["root"].shape == b["root"].shape == (2, 16, 3) and b["offsets"].shape == (2, 24, 3)
    with torch.no_grad():
        ab = net.retarget("cmu_asf", a["rotations"], a["root"], a["offsets"], "iclone_cc", b["offsets"])
        ba = net.retarget("iclone_cc", b["rotations"], b["root"], b["offsets"], "cmu_asf", a["offsets"])
        assert net.discriminators["iclone_cc"](*ab).shape == (2, 4)
    assert ab[0].shape == (2, 16, 24, 6) and ba[0].shape == (2, 16, 25, 6) and ab[1].shape == ba[1].shape == (2, 16, 3)


def test_takes_are_cut_where_the_pelvis_jumps():
    pelvis = torch.zeros(20, 3)
    pelvis[:, 2] = torch.arange(20) * 0.05                              # 1.5 m/s at 30 fps
    pelvis[6:, 0] += 2.0                                                # a 2 m jump after frame 5
    assert pieces(pelvis, 30.0) == [(0, 6), (6, 20)]
    assert pieces(pelvis[6:], 30.0) == [(0, 14)]


def test_a_few_steps_on_two_windows_lower_the_loss(specs, demo, game):
    torch.manual_seed(0)
    a = DomainWindows.from_motions(specs[0], [demo], length=16, stride=8, fps=30.0).batch([0, 20])
    b = DomainWindows.from_motions(specs[1], [game], length=16, stride=8, fps=30.0).batch([0, 4])
    model = Objective(RetargetConfig(domains=specs, width=16, hidden=24), {"rec": 1.0, "cycle": 1.0, "position": 50.0,
                                                                         "effector": 100.0, "root": 1.0})
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(12):
        total, terms = model(a, b)
        optimizer.zero_grad()
        total.backward()
        optimizer.step()
        losses.append((total - terms["discriminator"]).item())
    assert losses[-1] < 0.7 * losses[0], losses


def test_training_writes_checkpoints_and_resumes(mocap, tmp_path, monkeypatch):
    monkeypatch.setenv("HUMOTION_CACHE", str(tmp_path / "cache"))
    data = tmp_path / "data"
    for source, files in {"cmu_a": ["cmu_visdoom_mocapplayer/asf/09.asf", "cmu_visdoom_mocapplayer/amc/09_06-run.amc"],
                          "cmu_b": [GAME]}.items():
        (data / source).mkdir(parents=True)
        for f in files:
            shutil.copy(mocap / f, data / source)
    config = dict(data_root=str(data), domains={"cmu_a": ("cmu_a",), "cmu_b": ("cmu_b",)}, length=16, stride=4,
                  batch_size=2, checkpoint_every=2, out_dir=str(tmp_path / "run"), threads=1, progress=False,
                  model=RetargetConfig(width=8, hidden=8))
    first = train(RetargetTrainConfig(steps=2, **config))
    assert first["step"] == 2 and (tmp_path / "run" / "checkpoint-2.pt").is_file()
    again = train(RetargetTrainConfig(steps=4, **config))
    assert again["start_step"] == 2 and again["step"] == 4
    net = load_retarget_net(again["export"])
    assert [d.name for d in net.config.domains] == ["cmu_a", "cmu_b"] and net.fps == 30.0
    assert torch.isfinite(net.normalizers["cmu_b"].other_rotations).all()


@pytest.mark.skipif(not DEFAULT_WEIGHTS.is_file(), reason="shipped retargeter weights missing")
def test_shipped_weights_retarget_a_real_clip_onto_the_game_rig(demo, game):
    clip = demo[:60]                                                      # 2 s at 30 fps
    result = retarget_learned(clip, game.skeleton)
    assert result.skeleton is game.skeleton and result.num_frames == 60 and result.fps == clip.fps
    positions = result.world_positions()
    assert torch.isfinite(positions).all()
    rig = Rig.of(game.skeleton)
    pelvis_height = positions[:, rig.joint("pelvis"), 1] - positions[:, :, 1].amin(1)
    assert 0.6 * rig.hip_height() < float(pelvis_height.mean()) < 1.3 * rig.hip_height()
    back = retarget_learned(game[:90], demo.skeleton, feet=False)       # 60 fps in, 60 fps out
    assert back.num_frames == 90 and back.fps == 60.0 and torch.isfinite(back.world_positions()).all()


@pytest.mark.skipif(not DEFAULT_WEIGHTS.is_file(), reason="shipped retargeter weights missing")
def test_bad_input_is_refused_clearly(demo, tmp_path):
    with pytest.raises(ValueError, match="none of the skeleton domains"):
        retarget_learned(demo[:30], canonical_skeleton())
    broken = Motion(demo.skeleton, demo.rotations[:30].clone(), demo.root_positions[:30], demo.fps)
    broken.rotations[7, 3] = float("nan")
    with pytest.raises(ValueError, match="frame 7"):
        retarget_learned(broken, demo.skeleton)
    with pytest.raises(FileNotFoundError, match="humotion train retarget"):
        retarget_learned(demo[:30], demo.skeleton, weights=tmp_path / "missing.pt")
    sparse = DEFAULT_WEIGHTS.parents[1] / "sparse" / "sparse_poser.pt"
    with pytest.raises(ValueError, match="not RetargetNet weights"):
        retarget_learned(demo[:30], demo.skeleton, weights=sparse)


@pytest.mark.skipif(not DEFAULT_WEIGHTS.is_file(), reason="shipped retargeter weights missing")
def test_retarget_command_with_the_learned_method(mocap, tmp_path):
    out = tmp_path / "walk_game.bvh"
    result = CliRunner().invoke(main, ["retarget", str(demo_clip_path()), "--to", str(mocap / GAME), "--method",
                                       "learned", "-o", str(out)])
    assert result.exit_code == 0, result.output
    motion = load_motion(out)
    assert motion.skeleton.num_joints == 100 and np.isfinite(motion.rotations.numpy()).all()
    refused = CliRunner().invoke(main, ["retarget", str(demo_clip_path()), "--to", "canonical", "--method", "learned",
                                        "-o", str(tmp_path / "x.bvh")])
    assert refused.exit_code != 0 and "none of the skeleton domains" in refused.output

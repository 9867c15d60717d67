"""Sparse-tracking evaluation: known answers with an oracle model, baselines, the eval command."""

import json

import pytest
import torch
from click.testing import CliRunner

from humotion.canonical import to_canonical
from humotion.cli import main
from humotion.io import load_motion
from humotion.sparse import evaluation
from humotion.sparse.model import SparseOutput


class Oracle(torch.nn.Module):
    """A 'model' that returns the true motion whatever it is fed (rotation matrices, root)."""

    fps = 30.0

    def __init__(self, motion):
        super().__init__()
        self.motion = motion

    def forward(self, signals):
        return SparseOutput(self.motion.rotations_as("matrix"), self.motion.root_positions)


def test_hold_last_seen_keeps_the_last_pose_and_leaves_never_seen_frames_unseen():
    rotations = torch.arange(5.0)[:, None, None, None].expand(5, 3, 3, 3).clone()
    positions = torch.arange(5.0)[:, None, None].expand(5, 3, 3).clone()
    visible = torch.tensor([[False, True], [True, True], [False, True], [False, False], [True, False]])
    r, p, held = evaluation.hold_last_seen(rotations, positions, visible)
    assert held[:, 0].tolist() == [False, True, True, True, True]
    assert held[:, 1].all()
    assert p[2:4, 1].eq(1.0).all() and p[4, 1].eq(4.0).all()   # left hand: frames 2-3 hold frame 1
    assert p[3:, 2].eq(2.0).all() and r[4, 2].eq(2.0).all()    # right hand: frames 3-4 hold frame 2
    assert p[:, 0].tolist() == positions[:, 0].tolist()        # the head is untouched


def test_a_perfect_model_scores_zero_and_a_shifted_one_its_shift(mocap):
    truth = to_canonical(load_motion(mocap / "cmu_fairmotion" / "01_01.bvh"))[:90].resample(30.0)
    for scenario in ("MC", "HT"):
        scores = evaluation.evaluate_clip(Oracle(truth), truth, scenario, seed=0, solve=False)   # the network's output
        assert scores["MPJPE"] < 1e-3 and scores["MPJRE"] < 0.1 and scores["hand"] < 1e-3
    # Not anchored to the head, a root 5 cm off shows as 5 cm on every joint.
    shifted = truth.__class__(truth.skeleton, truth.rotations, truth.root_positions + torch.tensor([0.05, 0, 0]), truth.fps)
    scores = evaluation.evaluate_clip(Oracle(shifted), truth, "MC", seed=0, anchor=False, solve=False)
    assert scores["MPJPE"] == pytest.approx(5.0, abs=1e-3) and scores["MPJRE"] < 0.1
    # Anchored, the headset puts it back.
    assert evaluation.evaluate_clip(Oracle(shifted), truth, "MC", seed=0, solve=False)["MPJPE"] < 1e-3


def test_eval_sparse_command_json_on_a_held_out_subject(mocap):
    take = mocap / "cmu_cyun9601" / "amc" / "03" / "03_01.amc.gz"   # subject 03 is in the test split
    result = CliRunner().invoke(main, ["eval", "sparse", str(take), "--json", "--max-seconds", "4", "--baselines"])
    assert result.exit_code == 0, result.output
    rows = json.loads(result.output)
    assert [(r["scenario"], r["model"]) for r in rows] == [
        ("MC", "network"), ("MC", "network alone (no solve)"), ("MC", "own trajectory"), ("HT", "network"),
        ("HT", "network alone (no solve)"), ("HT", "hold last hand"), ("HT", "own trajectory"), ("-", "truth")]
    network = rows[0]
    frames = min(120, to_canonical(load_motion(take)).resample(30.0).num_frames)
    assert set(evaluation.METRICS) <= set(network) and network["frames"] == frames
    assert 2.0 < network["MPJPE"] < 25.0 and network["hand"] < network["lower"]
    assert network["unseen"] is None                                  # controllers: hands always seen
    assert rows[3]["unseen"] > rows[3]["hand"] * 0.5 and rows[5]["unseen"] is not None
    assert network["target"] < 1.0 < rows[1]["target"]               # the solve puts the wrists on the controllers
    assert network["reach"] < 0.01 and network["beyond"] < 5.0       # exactly, wherever the arm can reach
    assert rows[-1]["MPJPE"] is None and rows[-1]["pen"] is not None   # the truth's own foot figures


def test_eval_sparse_names_a_file_it_cannot_read(tmp_path):
    bad = tmp_path / "broken.bvh"
    bad.write_text("HIERARCHY\nROOT Hips\n{\n")
    result = CliRunner().invoke(main, ["eval", "sparse", str(bad)])
    assert result.exit_code != 0 and "broken.bvh" in result.output


def test_progress_is_a_flag_with_bars_on_stderr(capsys):
    """evaluate_models shows tqdm bars on stderr, per data set, advanced per clip and row; with
    progress=False it writes nothing at all."""
    from humotion.assets import demo_clip_path

    truth = to_canonical(load_motion(demo_clip_path()))[:40]
    sets = {"demo": [truth, truth]}
    rows = evaluation.evaluate_models({"oracle": Oracle(truth)}, sets, ("MC",), None, baselines=False, progress=False)
    assert capsys.readouterr() == ("", "")
    assert evaluation.evaluate_models({"oracle": Oracle(truth)}, sets, ("MC",), None, baselines=False) == rows
    shown = capsys.readouterr()
    assert shown.out == "" and "demo: MC oracle" in shown.err and "clip" in shown.err

"""Training SparsePoser: batches from real mocap, a tiny run that learns, checkpoints and resume."""

import json
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

from humotion.sparse.batches import AugmentedWindows, load_windows, make_batch
from humotion.sparse.model import SparseConfig, SparsePoser, load_sparse_model, save_sparse_model
from humotion.sparse.command import train_sparse_command
from humotion.sparse.train import TrainConfig, checkpoints, train, validate
from humotion.training import learning_rate

SMALL = SparseConfig(embed=8, hidden=32, layers=1, heads=2, feedforward=64, decoder=64)


@pytest.fixture
def config(mocap, tmp_path) -> TrainConfig:
    """Three clips of one CMU subject, every clip for training (one subject: no split)."""
    return TrainConfig(data_root=str(mocap / "cmu_mocgui_s02"), train_split=None, val_split=None, max_clips=3,
                       length=20, stride=20, batch_size=8, model=SMALL, out_dir=str(tmp_path / "run"),
                       cache_dir=str(tmp_path / "cache"), checkpoint_every=10, log_every=2, progress=False,
                       threads=1)


def test_batches_hold_signals_and_targets(config):
    windows = load_windows(config, None, config.stride)
    assert windows.num_joints == 22 and len(windows) > 8
    item = AugmentedWindows(windows)[0]
    assert item["rotations"].shape == (20, 22, 4) and item["eye"].shape == (3,)
    batch = torch.utils.data.default_collate([AugmentedWindows(windows)[i] for i in range(4)])
    inputs, target = make_batch(batch, scenario_ht=True, frustum=config.frustum, fps=config.fps)
    assert inputs["head"].shape == (4, 20, 9) and inputs["visible"].shape == (4, 20, 2)
    assert target["world_positions"].shape == (4, 20, 22, 3) and target["hands"].shape == (4, 20, 2, 9)
    # The true hand signals are the wrists' world poses, whether seen or not.
    torch.testing.assert_close(target["hands"][..., 0, 6:], target["world_positions"][..., 20, :])
    mc, _ = make_batch(batch, scenario_ht=False)
    assert bool((mc["visible"] == 1).all())
    # Augmented items differ from draw to draw; plain ones do not.
    a, b = AugmentedWindows(windows)[0], AugmentedWindows(windows)[0]
    assert not torch.equal(a["root_positions"], b["root_positions"])
    plain = AugmentedWindows(windows, augment=False)
    assert torch.equal(plain[0]["root_positions"], plain[0]["root_positions"])


def test_speed_augmentation_plays_windows_faster_and_slower(config):
    windows = load_windows(config, None, config.stride)
    data = AugmentedWindows(windows, speed_range=(0.8, 1.25))
    clip, start = windows.index[1]
    source = windows.motions[clip]
    # Twice as fast: frame k is the clip's frame start + 2k (moved back to fit in the clip).
    fast = data.at_speed(1, 2.0)
    assert fast.num_frames == windows.length and fast.fps == windows.fps
    first = min(start, source.num_frames - 1 - 2 * (windows.length - 1))
    torch.testing.assert_close(fast.root_positions, source.root_positions[first:first + 2 * windows.length:2])
    torch.testing.assert_close(fast.world_positions(), source[first:first + 2 * windows.length:2].world_positions())
    # Half as fast: every other frame is the clip's, the ones between are halfway.
    slow = data.at_speed(1, 0.5)
    torch.testing.assert_close(slow.root_positions[::2], source.root_positions[start:start + windows.length // 2])
    torch.testing.assert_close(slow.root_positions[1:-1:2], (source.root_positions[start:start + windows.length // 2 - 1]
                                                             + source.root_positions[start + 1:start + windows.length // 2]) / 2)
    assert torch.equal(data.at_speed(1, 1.0).rotations, windows.window(1).rotations)
    # Drawn per item within the range: with no body scale, the root's path length changes with the speed only.
    unscaled = AugmentedWindows(windows, scale_range=(1.0, 1.0), speed_range=(0.8, 1.25))
    torch.manual_seed(0)
    lengths = {round(float(unscaled[1]["root_positions"].diff(dim=0).norm(dim=-1).sum()) * 1000) for _ in range(8)}
    assert len(lengths) > 1
    plain = AugmentedWindows(windows, scale_range=(1.0, 1.0))
    assert len({round(float(plain[1]["root_positions"].diff(dim=0).norm(dim=-1).sum()) * 1000) for _ in range(8)}) == 1
    with pytest.raises(ValueError, match="speed_range"):
        AugmentedWindows(windows, speed_range=(1.2, 0.8))


def test_tiny_training_learns_checkpoints_and_resumes(config):
    summary = train(TrainConfig(**{**config.__dict__, "steps": 30}))
    assert summary["step"] == 30 and summary["start_step"] == 0
    out_path = Path(config.out_dir)
    assert [p.name for p in checkpoints(out_path)] == ["checkpoint-10.pt", "checkpoint-20.pt", "checkpoint-30.pt"]
    log = [json.loads(line) for line in open(out_path / "log.jsonl")]
    assert [r["step"] for r in log[:3]] == [2, 4, 6]
    assert {r["lr"] for r in log if "lr" in r} == {config.lr}      # constant unless lr_final is given

    # The trained model fits these windows better than an untrained one.
    windows = AugmentedWindows(load_windows(config, None, config.stride), augment=False)
    torch.manual_seed(123)
    before = validate(SparsePoser(SMALL), windows, config, torch.device("cpu"))["loss"]
    after = validate(load_sparse_model(out_path / "sparse_poser.pt"), windows, config, torch.device("cpu"))["loss"]
    assert after < 0.8 * before, (before, after)

    # Resume: a longer run continues from the newest checkpoint's step.
    resumed = train(TrainConfig(**{**config.__dict__, "steps": 34}))
    assert resumed["start_step"] == 30 and resumed["step"] == 34
    log = [json.loads(line) for line in open(out_path / "log.jsonl")]
    assert [r["step"] for r in log[-2:]] == [32, 34]
    state = torch.load(checkpoints(out_path)[-1], weights_only=True)
    assert state["step"] == 34 and state["config"]["steps"] == 34


def test_training_starts_from_given_weights(config, tmp_path):
    torch.manual_seed(7)
    start = SparsePoser(SMALL)
    save_sparse_model(start, tmp_path / "start.pt", fps=30.0)
    train(TrainConfig(**{**config.__dict__, "steps": 1, "lr": 1e-12, "init_weights": str(tmp_path / "start.pt")}))
    trained = load_sparse_model(Path(config.out_dir) / "sparse_poser.pt")
    for name, value in start.state_dict().items():
        torch.testing.assert_close(trained.state_dict()[name], value, atol=1e-8, rtol=0)
    other = SparseConfig(**{**SMALL.__dict__, "hidden": 16})
    with pytest.raises(ValueError, match="different network: hidden 32 \\(this run: 16\\)"):
        train(TrainConfig(**{**config.__dict__, "model": other, "out_dir": str(tmp_path / "other"),
                             "init_weights": str(tmp_path / "start.pt")}))


def test_command_line(config, tmp_path):
    runner = CliRunner()
    result = runner.invoke(train_sparse_command, ["--help"])
    assert result.exit_code == 0 and "--ablate-loss" in result.output and "--mask-token" in result.output
    args = ["--data", config.data_root, "--out", str(tmp_path / "cli"), "--steps", "2", "--batch-size", "4",
            "--length", "10", "--max-clips", "1", "--hidden", "16", "--embed", "4", "--mask-token", "fixed",
            "--ablate-loss", "smooth", "--ablate-loss", "aux", "--threads", "1", "--lr-final", "1e-5",
            "--speed", "0.8", "1.25", "--position-weight", "10"]
    result = runner.invoke(train_sparse_command, args, catch_exceptions=False)
    assert result.exit_code == 0, result.output
    state = torch.load(checkpoints(tmp_path / "cli")[-1], weights_only=True)
    weights = state["config"]["weights"]
    assert weights["smooth"] == weights["aux"] == weights["forecast"] == 0.0 and weights["se3"] == 1.0
    assert state["model"]["config"]["mask_token"] == "fixed"
    assert state["config"]["lr_final"] == 1e-5
    assert tuple(state["config"]["speed_range"]) == (0.8, 1.25) and state["config"]["position_weight"] == 10.0


def test_learning_rate_warms_up_then_follows_a_cosine_to_its_final_value():
    rates = [learning_rate(step, 100, 1e-3, 1e-5, warmup=10) for step in range(101)]
    assert rates[0] == pytest.approx(1e-4) and rates[9] == pytest.approx(1e-3)      # linear warm-up
    assert rates[10] == pytest.approx(1e-3) and rates[100] == pytest.approx(1e-5)
    assert rates[55] == pytest.approx((1e-3 + 1e-5) / 2)                              # half-way down
    assert rates[10:] == sorted(rates[10:], reverse=True)

"""The training windows cache holds data only: a planted pickle never runs, and a rebuilt entry
gives the same windows as the first build."""

import pickle
from pathlib import Path

import numpy as np
import torch

from humotion.canonical import canonical_skeleton
from humotion.data import MotionCollection
from humotion.data.cache import read_motions, write_motions
from humotion.motion import Motion
from humotion.training import RunConfig, load_windows


class Planted:
    """Unpickling this writes a file: what a hostile cache entry could do."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return Path.write_text, (self.marker, "pickle ran")


def config(mocap, tmp_path) -> RunConfig:
    settings = RunConfig(data_root=str(mocap / "cmu_mocgui_s02"), train_split=None, val_split=None, max_clips=1,
                         cache_dir=str(tmp_path / "cache"), progress=False)
    settings.length = 20          # a model's training config adds the window length
    return settings


def test_windows_cache_is_data_only(mocap, tmp_path, monkeypatch):
    settings = config(mocap, tmp_path)
    first = load_windows(settings, None, stride=20)
    [entry] = (tmp_path / "cache").iterdir()
    assert entry.suffix == ".npz"
    with np.load(entry, allow_pickle=False) as data:          # readable without pickle
        assert set(data.files) == {"meta", "rotations", "root_positions", "joint_offsets"}

    def no_building(*args, **kwargs):
        raise AssertionError("the windows were built again instead of read from the cache")

    monkeypatch.setattr(MotionCollection, "windows", no_building)
    again = load_windows(settings, None, stride=20)
    assert again.index == first.index and repr(again) == repr(first)
    assert torch.equal(again[3]["rotations"], first[3]["rotations"]) and torch.equal(again[3]["offsets"], first[3]["offsets"])

    # An old-style pickle at the entry's name is never opened: the windows are built again.
    monkeypatch.undo()
    marker = tmp_path / "marker.txt"
    entry.with_suffix(".pkl").write_bytes(pickle.dumps(Planted(marker)))
    entry.unlink()
    assert load_windows(settings, None, stride=20).index == first.index
    assert not marker.exists()


def test_motions_round_trip_through_one_file(tmp_path):
    generator = torch.Generator().manual_seed(0)
    small, tall = canonical_skeleton(1.6), canonical_skeleton(1.9)
    motions = [Motion(small, torch.randn(5, 22, 4, generator=generator), torch.randn(5, 3, generator=generator), 30.0,
                      name="a"),
               Motion(tall, torch.randn(2, 22, 4, generator=generator), torch.randn(2, 3, generator=generator), 30.0,
                      joint_offsets=torch.randn(2, 22, 3, generator=generator), name="b"),
               Motion(small, torch.randn(3, 22, 4, generator=generator), torch.randn(3, 3, generator=generator), 60.0)]
    write_motions(tmp_path / "m.npz", motions)
    back = read_motions(tmp_path / "m.npz")
    for a, b in zip(motions, back, strict=True):
        assert (a.name, a.fps, a.skeleton.names) == (b.name, b.fps, b.skeleton.names)
        assert torch.equal(a.skeleton.offsets, b.skeleton.offsets)
        assert torch.equal(a.rotations, b.rotations) and torch.equal(a.root_positions, b.root_positions)
        assert (a.joint_offsets is None) == (b.joint_offsets is None)
    assert torch.equal(back[1].joint_offsets, motions[1].joint_offsets)
    write_motions(tmp_path / "none.npz", [])
    assert read_motions(tmp_path / "none.npz") == []
    (tmp_path / "m.npz").write_bytes((tmp_path / "m.npz").read_bytes()[:300])   # damaged: rebuilt by the caller
    assert read_motions(tmp_path / "m.npz") is None and read_motions(tmp_path / "missing.npz") is None

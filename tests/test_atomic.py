"""Files are written whole or not at all (humotion.atomic.atomic_file): a writer that fails leaves
the previous file as it was and no temporary file behind, and every writer of the package shares
that one implementation."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
import pytest
import torch

from humotion.atomic import atomic_file
from humotion.body.files import save_json, save_npz
from humotion.io.paths import write_atomic
from humotion.model_files import save_model_file


def test_a_finished_block_replaces_the_file_and_keeps_its_permissions(tmp_path):
    path = tmp_path / "a.bin"
    path.write_bytes(b"old")
    path.chmod(0o600)
    with atomic_file(path) as file:
        file.write(b"new")
        assert Path(file.name).parent == tmp_path     # a named file beside path (onnx.save reads its name)
    assert path.read_bytes() == b"new" and path.stat().st_mode & 0o777 == 0o600
    with atomic_file(tmp_path / "b.bin") as file:
        file.write(b"b")
    assert (tmp_path / "b.bin").stat().st_mode & 0o777 == 0o644
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.bin", "b.bin"]


@pytest.mark.parametrize("error", [ValueError("the writer failed"), KeyboardInterrupt()])
def test_a_failing_writer_leaves_the_old_file_and_no_temporary(tmp_path, error):
    path = tmp_path / "a.bin"
    path.write_bytes(b"old")
    with pytest.raises(type(error)):
        with atomic_file(path) as file:
            file.write(b"half of the new")
            raise error
    assert path.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["a.bin"]


@dataclasses.dataclass
class TinyConfig:
    width: int = 2


class Tiny(torch.nn.Module):
    def __init__(self, config: TinyConfig = TinyConfig()):
        super().__init__()
        self.config = config
        self.linear = torch.nn.Linear(config.width, 1)


WRITERS = {
    "write_atomic": lambda path: write_atomic(path, [b"new ", b"bytes"]),
    "body save_npz": lambda path: save_npz(path, {"x": np.arange(3)}),
    "body save_json": lambda path: save_json(path, {"x": 1}),
    "save_model_file": lambda path: save_model_file(Tiny(), path),
}


@pytest.mark.parametrize("name", WRITERS)
def test_the_writers_keep_the_old_file_when_the_rename_fails(tmp_path, monkeypatch, name):
    path = tmp_path / "out"
    path.write_bytes(b"old")

    def full_disk(*args):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", full_disk)
    with pytest.raises(OSError):
        WRITERS[name](path)
    assert path.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["out"]
    monkeypatch.undo()
    WRITERS[name](path)
    assert path.read_bytes() != b"old" and [p.name for p in tmp_path.iterdir()] == ["out"]

"""BVH at its limits: deep skeletons, absurd values, takes read a block of rows at a time, the
outline `humotion info` reads, and the fast paths against their references."""

from __future__ import annotations

import gzip
import io
import itertools
import json
import tracemalloc

import numpy as np
import pytest
import torch
from click.testing import CliRunner

import humotion.io.bvh as bvh
from humotion import rotations as rot
from humotion.cli import main
from humotion.io.bvh import MAX_ANGLE, MAX_LENGTH, read_bvh, read_bvh_outline, write_bvh
from humotion.io.errors import MotionFileError
from humotion.motion import Motion
from humotion.skeleton import Skeleton
from test_bvh import SMALL, line_of, write
from textedit import replace_line

ROW1 = line_of(SMALL, "Frame Time:") + 1  # "1 2 3 0 0 0 ...": Hips X/Y/Zposition, Z/Y/Xrotation, Spine ...


def chain(joints: int) -> Skeleton:
    """A single chain of joints, 1 cm apart along +Y, with an end site."""
    return Skeleton([f"j{i}" for i in range(joints)], [-1] + list(range(joints - 1)),
                    np.tile([0.0, 0.01, 0.0], (joints, 1)), [joints - 1], [[0.0, 0.01, 0.0]])


def rows(frames: int, seed: int = 0) -> str:
    """SMALL with `frames` random rows (angles within ±180 degrees, positions within ±100)."""
    values = np.random.default_rng(seed).uniform(-180, 180, (frames, 15)).round(4)
    values[:, :3] /= 1.8
    head = SMALL.split("Frames: 3")[0]
    body = "\n".join(" ".join(f"{x:g}" for x in row) for row in values)
    return f"{head}Frames: {frames}\nFrame Time: 0.0333333\n{body}\n"


# -- item 6: deep skeletons -----------------------------------------------------------------
def test_a_chain_10000_joints_deep_is_written_and_read_back(tmp_path):
    skeleton = chain(10_000)
    motion = Motion(skeleton, rot.quat_identity(2, 10_000), torch.zeros(2, 3), 30.0)
    write_bvh(motion, tmp_path / "deep.bvh")
    back = read_bvh(tmp_path / "deep.bvh", units="m")
    assert back.skeleton.parents == skeleton.parents and back.skeleton.names == skeleton.names
    assert int(back.skeleton.depth()[-1]) == 9_999
    np.testing.assert_allclose(back.skeleton.rest_end_site_positions(), [[0.0, 100.0, 0.0]], atol=1e-6)


def test_indentation_stops_at_max_indent(tmp_path):
    motion = Motion(chain(50), rot.quat_identity(1, 50), torch.zeros(1, 3), 30.0)
    write_bvh(motion, tmp_path / "deep.bvh")
    lines = (tmp_path / "deep.bvh").read_text().split("\n")
    assert max(len(line) - len(line.lstrip("\t")) for line in lines) == bvh._MAX_INDENT + 2  # an end site's OFFSET


# -- item 7: absurd values name the file and the line ---------------------------------------
def _row1(*values: str) -> str:
    """SMALL with the first motion row's first values replaced."""
    tokens = SMALL.split("\n")[ROW1 - 1].split()
    return replace_line(SMALL, ROW1, " ".join(list(values) + tokens[len(values):]))


ABSURD = {
    "1e308 degrees": (_row1("1", "2", "3", "1e308"), ROW1, "motion value 1e+308 is beyond ±1e+06 degrees "
                      "(frame 0, joint 'Hips', channel Zrotation)"),
    "1e30 degrees": (_row1("1", "2", "3", "0", "-1e30"), ROW1, "motion value -1e+30 is beyond ±1e+06 degrees "
                     "(frame 0, joint 'Hips', channel Yrotation)"),
    "2e6 degrees on a later row": (SMALL.replace("-40 0 20", "-40 0 2e6"), ROW1 + 1, "(frame 1, joint 'Head', "
                                   "channel Zrotation)"),
    "1e308 position": (_row1("1e308"), ROW1, "motion value 1e+308 is beyond ±1e+09 file units "
                       "(frame 0, joint 'Hips', channel Xposition)"),
    "1e12 position": (_row1("1", "-1e12"), ROW1, "beyond ±1e+09 file units (frame 0, joint 'Hips', channel Yposition)"),
    "1e400 is infinity": (_row1("1", "2", "3", "1e400"), ROW1, "NaN or infinity (frame 0, joint 'Hips', channel Zrotation)"),
    "Frames: 1e20": (SMALL.replace("Frames: 3", "Frames: 100000000000000000000"), line_of(SMALL, "Frames:"),
                     "more rows than any file holds"),
    "OFFSET 1e308": (SMALL.replace("OFFSET 10 0 0", "OFFSET 10 1e308 0"), line_of(SMALL, "OFFSET 10 0 0"),
                     "OFFSET: '1e308' is beyond ±1e+09"),
}


@pytest.mark.parametrize("case", ABSURD)
def test_absurd_values_name_file_line_frame_and_channel(tmp_path, case):
    text, line, problem = ABSURD[case]
    path = write(tmp_path, text, "bad.bvh")
    with pytest.raises(MotionFileError) as raised:
        read_bvh(path)
    assert raised.value.line == line and problem in raised.value.problem, str(raised.value)
    assert str(raised.value).startswith(f"{path}, line {line}: ")


def test_values_at_the_limits_are_read(tmp_path):
    motion = read_bvh(write(tmp_path, _row1(f"{MAX_LENGTH:g}", "0", "0", f"{-MAX_ANGLE:g}")), units="m")
    assert float(motion.root_positions[0, 0]) == pytest.approx(MAX_LENGTH)
    angle = rot.quat_to_euler("ZYX", motion.rotations[0, 0].double(), degrees=True)
    assert float(angle[0]) == pytest.approx(-MAX_ANGLE % 360, abs=1e-3)


# -- item 8: rows read a block at a time ------------------------------------------------------
def test_reading_in_small_blocks_gives_the_same_motion(tmp_path, monkeypatch):
    text = rows(150).replace("\n", "\n\n", 3)  # blank lines too
    whole = read_bvh(write(tmp_path, text))
    monkeypatch.setattr(bvh, "_BLOCK_CHARS", 300)
    for name, data in (("a.bvh", text.encode()), ("a.bvh.gz", gzip.compress(text.encode()))):
        blocks = read_bvh(write(tmp_path, data, name))
        torch.testing.assert_close(blocks.rotations, whole.rotations, atol=0, rtol=0)
        torch.testing.assert_close(blocks.root_positions, whole.root_positions, atol=0, rtol=0)


def test_errors_in_later_blocks_name_their_lines(tmp_path, monkeypatch):
    monkeypatch.setattr(bvh, "_BLOCK_CHARS", 100)
    text = rows(50)
    last = len(text.rstrip("\n").split("\n"))
    cases = [(replace_line(text, last - 5, "1 2 3"), last - 5, "motion row has 3 values"),
             (replace_line(text, last - 3, "1 2 3 0 0 0 0 0 0 0 0 0 0 0 x"), last - 3, "'x' is not a number"),
             (text.replace("Frames: 50", "Frames: 45"), last - 4, "more motion rows than 'Frames: 45'"),
             (text.replace("Frames: 50", "Frames: 1000000000000"), last, "file ends after 50 of 1000000000000 frames")]
    for text, line, problem in cases:
        with pytest.raises(MotionFileError) as raised:
            read_bvh(write(tmp_path, text))
        assert raised.value.line == line and problem in raised.value.problem, str(raised.value)


def test_reading_holds_the_motion_and_a_block_not_the_text(tmp_path, monkeypatch):
    """numpy's allocations while reading 1.5 MB of rows in 64 kB blocks: under twice the file's
    size (the motion's arrays are 0.6 times it here; whole-file readers hold 20-60 times), and
    the outline's under a quarter of it."""
    monkeypatch.setattr(bvh, "_BLOCK_CHARS", 1 << 16)
    path = write(tmp_path, rows(12_000))
    size = path.stat().st_size
    tracemalloc.start()
    try:
        motion = read_bvh(path)
        read_peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.reset_peak()
        held = tracemalloc.get_traced_memory()[0]
        outline = read_bvh_outline(path)
        outline_peak = tracemalloc.get_traced_memory()[1] - held
    finally:
        tracemalloc.stop()
    assert motion.num_frames == outline.num_frames == 12_000
    assert read_peak < 2 * size, (read_peak, size)
    assert outline_peak < size / 4, (outline_peak, size)


def test_writing_holds_the_motion_not_the_text(tmp_path):
    """numpy's and Python's allocations while writing 1.8 MB: under 2.5 times the file's size
    (the Euler angles and rows as float64 are 1.5 times it; the whole text and its rows as Python
    floats took 5.6 times)."""
    motion = read_bvh(write(tmp_path, rows(10_000)))
    tracemalloc.start()
    try:
        write_bvh(motion, tmp_path / "out.bvh")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    size = (tmp_path / "out.bvh").stat().st_size
    assert peak < 2.5 * size, (peak, size)
    torch.testing.assert_close(read_bvh(tmp_path / "out.bvh").world_positions(), motion.world_positions(), atol=1e-5, rtol=0)


def test_outline_converts_only_the_rows_units_auto_looks_at(tmp_path, monkeypatch):
    path = write(tmp_path, rows(1000))
    converted = []
    pose = bvh._Layout.pose
    monkeypatch.setattr(bvh._Layout, "pose", lambda self, values: converted.append(len(values)) or pose(self, values))
    outline = read_bvh_outline(path)
    assert converted == [64]  # the sampled rows, once, for the figure's size
    motion = read_bvh(path)
    assert outline.num_frames == motion.num_frames and outline.fps == motion.fps and outline.name == motion.name
    assert outline.skeleton.names == motion.skeleton.names
    assert torch.equal(outline.skeleton.offsets, motion.skeleton.offsets)
    assert outline.animated_joint_offsets is False and outline.duration == motion.duration


def test_info_reads_a_bvh_outline_only(tmp_path, monkeypatch):
    path = write(tmp_path, rows(100))
    monkeypatch.setattr(bvh, "read_bvh", lambda *args, **kwargs: pytest.fail("info read every frame"))
    result = CliRunner().invoke(main, ["info", str(path), "--json"])
    assert result.exit_code == 0, result.output
    facts = json.loads(result.output)
    assert facts["frames"] == 100 and facts["joints"] == 5 and facts["animated_joint_offsets"] is False
    broken = write(tmp_path, rows(100).replace("Frames: 100", "Frames: 101"), "broken.bvh")
    result = CliRunner().invoke(main, ["info", str(broken)])
    assert result.exit_code == 1 and "file ends after 100 of 101 frames" in result.output


# -- fast paths against their references ------------------------------------------------------
def test_euler_to_quat_matches_the_rotations_module():
    angles = np.random.default_rng(1).uniform(-720, 720, (40, 3, 3))
    for n in (1, 2, 3):
        for order in map("".join, itertools.permutations("XYZ", n)):
            expected = rot.euler_to_quat(order, torch.from_numpy(angles[..., :n]), degrees=True).numpy()
            np.testing.assert_allclose(bvh._euler_to_quat(order, angles[..., :n]), expected, atol=1e-15, rtol=0)


def test_block_values_match_the_value_by_value_reference():
    text = rows(200, seed=2)
    lines = [line.replace(" ", "\t ", r % 4) + " " * (r % 3) for r, line in
             enumerate(text.split("Frame Time: 0.0333333\n")[1].split("\n")) if line]
    lines[7] = " +15e-1 " + lines[7].split(maxsplit=1)[1]
    reader = bvh._Reader("x.bvh")
    layout = bvh._Layout.of(reader.header(bvh._Lines(reader, io.StringIO(text))).joints)
    fast = reader.values(lines, list(range(len(lines))), np.arange(len(lines)), layout)
    np.testing.assert_array_equal(fast, reader.values_one_by_one(lines, list(range(len(lines))), layout.count))

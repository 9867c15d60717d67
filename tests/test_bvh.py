"""BVH reading and writing: real files, known answers, malformed input, fuzzing."""

from __future__ import annotations

import functools
import gzip
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from humotion import rotations as rot
from humotion.io.bvh import UNITS, read_bvh, write_bvh
from humotion.io.errors import MotionFileError
from humotion.motion import Motion
from humotion.skeleton import Skeleton
from textedit import replace_line

DATA = Path(__file__).parents[1] / ".." / "shared" / "data"
MOCAP = DATA / "mocap"
CMU_BVH = MOCAP / "cmu_fairmotion" / "01_01.bvh"
ICLONE_BVH = MOCAP / "cmu_iclone_ccskeleton" / "001_01.bvh.gz"
SALSA_BVH = MOCAP / "cmu_salsa_beemsoft" / "60_01_scaled.bvh.gz"


def data_file(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"data not available: {path}")
    return path


@functools.lru_cache(maxsize=None)
def read_real(path: Path) -> Motion:
    """Each real file is read once per test session (tests only look at it)."""
    return read_bvh(data_file(path))


def figure_size(motion: Motion, frame: int = 0) -> float:
    """Largest extent over the axes of joints and end sites at one frame, metres."""
    pose = motion[frame]
    points = torch.cat([pose.world_positions()[0], pose.end_site_positions()[0]])
    return float((points.max(0).values - points.min(0).values).max())


# A small figure in centimetres, 1.8 m tall; line numbers matter to the error tests below.
SMALL = """\
HIERARCHY
ROOT Hips
{
  OFFSET 0 100 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
  JOINT Spine
  {
    OFFSET 0 10 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    JOINT Head
    {
      OFFSET 0 50 0
      CHANNELS 3 Xrotation Yrotation Zrotation
      End Site
      {
        OFFSET 0 20 0
      }
    }
  }
  JOINT LeftUpLeg
  {
    OFFSET 10 0 0
    CHANNELS 3 Zrotation Yrotation Xrotation
    JOINT LeftLeg
    {
      OFFSET 0 -50 0
      CHANNELS 0
      End Site
      {
        OFFSET 0 -50 0
      }
    }
  }
}
MOTION
Frames: 3
Frame Time: 0.0333333
1 2 3 0 0 0 0 0 0 0 0 0 0 0 0
1.5 2 3 10 20 30 5 -5 15 -40 0 20 0 0 45
2 2.5 3.5 -10 0 5 0 90 0 90 90 0 30 -20 10
"""


def write(tmp_path: Path, text: str | bytes, name: str = "x.bvh") -> Path:
    path = tmp_path / name
    path.write_bytes(text.encode() if isinstance(text, str) else text)
    return path


def line_of(text: str, fragment: str) -> int:
    """1-based number of the first line containing fragment."""
    return next(i + 1 for i, line in enumerate(text.split("\n")) if fragment in line)


# -- real files ---------------------------------------------------------------------------
def test_cmu_bvh():
    motion = read_real(CMU_BVH)
    assert motion.skeleton.num_joints == 31
    assert motion.num_frames == 2752
    assert motion.fps == 120.0
    assert motion.joint_offsets is None
    assert motion.name == "01_01"
    assert len(motion.skeleton.end_site_names) == 7 and "Head_end" in motion.skeleton.end_site_names
    assert 1.4 <= figure_size(motion) <= 1.9
    # units="auto" picked CMU units (1/0.45 inch): first row's root channels 9.3722 17.8693 -17.3198.
    np.testing.assert_allclose(motion.root_positions[0].numpy(), np.array([9.3722, 17.8693, -17.3198]) * UNITS["cmu"], rtol=1e-6)
    # Frame 0 is the T-pose the converter added: hands level with the shoulders, arms out.
    p = motion.world_positions()[0]
    s = motion.skeleton
    for side in ("Left", "Right"):
        arm, hand = p[s.index(f"{side}Arm")], p[s.index(f"{side}Hand")]
        assert abs(float(hand[1] - arm[1])) < 0.06
        assert abs(float(hand[0] - arm[0])) > 0.4
    assert float(p[s.index("LeftHand"), 0] - p[s.index("RightHand"), 0]) > 1.2  # +X is the left


def test_iclone_gzip_centimetres():
    motion = read_real(ICLONE_BVH)
    assert motion.skeleton.num_joints == 100
    assert motion.fps == 60.0
    assert 1.5 <= figure_size(motion) <= 1.9
    # Centimetres; world root = OFFSET (0, 105.214226, 0.000021) + first row's channels.
    expected = (np.array([0.0, 105.214226, 0.000021]) + [0.056791, 7.151138, 0.213898]) * 0.01
    np.testing.assert_allclose(motion.root_positions[0].numpy(), expected, rtol=1e-6)
    np.testing.assert_allclose(motion.skeleton.offsets[0], [0.0, 1.05214226, 0.00000021])


def test_salsa_metres():
    motion = read_real(SALSA_BVH)
    assert motion.skeleton.num_joints == 43
    assert motion.fps == 120.0
    np.testing.assert_allclose(motion.root_positions[0].numpy(), [-0.537652, 0.658012, -0.017330], rtol=1e-6)
    # The repository's "scaled" files hold a small figure (about 1.2 m) in metres.
    assert 1.0 <= figure_size(motion) <= 1.4


# -- conventions --------------------------------------------------------------------------
def test_small_known_answers(tmp_path):
    motion = read_bvh(write(tmp_path, SMALL), units="cm")
    s = motion.skeleton
    assert s.names == ("Hips", "Spine", "Head", "LeftUpLeg", "LeftLeg")
    assert s.parents == (-1, 0, 1, 0, 3)
    assert s.end_site_names == ("Head_end", "LeftLeg_end")
    assert motion.fps == 30.0 and motion.num_frames == 3 and motion.joint_offsets is None
    # Root world position = root OFFSET + position channels.
    np.testing.assert_allclose(motion.root_positions[0].numpy(), [0.01, 1.02, 0.03], atol=1e-6)
    # Frame 0 is the rest pose; the channel-less LeftLeg always has the identity.
    np.testing.assert_allclose(motion.world_positions()[0].numpy(), s.rest_positions().numpy() + [0.01, 0.02, 0.03], atol=1e-6)
    torch.testing.assert_close(motion.rotations[:, 4], rot.quat_identity(3))
    # Units: auto picks centimetres for this 1.8 m figure; a float is metres per unit.
    assert s.height() == pytest.approx(1.8)
    torch.testing.assert_close(read_bvh(tmp_path / "x.bvh").root_positions, motion.root_positions)
    assert read_bvh(tmp_path / "x.bvh", units=0.5).skeleton.height() == pytest.approx(90.0)
    with pytest.raises(ValueError):
        read_bvh(tmp_path / "x.bvh", units="furlong")


def _axis_matrix(axis: str, degrees: float) -> np.ndarray:
    """Independent check: the textbook rotation matrix about one axis."""
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    return {"X": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
            "Y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
            "Z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])}[axis]


def test_frame_2_known_positions(tmp_path):
    """Frame 2 of SMALL by hand: row "2 2.5 3.5 | -10 0 5 | 0 90 0 | 90 90 0 | 30 -20 10".

    Hips ZYX (-10, 0, 5); Spine ZXY (0, 90, 0) = Rx(90); Head XYZ (90, 90, 0) = Rx(90) @ Ry(90);
    LeftUpLeg ZYX (30, -20, 10) = Rz(30) @ Ry(-20) @ Rx(10).
    """
    motion = read_bvh(write(tmp_path, SMALL), units="cm")
    p, e = motion.world_positions()[2].double().numpy(), motion.end_site_positions()[2].double().numpy()
    hips = _axis_matrix("Z", -10) @ _axis_matrix("X", 5)
    np.testing.assert_allclose(p[0], [0.02, 1.025, 0.035], atol=1e-6)  # OFFSET + channels
    np.testing.assert_allclose(p[1], p[0] + hips @ [0, 0.1, 0], atol=1e-6)
    np.testing.assert_allclose(p[2], p[1] + hips @ [0, 0, 0.5], atol=1e-6)  # Rx(90): +Y -> +Z
    # Rx(90) @ Ry(90) takes +Y to +Z, then the spine's Rx(90) takes +Z to -Y.
    np.testing.assert_allclose(e[0], p[2] + hips @ [0, -0.2, 0], atol=1e-6)
    leg = _axis_matrix("Z", 30) @ _axis_matrix("Y", -20) @ _axis_matrix("X", 10)
    np.testing.assert_allclose(p[3], p[0] + hips @ [0.1, 0, 0], atol=1e-6)
    np.testing.assert_allclose(p[4], p[3] + hips @ leg @ [0, -0.5, 0], atol=1e-6)
    np.testing.assert_allclose(e[1], p[4] + hips @ leg @ [0, -0.5, 0], atol=1e-6)


def test_rotation_orders_same_rotation(tmp_path):
    """Rx(90) @ Ry(90) written as "X Y Z: 90 90 0" equals Rz(90) @ Rx(90) written as "Z Y X: 90 0 90".

    Both map x->y, y->z, z->x, so a child at +10 cm Z lands at +10 cm X.
    """
    template = ("HIERARCHY\nROOT A\n{\n OFFSET 0 0 0\n CHANNELS 3 ORDER\n JOINT B\n {\n  OFFSET 0 0 10\n"
                "  End Site\n  {\n   OFFSET 10 0 0\n  }\n }\n}\nMOTION\nFrames: 1\nFrame Time: 0.01\nVALUES\n")
    xyz = template.replace("ORDER", "Xrotation Yrotation Zrotation").replace("VALUES", "90 90 0")
    zyx = template.replace("ORDER", "Zrotation Yrotation Xrotation").replace("VALUES", "90 0 90")
    yxz = template.replace("ORDER", "Yrotation Xrotation Zrotation").replace("VALUES", "90 90 0")
    a = read_bvh(write(tmp_path, xyz, "xyz.bvh"), units="cm")
    b = read_bvh(write(tmp_path, zyx, "zyx.bvh"), units="cm")
    c = read_bvh(write(tmp_path, yxz, "yxz.bvh"), units="cm")
    np.testing.assert_allclose(a.world_positions()[0, 1].numpy(), [0.1, 0, 0], atol=1e-6)
    np.testing.assert_allclose(a.end_site_positions()[0, 0].numpy(), [0.1, 0.1, 0], atol=1e-6)
    torch.testing.assert_close(a.world_positions(), b.world_positions(), atol=1e-6, rtol=0)
    torch.testing.assert_close(a.end_site_positions(), b.end_site_positions(), atol=1e-6, rtol=0)
    # The other order of the same angles, Ry(90) @ Rx(90), takes +Z to -Y.
    np.testing.assert_allclose(c.world_positions()[0, 1].numpy(), [0, -0.1, 0], atol=1e-6)


def test_crlf_tabs_whitespace(tmp_path):
    messy = SMALL.replace("  ", "\t \t").replace(" 0 ", "   0\t").replace("\n", "\r\n")
    a = read_bvh(write(tmp_path, SMALL, "a.bvh"))
    b = read_bvh(write(tmp_path, messy, "b.bvh"))
    assert a.skeleton.names == b.skeleton.names
    torch.testing.assert_close(a.world_positions(), b.world_positions(), atol=0, rtol=0)
    torch.testing.assert_close(a.end_site_positions(), b.end_site_positions(), atol=0, rtol=0)
    gz = read_bvh(write(tmp_path, gzip.compress(messy.encode()), "c.bvh.gz"))
    torch.testing.assert_close(a.rotations, gz.rotations, atol=0, rtol=0)


def test_position_channels_on_non_root_joint(tmp_path):
    text = SMALL.replace("    OFFSET 0 10 0\n    CHANNELS 3 Zrotation Xrotation Yrotation",
                         "    OFFSET 0 10 0\n    CHANNELS 6 Zrotation Xrotation Yrotation Xposition Yposition Zposition")
    rows = ["1 2 3 0 0 0 0 0 0 0 20 0 0 0 0 0 0 0",
            "1 2 3 0 0 0 0 0 0 5 15 -5 0 0 0 0 0 0",
            "1 2 3 0 0 0 90 0 0 0 10 0 0 0 0 0 0 0"]
    text = text.split("Frame Time: 0.0333333\n")[0] + "Frame Time: 0.0333333\n" + "\n".join(rows) + "\n"
    motion = read_bvh(write(tmp_path, text), units="cm")
    assert motion.joint_offsets is not None and motion.joint_offsets.shape == (3, 5, 3)
    # The channels replace the Spine's OFFSET (0, 10, 0); other joints keep theirs.
    np.testing.assert_allclose(motion.joint_offsets[:, 1].numpy(), [[0, 0.2, 0], [0.05, 0.15, -0.05], [0, 0.1, 0]], atol=1e-7)
    np.testing.assert_allclose(motion.joint_offsets[:, 2].numpy(), np.tile([0, 0.5, 0], (3, 1)), atol=1e-7)
    p = motion.world_positions()
    np.testing.assert_allclose(p[0, 1].numpy(), [0.01, 1.22, 0.03], atol=1e-6)
    np.testing.assert_allclose(p[1, 1].numpy(), [0.06, 1.17, -0.02], atol=1e-6)
    # The Spine's Zrotation 90 turns its child: Head offset +Y becomes -X.
    np.testing.assert_allclose(p[2, 2].numpy(), p[2, 1].numpy() + [-0.5, 0, 0], atol=1e-6)
    # Writing keeps the per-frame offsets (6 channels on every joint), in the file's centimetres.
    back = read_bvh(write_and_path(motion, tmp_path / "back.bvh"), units="cm")
    assert back.joint_offsets is not None
    torch.testing.assert_close(back.world_positions(), p, atol=1e-5, rtol=0)


def write_and_path(motion: Motion, path: Path, **kwargs) -> Path:
    write_bvh(motion, path, **kwargs)
    return path


@pytest.mark.parametrize("frame_time, fps", [
    ("0.008333", 120.0), (".0083333", 120.0), ("0.016667", 60.0), ("0.0333333", 30.0), ("0.04", 25.0),
    ("8.333333e-3", 120.0), ("1", 1.0), ("0.033367", 1 / 0.033367), ("0.0125", 80.0), ("0.012", 1 / 0.012),
    ("0.0083", 1 / 0.0083),
])
def test_fps_snapping(tmp_path, frame_time, fps):
    text = SMALL.replace("Frame Time: 0.0333333", f"Frame Time: {frame_time}")
    assert read_bvh(write(tmp_path, text)).fps == pytest.approx(fps, rel=1e-12)


# -- writing ------------------------------------------------------------------------------
@pytest.mark.parametrize("path, frames, suffix", [
    (CMU_BVH, 1000, ".bvh"), (ICLONE_BVH, 300, ".bvh.gz"), (SALSA_BVH, 300, ".bvh"),
])
def test_round_trip_real_files(tmp_path, path, frames, suffix):
    motion = read_real(path)
    if frames:
        motion = motion[:frames]
    out = write_and_path(motion, tmp_path / f"out{suffix}")
    if suffix.endswith(".gz"):
        assert out.read_bytes()[:2] == b"\x1f\x8b"
    back = read_bvh(out)  # auto units: written in metres, found to be metres
    assert back.skeleton.names == motion.skeleton.names
    assert back.fps == motion.fps and back.num_frames == motion.num_frames
    torch.testing.assert_close(back.world_positions(), motion.world_positions(), atol=1e-5, rtol=0)
    torch.testing.assert_close(back.end_site_positions(), motion.end_site_positions(), atol=1e-5, rtol=0)


def random_motion(seed: int, joints: int = 12, frames: int = 20, animated_offsets: bool = False) -> Motion:
    g = torch.Generator().manual_seed(seed)
    parents = [-1] + [int(torch.randint(0, j, (1,), generator=g)) for j in range(1, joints)]
    offsets = (torch.rand(joints, 3, generator=g, dtype=torch.float64) - 0.5) * 0.4
    leaves = [j for j in range(joints) if j not in parents]
    skeleton = Skeleton([f"j{j}" for j in range(joints)], parents, offsets.numpy(), leaves,
                        np.full((len(leaves), 3), 0.05))
    q = torch.nn.functional.normalize(torch.randn(frames, joints, 4, generator=g), dim=-1)
    # Gimbal-lock rotations (middle ZYX angle +-90 degrees) on the first frames.
    q[0] = rot.euler_to_quat("ZYX", torch.tensor([30.0, 90.0, 10.0])).expand(joints, 4)
    q[1] = rot.euler_to_quat("ZYX", torch.tensor([-120.0, -90.0, 45.0])).expand(joints, 4)
    root = torch.randn(frames, 3, generator=g) + torch.tensor([0.0, 1.0, 0.0])
    joint_offsets = None
    if animated_offsets:
        joint_offsets = torch.as_tensor(offsets, dtype=torch.float32).expand(frames, joints, 3).clone()
        joint_offsets += 0.05 * torch.randn(frames, joints, 3, generator=g)
    return Motion(skeleton, q, root, 30.0, joint_offsets)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("order", ["ZYX", "XYZ", "YZX"])
def test_round_trip_random(tmp_path, seed, order):
    motion = random_motion(seed, animated_offsets=seed % 2 == 1)
    back = read_bvh(write_and_path(motion, tmp_path / "r.bvh", euler_order=order), units="m")
    # Joints come back depth-first; compare by name.
    index = [back.skeleton.index(n) for n in motion.skeleton.names]
    torch.testing.assert_close(back.world_positions()[:, index], motion.world_positions(), atol=1e-5, rtol=0)
    by_name = {n: i for i, n in enumerate(back.skeleton.end_site_names)}
    end_index = [by_name[n] for n in motion.skeleton.end_site_names]
    torch.testing.assert_close(back.end_site_positions()[:, end_index], motion.end_site_positions(), atol=1e-5, rtol=0)
    assert (back.joint_offsets is None) == (motion.joint_offsets is None)


def test_write_is_atomic(tmp_path, monkeypatch):
    target = write(tmp_path, SMALL, "keep.bvh")
    motion = read_bvh(target)

    def broken_replace(*args):
        raise OSError("disk full")

    monkeypatch.setattr("humotion.io.bvh.os.replace", broken_replace)
    with pytest.raises(OSError):
        write_bvh(motion, target)
    assert target.read_text() == SMALL
    assert [p.name for p in tmp_path.iterdir()] == ["keep.bvh"]


def test_write_rejects_bad_arguments(tmp_path):
    motion = read_bvh(write(tmp_path, SMALL))
    with pytest.raises(ValueError, match="euler_order"):
        write_bvh(motion, tmp_path / "o.bvh", euler_order="ZZX")
    spaced = Motion(Skeleton(("a b",), (-1,), np.zeros((1, 3))), rot.quat_identity(1, 1), torch.zeros(1, 3), 30.0)
    with pytest.raises(ValueError, match="whitespace"):
        write_bvh(spaced, tmp_path / "o.bvh")
    assert not (tmp_path / "o.bvh").exists()


# -- malformed input ----------------------------------------------------------------------
def _cut_after(text: str, line: int) -> str:
    return "\n".join(text.split("\n")[:line]) + "\n"


L = {key: line_of(SMALL, key) for key in ("JOINT Head", "CHANNELS 3 Zrotation Xrotation", "MOTION", "Frames:",
                                           "Frame Time:", "JOINT LeftLeg", "OFFSET 10 0 0")}
ROW1, ROW2, ROW3 = L["Frame Time:"] + 1, L["Frame Time:"] + 2, L["Frame Time:"] + 3
CLOSE_LEG = L["MOTION"] - 2  # the "  }" closing LeftUpLeg

MALFORMED = {
    "hierarchy cut off": (_cut_after(SMALL, L["JOINT LeftLeg"] + 2), L["JOINT LeftLeg"] + 2, "ends inside the hierarchy"),
    "fewer rows than Frames": (_cut_after(SMALL, ROW2), ROW2, "ends after 2 of 3 frames"),
    "short last row": (SMALL[: SMALL.rindex(" 30 -20")] + "\n", ROW3, "has 12 values"),
    "long row": (replace_line(SMALL, ROW2, SMALL.split("\n")[ROW2 - 1] + " 7"), ROW2, "has 16 values"),
    "not a number": (replace_line(SMALL, ROW2, SMALL.split("\n")[ROW2 - 1].replace("10", "1O", 1)), ROW2, "'1O' is not a number"),
    "nan": (replace_line(SMALL, ROW3, SMALL.split("\n")[ROW3 - 1].replace("30", "nan")), ROW3,
            "NaN or infinity (frame 2, joint 'LeftUpLeg', channel Zrotation)"),
    "inf": (replace_line(SMALL, ROW1, SMALL.split("\n")[ROW1 - 1].replace("2", "-inf", 1)), ROW1,
            "NaN or infinity (frame 0, joint 'Hips', channel Yposition)"),
    "extra row": (SMALL + "1 2 3 0 0 0 0 0 0 0 0 0 0 0 0\n", ROW3 + 1, "more motion rows"),
    "missing }": (replace_line(SMALL, CLOSE_LEG, None), L["MOTION"] - 1, "unbalanced braces"),
    "extra }": (replace_line(SMALL, CLOSE_LEG, "  }\n  }"), CLOSE_LEG + 2, "unbalanced braces"),
    "unknown keyword": (replace_line(SMALL, L["JOINT Head"] + 2, "      OFSET 0 50 0"), L["JOINT Head"] + 2, "unknown keyword 'OFSET'"),
    "CHANNELS count": (replace_line(SMALL, L["CHANNELS 3 Zrotation Xrotation"], "    CHANNELS 4 Zrotation Xrotation Yrotation"),
                       L["CHANNELS 3 Zrotation Xrotation"], "CHANNELS says 4 but lists 3"),
    "unknown channel": (replace_line(SMALL, L["CHANNELS 3 Zrotation Xrotation"], "    CHANNELS 3 Zrotation Wrotation Yrotation"),
                        L["CHANNELS 3 Zrotation Xrotation"], "unknown channel 'Wrotation'"),
    "repeated channel": (replace_line(SMALL, L["CHANNELS 3 Zrotation Xrotation"], "    CHANNELS 3 Zrotation Xrotation Zrotation"),
                         L["CHANNELS 3 Zrotation Xrotation"], "listed twice"),
    "no MOTION": (_cut_after(SMALL, L["MOTION"] - 1), L["MOTION"] - 1, "no MOTION section"),
    "duplicate joint": (replace_line(SMALL, L["JOINT LeftLeg"], "    JOINT Spine"), L["JOINT LeftLeg"], "duplicate joint name 'Spine'"),
    "zero frames": (SMALL.replace("Frames: 3", "Frames: 0"), L["Frames:"], "no frames"),
    "bad frame count": (SMALL.replace("Frames: 3", "Frames: three"), L["Frames:"], "not a whole number"),
    "missing Frame Time": (replace_line(SMALL, L["Frame Time:"], None), L["Frame Time:"], "expected 'Frame Time:"),
    "zero Frame Time": (SMALL.replace("Frame Time: 0.0333333", "Frame Time: 0"), L["Frame Time:"], "positive"),
    "OFFSET with 2 numbers": (replace_line(SMALL, L["OFFSET 10 0 0"], "    OFFSET 10 0"), L["OFFSET 10 0 0"], "OFFSET needs 3 numbers"),
    "OFFSET nan": (replace_line(SMALL, L["OFFSET 10 0 0"], "    OFFSET 10 nan 0"), L["OFFSET 10 0 0"], "not a finite number"),
    "no HIERARCHY": (SMALL.replace("HIERARCHY", "HIERARCHIES"), 1, "starts with HIERARCHY"),
    "missing {": (replace_line(SMALL, L["JOINT Head"] + 1, None), L["JOINT Head"] + 1, "expected '{' to open 'Head'"),
    "cut after MOTION": (_cut_after(SMALL, L["MOTION"]), L["MOTION"], "file ends before 'Frames:'"),
    "only HIERARCHY": ("HIERARCHY\n\n", 1, "no MOTION section"),
}


@pytest.mark.parametrize("case", MALFORMED)
def test_malformed(tmp_path, case):
    text, line, problem = MALFORMED[case]
    path = write(tmp_path, text, "bad.bvh")
    with pytest.raises(MotionFileError) as raised:
        read_bvh(path)
    assert raised.value.line == line, str(raised.value)
    assert problem in raised.value.problem
    assert str(raised.value).startswith(f"{path}, line {line}: ")


@pytest.mark.parametrize("content, problem", [(b"", "empty"), (b" \r\n\t\n", "empty"),
                                              (gzip.compress(SMALL.encode())[:-30], "gzip")])
def test_unreadable(tmp_path, content, problem):
    with pytest.raises(MotionFileError, match=problem):
        read_bvh(write(tmp_path, content))


def test_missing_file(tmp_path):
    with pytest.raises(MotionFileError, match="cannot read"):
        read_bvh(tmp_path / "absent.bvh")


# -- fuzzing ------------------------------------------------------------------------------
SMALL_BYTES = SMALL.encode()
TOKENS = SMALL.replace("\n", " \n ").split(" ")


def _mutate(data) -> bytes:
    kind = data.draw(st.sampled_from(["truncate", "bytes", "delete token", "duplicate token", "swap token"]))
    if kind == "truncate":
        return SMALL_BYTES[: data.draw(st.integers(0, len(SMALL_BYTES)))]
    if kind == "bytes":
        out = bytearray(SMALL_BYTES)
        for _ in range(data.draw(st.integers(1, 4))):
            out[data.draw(st.integers(0, len(out) - 1))] = data.draw(st.integers(0, 255))
        return bytes(out)
    tokens = list(TOKENS)
    i = data.draw(st.integers(0, len(tokens) - 1))
    if kind == "delete token":
        del tokens[i]
    elif kind == "duplicate token":
        tokens.insert(i, tokens[i])
    else:
        tokens[i] = data.draw(st.sampled_from(["{", "}", "JOINT", "End", "OFFSET", "CHANNELS", "MOTION", "1e400",
                                               "-0", "99999999999999999999", "Xposition", "nan", "", "\r"]))
    return " ".join(tokens).encode()


@pytest.fixture(scope="module")
def fuzz_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("fuzz")


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_fuzz_mutations_raise_only_motion_file_error(fuzz_dir, data):
    """Truncations, byte changes, token deletions/duplications/swaps: a Motion or MotionFileError."""
    path = fuzz_dir / "fuzz.bvh"
    path.write_bytes(_mutate(data))
    try:
        motion = read_bvh(path)
    except MotionFileError:
        return
    assert isinstance(motion, Motion) and motion.num_frames >= 1
    assert torch.isfinite(motion.rotations).all() and math.isfinite(motion.fps)


def test_units_table():
    assert UNITS["cmu"] == pytest.approx(0.0254 / 0.45)
    assert set(UNITS) == {"m", "cm", "mm", "inch", "cmu"}

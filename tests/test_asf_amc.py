"""ASF/AMC reading: real CMU and HDM05 files, known answers, malformed input, fuzzing."""

from __future__ import annotations

import gzip
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from humotion import rotations as rot
from humotion.io import load_motion
from humotion.io.amc import _parse_general, _parse_regular
from humotion.io.asf_amc import AsfSkeleton, find_asf, read_amc, read_asf
from humotion.io.errors import MotionFileError
from data_root import MOCAP
from textedit import replace_line

FAIR = MOCAP / "cmu_fairmotion"
CMU_UNIT = 0.0254 / 0.45


def need(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"data file not found: {path}")
    return path


@pytest.fixture(scope="module")
def asf01() -> AsfSkeleton:
    return read_asf(need(FAIR / "01.asf"))


@pytest.fixture(scope="module")
def amc01(asf01):
    return read_amc(need(FAIR / "01_01.amc"), asf=asf01)


def frame_lines(text: str) -> int:
    return len(re.findall(r"^\d+\s*$", text, re.M))


# -- ASF ----------------------------------------------------------------------------------------
def test_asf_skeleton(asf01):
    sk = asf01.skeleton
    assert sk.num_joints == 31
    assert sk.names[0] == "root" and {"lfemur", "ltibia", "thorax", "rthumb"} <= set(sk.names)
    assert sk.names[sk.parents[sk.index("ltibia")]] == "lfemur"
    assert sk.names[sk.parents[sk.index("lclavicle")]] == "thorax"
    assert sorted(sk.end_site_names) == sorted(["ltoes_end", "rtoes_end", "head_end", "lfingers_end", "lthumb_end",
                                                "rfingers_end", "rthumb_end"])
    assert asf01.metres_per_unit == pytest.approx(0.0564444, rel=1e-5)
    assert 1.5 < sk.height() < 1.8
    # A joint sits at its bone's start: lfemur (the hip) is offset from the root by the lhipjoint bone.
    lhip = np.array([0.566809, -0.746272, 0.349008]) * 2.40479 * CMU_UNIT
    np.testing.assert_allclose(sk.offsets[sk.index("lfemur")], lhip, atol=1e-9)
    np.testing.assert_allclose(sk.offsets[sk.index("lhipjoint")], 0.0)
    # left is +X, up is +Y, the feet point +Z
    rest = sk.rest_positions()
    assert rest[sk.index("lfemur"), 0] > 0 > rest[sk.index("rfemur"), 0]
    assert rest[sk.index("head"), 1] > 0 > rest[sk.index("lfoot"), 1]
    assert sk.rest_end_site_positions()[sk.end_site_names.index("ltoes_end"), 2] > rest[sk.index("lfoot"), 2]


def test_asf_dofs_limits_axes(asf01):
    assert asf01.dofs["ltibia"] == ("rx",)
    assert asf01.limits["ltibia"] == ((-10.0, 170.0),)
    assert asf01.dofs["lfemur"] == ("rx", "ry", "rz")
    assert asf01.limits["lfemur"] == ((-160.0, 20.0), (-70.0, 70.0), (-60.0, 70.0))
    assert asf01.dofs["lclavicle"] == ("ry", "rz")
    assert asf01.dofs["lhipjoint"] == () and asf01.limits["lhipjoint"] == ()
    assert asf01.dofs["root"] == ("tx", "ty", "tz", "rx", "ry", "rz") == asf01.root_order
    np.testing.assert_allclose(asf01.axis_angles["lfemur"], [0, 0, 20])
    assert asf01.axis_orders["lhumerus"] == "XYZ"
    assert asf01.units["angle"] == "deg" and asf01.units["length"] == 0.45
    # C for "axis 0 0 20 XYZ" is a 20 degree turn about Z.
    c = torch.as_tensor(asf01.axis_rotations[asf01.skeleton.index("lfemur")])
    np.testing.assert_allclose(rot.convert(c, "quat", "rotvec").numpy(), [0, 0, math.radians(20)], atol=1e-9)


# -- AMC on real files --------------------------------------------------------------------------
def test_amc_01_01(amc01, asf01):
    text = (FAIR / "01_01.amc").read_text()
    assert frame_lines(text) == 2751
    assert amc01.num_frames == 2751 and amc01.fps == 120.0 and amc01.name == "01_01"
    assert amc01.skeleton is asf01.skeleton
    # root line of frame 1: "root 9.37216 17.8693 -17.3198 -2.01677 -7.59696 -3.23164"
    np.testing.assert_allclose(amc01.root_positions[0].numpy(), np.array([9.37216, 17.8693, -17.3198]) * CMU_UNIT, rtol=1e-6)
    # ltibia of frame 1 is "rx 20.088" about the bone's x axis, which "axis 0 0 20" turns 20 deg about Z:
    # the local rotation is 20.088 deg about (cos 20, sin 20, 0).
    q = amc01.rotations[0, asf01.skeleton.index("ltibia")].double()
    axis = np.array([math.cos(math.radians(20)), math.sin(math.radians(20)), 0.0])
    np.testing.assert_allclose(rot.convert(q, "quat", "rotvec").numpy(), axis * math.radians(20.088), atol=1e-6)
    # joints without dofs stay put, the figure stands on the floor in a plausible size
    assert torch.allclose(amc01.rotations[:, asf01.skeleton.index("lhipjoint")], torch.tensor([1.0, 0, 0, 0]))
    pos = amc01.world_positions()
    feet = pos[:, [asf01.skeleton.index(n) for n in ("lfoot", "rfoot", "ltoes", "rtoes")], 1]
    assert -0.05 < float(feet.min()) < 0.15
    assert 1.3 < float((pos[0, :, 1].max() - pos[0, :, 1].min())) < 1.8


def test_gzip_copy_finds_its_asf(amc01):
    path = need(MOCAP / "cmu_cyun9601" / "amc" / "01" / "01_01.amc.gz")
    assert find_asf(path).name == "01.asf"  # ../../asf/01.asf
    motion = read_amc(path)
    assert motion.name == "01_01" and motion.num_frames == frame_lines(gzip.decompress(path.read_bytes()).decode())
    # The same take as the plain fairmotion copy (which only adds a comment line).
    torch.testing.assert_close(motion.rotations, amc01.rotations)
    torch.testing.assert_close(motion.root_positions, amc01.root_positions)


def test_hdm05_finds_actor_asf():
    path = need(MOCAP / "hdm05_jointlearning" / "amc" / "squat1Reps" / "HDM_bd_squat1Reps_001_120.amc.gz")
    assert find_asf(path).name == "HDM_bd.asf"
    motion = load_motion(path)
    assert motion.skeleton.num_joints == 31 and motion.name == "HDM_bd_squat1Reps_001_120"
    assert motion.num_frames == frame_lines(gzip.decompress(path.read_bytes()).decode("latin-1"))
    assert 1.4 < motion.skeleton.height() < 1.9


def test_sxaxmz_layout_and_labelled_names():
    folder = need(MOCAP / "cmu_sxaxmz" / "amc" / "05")
    path = sorted(folder.glob("05_02*.amc.gz"))[0]
    assert find_asf(path) == (MOCAP / "cmu_sxaxmz" / "asf" / "05.asf").resolve()   # the reader resolves the AMC's folder
    assert read_amc(path).num_frames > 100


def test_truncated_cmu_file():
    """cmu_visdoom_mocapplayer/amc/07_12-walk.amc really ends inside frame 245 (no ltoes line)."""
    path = need(MOCAP / "cmu_visdoom_mocapplayer" / "amc" / "07_12-walk.amc")
    with pytest.raises(MotionFileError, match="truncated last frame: frame 245") as info:
        read_amc(path)
    assert info.value.line == len(path.read_text().rstrip("\n").split("\n"))
    assert read_amc(path, allow_truncated=True).num_frames == 244


@pytest.mark.slow
def test_every_amc_file_reads():
    files = sorted(p for p in MOCAP.rglob("*") if p.name.lower().endswith((".amc", ".amc.gz")) and p.is_file())
    assert len(files) > 300
    for path in files:
        motion = read_amc(path, allow_truncated=True)
        assert motion.num_frames > 0 and 1.2 < motion.skeleton.height() < 2.0, path


# -- small synthetic files ------------------------------------------------------------------------
def snippet(frames: int = 3) -> str:
    """The header and first frames of 01_01.amc (30 lines a frame)."""
    lines = need(FAIR / "01_01.amc").read_text().split("\n")
    return "\n".join(lines[: 4 + 30 * frames]) + "\n"


def write(tmp_path: Path, text: str, name: str = "clip.amc") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_radians_and_any_bone_order_agree(tmp_path, asf01):
    base = read_amc(write(tmp_path, snippet()), asf=asf01)
    lines = snippet().split("\n")
    # every frame's bone lines in reverse order: the line-by-line reader takes them
    shuffled = lines[:4]
    for f in range(3):
        block = lines[4 + 30 * f: 4 + 30 * (f + 1)]
        shuffled += [block[0]] + block[1:][::-1]
    other = read_amc(write(tmp_path, "\n".join(shuffled) + "\n", "shuffled.amc"), asf=asf01)
    torch.testing.assert_close(other.rotations, base.rotations)
    # the same angles in radians
    out = []
    for line in lines:
        t = line.split()
        if line.startswith(":DEGREES"):
            out.append(":RADIANS")
        elif t and t[0] in asf01.dofs:
            vals = [float(v) for v in t[1:]]
            rad = [v if d.startswith("t") else math.radians(v) for d, v in zip(asf01.dofs[t[0]], vals)]
            out.append(" ".join([t[0]] + [repr(v) for v in rad]))
        else:
            out.append(line)
    radians = read_amc(write(tmp_path, "\n".join(out), "radians.amc"), asf=asf01)
    torch.testing.assert_close(radians.rotations, base.rotations, atol=1e-6, rtol=0)
    torch.testing.assert_close(radians.root_positions, base.root_positions)
    # gzip, found by content
    gz = tmp_path / "zipped.amc.gz"
    gz.write_bytes(gzip.compress(snippet().encode()))
    torch.testing.assert_close(read_amc(gz, asf=asf01).rotations, base.rotations)


def test_bones_without_dofs_may_be_listed(tmp_path, asf01):
    """Some exporters write a bare 'lhipjoint' line for bones without dofs; both readers take it."""
    base = read_amc(write(tmp_path, snippet()), asf=asf01)
    text = re.sub(r"^(lowerback .*)$", r"lhipjoint\n\1", snippet(), flags=re.M)
    torch.testing.assert_close(read_amc(write(tmp_path, text, "a.amc"), asf=asf01).rotations, base.rotations)
    # ... but they do not stand in for a missing bone with dofs
    text = text.replace("lowerback 2.30193 -0.395121 1.17299\n", "", 1)
    with pytest.raises(MotionFileError, match="incomplete frame: frame 1 .* lowerback") as info:
        read_amc(write(tmp_path, text, "b.amc"), asf=asf01)
    assert info.value.line == 5


# line 5 is "1", 6 "root ...", 7 "lowerback ...", 35 "2", 65 "3", 94 the last "ltoes ..."
@pytest.mark.parametrize("change, line, message", [
    ((7, "lowerbak 2.30193 -0.395121 1.17299"), 7, "unknown bone 'lowerbak'"),
    ((7, "lowerback 2.30193 -0.395121"), 7, "has 2 value"),
    ((7, "lowerback 2.30193 -0.395121 1.17299 4"), 7, "has 4 value"),
    ((7, "lowerback 2.30193 abc 1.17299"), 7, "non-numeric value 'abc'"),
    ((7, "lowerback 2.30193 nan 1.17299"), 7, "NaN or infinite"),
    ((7, "lowerback 2.30193 1e999 1.17299"), 7, "NaN or infinite"),
    ((35, "3"), 35, "frames missing"),
    ((65, "2"), 65, "out of order"),
    ((35, None), 35, "'root' appears twice in frame 1 .first at line 6"),
    ((35, "2 2"), 35, "only the number"),
    ((94, None), 93, "truncated last frame: frame 3"),
    ((94, "ltoes"), 94, "seems truncated"),
    ((8, None), 5, "incomplete frame: frame 1 .* upperback"),
    ((6, "root 9.37216 17.8693 -17.3198 -2.01677 -7.59696 -3.23164 :x"), 6, "root' has 7 value"),
])
def test_amc_errors_name_the_line(tmp_path, asf01, change, line, message):
    path = write(tmp_path, replace_line(snippet(), *change))
    with pytest.raises(MotionFileError, match=message) as info:
        read_amc(path, asf=asf01)
    assert info.value.line == line and info.value.path == str(path)
    assert f"line {line}:" in str(info.value)


def test_amc_empty_and_headerless(tmp_path, asf01):
    with pytest.raises(MotionFileError, match="empty"):
        read_amc(write(tmp_path, "", "empty.amc"), asf=asf01)
    with pytest.raises(MotionFileError, match="no frames"):
        read_amc(write(tmp_path, ":FULLY-SPECIFIED\n:DEGREES\n", "header.amc"), asf=asf01)
    with pytest.raises(MotionFileError, match="expected a frame number") as info:
        read_amc(write(tmp_path, ":DEGREES\nroot 1 2 3 4 5 6\n", "noframe.amc"), asf=asf01)
    assert info.value.line == 2


def test_missing_asf_says_where_it_looked(tmp_path):
    folder = tmp_path / "deep" / "amc"
    folder.mkdir(parents=True)
    path = write(folder, snippet(), "77_01.amc")
    with pytest.raises(MotionFileError, match=r"no ASF skeleton found.*77\.asf.*looked|looked.*77\.asf"):
        read_amc(path)
    # ../asf/<subject>.asf is found, in any letter case
    (folder.parent / "asf").mkdir()
    shutil.copy(FAIR / "01.asf", folder.parent / "asf" / "77.ASF")
    assert read_amc(path).num_frames == 3


def test_asf_errors(tmp_path):
    text = need(FAIR / "01.asf").read_text()
    lines = text.split("\n")
    bad_parent = text.replace("    lhumerus lradius", "    lhumerrus lradius")
    line = bad_parent.split("\n").index("    lhumerrus lradius") + 1
    with pytest.raises(MotionFileError, match="unknown parent 'lhumerrus'") as info:
        read_asf(write(tmp_path, bad_parent, "a.asf"))
    assert info.value.line == line
    # a bone block without its direction: reported at the block's 'begin'
    d = next(i for i, s in enumerate(lines) if s.strip().startswith("direction"))
    begin = max(i for i in range(d) if lines[i].strip() == "begin")
    with pytest.raises(MotionFileError, match="bone block has no direction") as info:
        read_asf(write(tmp_path, "\n".join(lines[:d] + lines[d + 1:]), "b.asf"))
    assert info.value.line == begin + 1
    with pytest.raises(MotionFileError, match="2 dofs but 1 limits"):
        read_asf(write(tmp_path, text.replace("limits (-45.0 90.0)\n           (-70.0 20.0)", "limits (-45.0 90.0)"), "c.asf"))
    with pytest.raises(MotionFileError, match="not connected to the root"):
        read_asf(write(tmp_path, text.replace("    rhand rfingers\n", ""), "d.asf"))
    with pytest.raises(MotionFileError, match="unknown dof 'rw'"):
        read_asf(write(tmp_path, text.replace("dof rx ry rz", "dof rx rw rz", 1), "e.asf"))
    with pytest.raises(MotionFileError, match="empty"):
        read_asf(write(tmp_path, "  \n", "f.asf"))


def test_asf_other_orders_and_radians(tmp_path, asf01):
    """axis given in ZYX order and radians: same C when the angles describe the same rotation."""
    text = need(FAIR / "01.asf").read_text()
    new = text.replace("angle deg", "angle rad").replace("axis 0 0 20  XYZ", "axis 0 0 0.3490658503988659 ZYX")
    asf = read_asf(write(tmp_path, new, "rad.asf"))
    j = asf.skeleton.index("lfemur")
    np.testing.assert_allclose(asf.axis_rotations[j], asf01.axis_rotations[j], atol=1e-12)
    np.testing.assert_allclose(asf.axis_angles["lfemur"], [0, 0, 20])  # reported in degrees
    assert asf.limits["ltibia"][0] == pytest.approx((math.degrees(-10.0), math.degrees(170.0)))


def test_bone_translation_and_length_dofs(tmp_path):
    """tx/ty/tz move a joint (in its axis frame), l stretches its bone: Motion.joint_offsets."""
    asf_text = """:version 1.10
:units
  length 0.45
  angle deg
:root
  order TX TY TZ RX RY RZ
  axis XYZ
  position 0 0 0
  orientation 0 0 0
:bonedata
  begin
    id 1
    name a
    direction 0 1 0
    length 10
    axis 0 0 90 XYZ
    dof rx l
  end
  begin
    id 2
    name b
    direction 0 1 0
    length 5
    axis 0 0 0 XYZ
    dof tx
  end
:hierarchy
  begin
    root a
    a b
  end
"""
    asf = read_asf(write(tmp_path, asf_text, "t.asf"))
    amc = ":DEGREES\n1\nroot 0 0 0 0 0 0\na 0 2\nb 3\n2\nroot 0 0 0 0 0 0\na 90 0\nb 0\n"
    motion = read_amc(write(tmp_path, amc, "t.amc"), asf=asf)
    offsets = motion.joint_offsets.numpy() / CMU_UNIT
    np.testing.assert_allclose(offsets[0, asf.skeleton.index("b")], [3, 12, 0], atol=1e-5)  # 10 + l=2 along y, tx 3
    np.testing.assert_allclose(offsets[1, asf.skeleton.index("b")], [0, 10, 0], atol=1e-5)
    # rx about the bone axis, which "axis 0 0 90" turns onto +Y: 90 deg about world +Y
    q = motion.rotations[1, asf.skeleton.index("a")].double()
    np.testing.assert_allclose(rot.convert(q, "quat", "rotvec").numpy(), [0, math.pi / 2, 0], atol=1e-6)


# -- fuzzing --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def fuzz_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("amc_fuzz")


@st.composite
def damaged(draw):
    data = bytearray(snippet(2).encode())
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["truncate", "corrupt", "delete_token", "duplicate_line", "insert"]))
        if not data:
            break
        if kind == "truncate":
            del data[draw(st.integers(0, len(data) - 1)):]
        elif kind == "corrupt":
            data[draw(st.integers(0, len(data) - 1))] = draw(st.sampled_from(b"0123456789 \n\t-.eE#:xnaif\x00\xff\r"))
        elif kind == "insert":
            at = draw(st.integers(0, len(data)))
            data[at:at] = draw(st.sampled_from([b"\n", b" ", b"nan", b"inf", b"1e999", b"lfemur", b"7\n", b"#", b"\n\n"]))
        else:
            text = data.decode("latin-1")
            lines = text.split("\n")
            i = draw(st.integers(0, len(lines) - 1))
            if kind == "duplicate_line":
                lines.insert(i, lines[i])
            else:
                tokens = lines[i].split(" ")
                del tokens[draw(st.integers(0, len(tokens) - 1))]
                lines[i] = " ".join(tokens)
            data = bytearray("\n".join(lines).encode("latin-1"))
    return bytes(data)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(damaged())
def test_fuzz_amc_reader(fuzz_dir, asf01, data):
    path = fuzz_dir / "fuzz.amc"
    path.write_bytes(data)
    try:
        motion = read_amc(path, asf=asf01)
    except MotionFileError as error:
        assert error.path == str(path)
        motion = None
    if motion is not None:
        assert motion.num_frames >= 1 and torch.isfinite(motion.rotations).all()
    # The fast reader never accepts what the line-by-line reader rejects, and agrees with it.
    text = data.decode("utf-8", errors="replace")
    lines = text.split("\n")
    start = next((i for i, s in enumerate(lines) if s.strip() and not s.strip().startswith(("#", ":"))), None)
    if start is None or not lines[start].strip().isdigit():
        return
    fast = _parse_regular(lines, start, asf01)
    if fast is not None:
        slow = _parse_general(path, lines, start, asf01)
        assert slow[0] == fast[0] and slow[1].keys() == fast[1].keys()
        for bone in fast[1]:
            np.testing.assert_array_equal(slow[1][bone], fast[1][bone])


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.data())
def test_fuzz_asf_reader(fuzz_dir, data):
    """Damaged ASF files: an AsfSkeleton or MotionFileError, nothing else."""
    text = bytearray(need(FAIR / "01.asf").read_bytes())
    for _ in range(data.draw(st.integers(1, 4))):
        if not text:
            break
        at = data.draw(st.integers(0, len(text) - 1))
        kind = data.draw(st.sampled_from(["truncate", "corrupt", "insert", "delete"]))
        if kind == "truncate":
            del text[at:]
        elif kind == "corrupt":
            text[at] = data.draw(st.sampled_from(b"0123456789 \n\t-.eE#:()xnaifXYZ\x00\xff\r"))
        elif kind == "delete":
            del text[at:at + data.draw(st.integers(1, 40))]
        else:
            text[at:at] = data.draw(st.sampled_from([b"\n", b"end\n", b"begin\n", b"(", b")", b"nan", b"1e999",
                                                     b" root", b":hierarchy\n", b"dof rx l tx\n", b"limits (1 2)\n"]))
    path = fuzz_dir / "fuzz.asf"
    path.write_bytes(bytes(text))
    try:
        asf = read_asf(path)
    except MotionFileError as error:
        assert error.path == str(path)
    else:
        assert asf.skeleton.names[0] == "root" and set(asf.dofs) == set(asf.skeleton.names)

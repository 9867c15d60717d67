"""The CMU exp-map text format (cmu_expmap_li2018): FK against the source repo's convention."""

from __future__ import annotations

import gzip
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from humotion.io import load_motion
from humotion.io.errors import MotionFileError
from humotion.io.expmap import CMU_EXPMAP_JOINTS, CMU_UNIT, read_expmap, read_expmap_skeleton

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
ROOT = DATA / "mocap" / "cmu_expmap_li2018"
WALK = ROOT / "data" / "test" / "walking" / "walking_1.txt.gz"
JUMP = ROOT / "data" / "test" / "jumping" / "jumping_1.txt.gz"


def need(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"data file not found: {path}")
    return path


def rodrigues(r: np.ndarray) -> np.ndarray:
    """R(e) = I + sin(t) K + (1 - cos(t)) K^2, as expmap2rotmat in the source repo."""
    t = np.linalg.norm(r)
    if t < 1e-12:
        return np.eye(3)
    k = r / t
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(t) * kx + (1 - np.cos(t)) * kx @ kx


def repo_fk(row: np.ndarray, parent: list[int], offset: np.ndarray) -> np.ndarray:
    """The repo's row-vector FK, straight from skeleton.json's description (file units)."""
    joints = len(parent)
    rotation, xyz = [None] * joints, [None] * joints
    for j in range(joints):
        r = rodrigues(row[3 + 3 * j: 6 + 3 * j])
        if parent[j] < 0:
            rotation[j], xyz[j] = r, offset[j] + row[:3]
        else:
            xyz[j] = offset[j] @ rotation[parent[j]] + xyz[parent[j]]
            rotation[j] = r @ rotation[parent[j]]
    return np.array(xyz)


@pytest.mark.parametrize("clip", [WALK, JUMP])
def test_fk_matches_the_repo_convention(clip):
    need(clip)
    skeleton = json.loads((ROOT / "skeleton.json").read_text())
    raw = np.loadtxt(gzip.open(clip, "rt"), delimiter=",")
    assert raw.shape[1] == 117
    motion = read_expmap(clip)
    assert motion.num_frames == len(raw)
    frames = np.arange(0, len(raw), max(1, len(raw) // 150))  # ~150 frames spread over the clip
    expected = np.array([repo_fk(raw[f], skeleton["parent"], np.array(skeleton["offset_raw"])) for f in frames]) * CMU_UNIT
    got = motion.world_positions().numpy()[frames]
    error = np.abs(got - expected).max()
    print(f"\n{clip.name}: max |humotion FK - repo FK| = {error * 1000:.4f} mm")
    assert error < 1e-4


def test_skeleton_names_and_geometry():
    skeleton, root_offset = read_expmap_skeleton(need(ROOT / "skeleton.json"))
    assert skeleton.num_joints == 38 and skeleton.names == CMU_EXPMAP_JOINTS
    np.testing.assert_allclose(root_offset, 0.0)
    parent = {n: skeleton.names[p] if p >= 0 else None for n, p in zip(skeleton.names, skeleton.parents)}
    assert parent["lfemur"] == "lhipjoint" and parent["ltoes_end"] == "ltoes"
    assert parent["lclavicle"] == parent["lowerneck"] == "thorax" and parent["lthumb"] == "lwrist"
    rest = skeleton.rest_positions()
    at = {n: rest[i] for i, n in enumerate(skeleton.names)}
    # joints sit at bone starts: the hipjoint bones start at the root, the hip at their end
    np.testing.assert_allclose(at["lhipjoint"], at["root"])
    assert np.linalg.norm(at["lfemur"] - at["root"]) > 0.1 and at["lfemur"][0] > 0 > at["rfemur"][0]
    # as in CMU's cgspeed BVH, thorax and wrist bones have no length here
    np.testing.assert_allclose(at["lowerneck"], at["thorax"])
    np.testing.assert_allclose(at["lhand"], at["lwrist"])
    assert np.linalg.norm(at["upperneck"] - at["lowerneck"]) > 0.05
    # metric size: 1.42 m from toe tips to the top of the head bone (no thorax, ~12 cm, in this tree)
    assert 1.3 < skeleton.height() < 1.6
    assert 0.40 < np.linalg.norm(at["ltibia"] - at["lfemur"]) < 0.46  # thigh, metres


def test_walk_is_upright_and_knees_bend_forward():
    motion = read_expmap(need(WALK))
    assert motion.skeleton.num_joints == 38 and motion.fps == 120.0 and motion.name == "walking_1"
    pos = motion.world_positions().numpy()
    idx = motion.skeleton.index
    height = pos[:, :, 1].max(1) - pos[:, :, 1].min(1)
    assert 1.35 < np.median(height) < 1.6
    assert -0.05 < pos[:, [idx("ltoes"), idx("rtoes")], 1].min() < 0.1  # on the floor
    assert pos[:, idx("head"), 1].min() > pos[:, idx("root"), 1].max()  # head above the pelvis
    for side in "lr":
        hip, knee, ankle, toe = (pos[:, idx(side + n)] for n in ("femur", "tibia", "foot", "toes"))
        forward = toe - ankle
        forward /= np.linalg.norm(forward, axis=1, keepdims=True)
        thigh = (knee - hip) / np.linalg.norm(knee - hip, axis=1, keepdims=True)
        shank = (ankle - knee) / np.linalg.norm(ankle - knee, axis=1, keepdims=True)
        # a flexed knee points forward: the shank turns back relative to the thigh
        bend = np.einsum("fi,fi->f", shank - thigh, forward)
        assert (bend < 1e-3).mean() > 0.99


def test_plain_text_and_load_motion(tmp_path):
    need(WALK)
    folder = tmp_path / "set" / "walking"
    folder.mkdir(parents=True)
    shutil.copy(ROOT / "skeleton.json", tmp_path / "set" / "skeleton.json")  # found two levels up
    plain = folder / "walking_1.txt"
    plain.write_bytes(gzip.decompress(WALK.read_bytes()))
    a, b = read_expmap(plain), load_motion(WALK)
    assert a.name == b.name == "walking_1"
    np.testing.assert_array_equal(a.rotations.numpy(), b.rotations.numpy())


def test_errors_name_the_line(tmp_path):
    shutil.copy(need(ROOT / "skeleton.json"), tmp_path / "skeleton.json")
    lines = gzip.decompress(need(WALK).read_bytes()).decode().split("\n")[:5]

    def attempt(text: str, name: str = "bad.txt"):
        path = tmp_path / name
        path.write_text(text)
        with pytest.raises(MotionFileError) as info:
            read_expmap(path)
        return info.value

    error = attempt("\n".join(lines[:2] + [lines[2].rsplit(",", 1)[0]] + lines[3:]))
    assert error.line == 3 and "116 comma-separated values, expected 117" in error.problem
    error = attempt("\n".join(lines[:3] + [lines[3].replace(",", ",x", 1)] + lines[4:]))
    assert error.line == 4 and "non-numeric value 'x" in error.problem
    error = attempt("\n".join(lines[:1] + [lines[1].replace(",", ",nan,", 1).rsplit(",", 1)[0]] + lines[2:]))
    assert error.line == 2 and "NaN" in error.problem
    assert "empty" in attempt("\n\n", "empty.txt").problem
    with pytest.raises(MotionFileError, match="cannot read"):
        read_expmap(tmp_path / "bad.txt", skeleton_json=tmp_path / "missing.json")


def test_missing_skeleton_json(tmp_path_factory):
    folder = tmp_path_factory.mktemp("no_skeleton")
    if any((p / "skeleton.json").exists() for p in (folder, *folder.parents)):
        pytest.skip("a skeleton.json lies above the temporary folder")
    (folder / "x.txt").write_text(",".join(["0"] * 117) + "\n")
    with pytest.raises(MotionFileError, match="no skeleton.json found"):
        read_expmap(folder / "x.txt")
    # a json without the needed entries
    (folder / "skeleton.json").write_text('{"parent": [-1]}')
    with pytest.raises(MotionFileError, match="'parent' and 'offset_raw'"):
        read_expmap(folder / "x.txt")


@pytest.fixture(scope="module")
def fuzz_dir(tmp_path_factory):
    folder = tmp_path_factory.mktemp("expmap_fuzz")
    shutil.copy(need(ROOT / "skeleton.json"), folder / "skeleton.json")
    return folder


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.data())
def test_fuzz_expmap_reader(fuzz_dir, data):
    text = bytearray("\n".join(gzip.decompress(need(WALK).read_bytes()).decode().split("\n")[:3]).encode())
    for _ in range(data.draw(st.integers(1, 3))):
        if not text:
            break
        at = data.draw(st.integers(0, len(text) - 1))
        kind = data.draw(st.sampled_from(["truncate", "corrupt", "insert"]))
        if kind == "truncate":
            del text[at:]
        elif kind == "corrupt":
            text[at] = data.draw(st.sampled_from(b"0123456789,.-e \n\rxnaif\x00\xff"))
        else:
            text[at:at] = data.draw(st.sampled_from([b",", b"\n", b"nan", b"1e999", b"1e300", b",,"]))
    path = fuzz_dir / "fuzz.txt"
    path.write_bytes(bytes(text))
    try:
        motion = read_expmap(path)
    except MotionFileError as error:
        assert error.path == str(path)
    else:
        assert motion.skeleton.num_joints == 38 and motion.num_frames >= 1

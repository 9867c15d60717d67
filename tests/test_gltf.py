"""glTF export: round trips through write_gltf / read_gltf_animation and the GLB structure."""

import base64
import json
import math
import os
import shutil
import struct
import subprocess

import numpy as np
import pytest
import torch

from humotion import Motion, Skeleton
from humotion import rotations as rot
from humotion.assets import demo_clip_path
from humotion.io import MotionFileError, load_motion, save_motion
from humotion.io.gltf import read_gltf_animation, write_gltf

TOLERANCE = 1e-5  # metres


@pytest.fixture(scope="module")
def demo() -> Motion:
    return load_motion(demo_clip_path())


def random_motion(frames=23, fps=24.5, joint_offsets=False, seed=0) -> Motion:
    """A small skeleton whose joint order is breadth-first (not the depth-first order of BVH)."""
    g = torch.Generator().manual_seed(seed)
    rng = np.random.default_rng(seed)
    names = ["hips", "spine", "l_leg", "r_leg", "neck", "l_knee", "r_knee", "head"]
    parents = [-1, 0, 0, 0, 1, 2, 3, 4]
    skeleton = Skeleton(names, parents, rng.normal(size=(8, 3)) * 0.2, [7, 5, 6, 7],
                        rng.normal(size=(4, 3)) * 0.1, ["head_top", "l_foot", "r_foot", "nose"])
    rotations = rot.convert(torch.randn(frames, 8, 3, generator=g), "rotvec", "quat")
    rotations[::3] *= -1  # sign flips between frames must not matter
    offsets = skeleton.offsets + 0.05 * torch.randn(frames, 8, 3, generator=g) if joint_offsets else None
    return Motion(skeleton, rotations, torch.randn(frames, 3, generator=g), fps, offsets, name="random")


def assert_same_motion(read: Motion, original: Motion) -> None:
    assert read.skeleton.names == original.skeleton.names
    assert read.skeleton.parents == original.skeleton.parents
    assert read.skeleton.end_site_names == original.skeleton.end_site_names
    assert read.skeleton.end_site_parents == original.skeleton.end_site_parents
    np.testing.assert_allclose(read.skeleton.offsets[1:], original.skeleton.offsets[1:], atol=TOLERANCE)
    assert read.num_frames == original.num_frames
    assert read.fps == pytest.approx(original.fps, rel=1e-12)
    assert (read.joint_offsets is None) == (original.joint_offsets is None)
    assert (read.world_positions() - original.world_positions()).abs().max() < TOLERANCE
    if original.skeleton.end_site_parents:
        assert (read.end_site_positions() - original.end_site_positions()).abs().max() < TOLERANCE


@pytest.mark.parametrize("suffix", [".glb", ".gltf"])
def test_demo_clip_round_trip(demo, tmp_path, suffix):
    path = tmp_path / f"demo{suffix}"
    save_motion(demo, path)
    read = load_motion(path)
    assert_same_motion(read, demo)
    assert read.name == demo.name
    assert [p.name for p in tmp_path.iterdir()] == [path.name]  # no temporary file left


@pytest.mark.parametrize("suffix, mesh", [(".glb", True), (".gltf", False), (".glb.gz", True)])
def test_random_round_trip_with_joint_offsets(tmp_path, suffix, mesh):
    motion = random_motion(joint_offsets=True)
    path = tmp_path / f"random{suffix}"
    write_gltf(motion, path, mesh=mesh)
    assert_same_motion(read_gltf_animation(path), motion)


def test_single_joint_single_frame(tmp_path):
    motion = Motion(Skeleton(["root"], [-1], [[0.0, 1.0, 0.0]]), rot.quat_identity(1, 1), [[0.5, 1.0, 0.0]], 30.0)
    write_gltf(motion, tmp_path / "one.glb")
    assert_same_motion(read_gltf_animation(tmp_path / "one.glb"), motion)


# -- structure --------------------------------------------------------------------------------
def parse_glb(data: bytes) -> tuple[dict, bytes]:
    magic, version, length = struct.unpack("<4sII", data[:12])
    assert magic == b"glTF" and version == 2 and length == len(data)
    json_length, json_type = struct.unpack("<I4s", data[12:20])
    assert json_type == b"JSON" and json_length % 4 == 0
    document = json.loads(data[20:20 + json_length])
    bin_length, bin_type = struct.unpack("<I4s", data[20 + json_length:28 + json_length])
    assert bin_type == b"BIN\0" and 28 + json_length + bin_length == len(data)
    return document, data[28 + json_length:]


def accessor_values(document: dict, blob: bytes, index: int) -> np.ndarray:
    accessor = document["accessors"][index]
    view = document["bufferViews"][accessor["bufferView"]]
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}[accessor["type"]]
    dtype = {5126: np.float32, 5121: np.uint8, 5123: np.uint16}[accessor["componentType"]]
    start = view.get("byteOffset", 0) + accessor.get("byteOffset", 0)
    assert start % np.dtype(dtype).itemsize == 0
    assert start + accessor["count"] * width * np.dtype(dtype).itemsize <= view.get("byteOffset", 0) + view["byteLength"]
    assert view.get("byteOffset", 0) + view["byteLength"] <= len(blob)
    return np.frombuffer(blob, dtype=dtype, count=accessor["count"] * width, offset=start).reshape(accessor["count"], width)


def test_glb_structure(demo, tmp_path):
    path = tmp_path / "demo.glb"
    write_gltf(demo, path)
    document, blob = parse_glb(path.read_bytes())
    assert document["asset"]["version"] == "2.0"
    assert document["buffers"] == [{"byteLength": len(blob)}]
    joints, ends, frames = demo.skeleton.num_joints, len(demo.skeleton.end_site_parents), demo.num_frames

    nodes = document["nodes"]
    assert [n["name"] for n in nodes[:joints + ends]] == list(demo.skeleton.names + demo.skeleton.end_site_names)
    assert all("rotation" not in n and "scale" not in n for n in nodes)
    skin = document["skins"][0]
    assert skin["joints"] == list(range(joints + ends)) and skin["skeleton"] == 0
    ibm = accessor_values(document, blob, skin["inverseBindMatrices"]).reshape(-1, 4, 4)  # column-major
    rest = demo.skeleton.rest_points().numpy()
    np.testing.assert_allclose(ibm[:, 3, :3], -rest, atol=1e-6)
    assert document["scenes"][document["scene"]]["nodes"][0] == 0

    mesh_node = next(n for n in nodes if "mesh" in n)  # skinned stick figure at the scene root
    assert mesh_node["skin"] == 0 and "translation" not in mesh_node
    primitive = document["meshes"][mesh_node["mesh"]]["primitives"][0]
    position = document["accessors"][primitive["attributes"]["POSITION"]]
    values = accessor_values(document, blob, primitive["attributes"]["POSITION"])
    assert position["min"] == values.min(0).tolist() and position["max"] == values.max(0).tolist()
    assert accessor_values(document, blob, primitive["attributes"]["JOINTS_0"]).max() < joints
    np.testing.assert_allclose(accessor_values(document, blob, primitive["attributes"]["WEIGHTS_0"]).sum(1), 1.0)
    assert accessor_values(document, blob, primitive["indices"]).max() < position["count"]

    animation, = document["animations"]
    assert animation["extras"]["fps"] == demo.fps
    targets = {(c["target"]["node"], c["target"]["path"]) for c in animation["channels"]}
    assert targets == {(j, "rotation") for j in range(joints)} | {(0, "translation")}
    inputs = {animation["samplers"][c["sampler"]]["input"] for c in animation["channels"]}
    assert len(inputs) == 1
    time = document["accessors"][inputs.pop()]
    times = accessor_values(document, blob, animation["samplers"][0]["input"])[:, 0]
    assert time["count"] == frames and time["componentType"] == 5126
    assert time["min"] == [0.0] and time["max"] == [float(np.float32((frames - 1) / demo.fps))]
    np.testing.assert_allclose(times, np.arange(frames) / demo.fps, atol=1e-6)
    for channel in animation["channels"]:
        sampler = animation["samplers"][channel["sampler"]]
        assert sampler["interpolation"] == "LINEAR"
        output = accessor_values(document, blob, sampler["output"])
        assert len(output) == frames
        if channel["target"]["path"] == "rotation":
            np.testing.assert_allclose(np.linalg.norm(output, axis=1), 1.0, atol=1e-6)
            assert (np.sum(output[1:] * output[:-1], axis=1) >= 0).all()  # sign-continuous
        else:
            np.testing.assert_allclose(output, demo.root_positions.numpy(), atol=1e-7)


def test_gltf_is_self_contained_json(tmp_path):
    motion = random_motion()
    path = tmp_path / "random.gltf"
    write_gltf(motion, path)
    document = json.loads(path.read_text())
    buffer, = document["buffers"]
    prefix = "data:application/octet-stream;base64,"
    assert buffer["uri"].startswith(prefix)
    assert len(base64.b64decode(buffer["uri"][len(prefix):])) == buffer["byteLength"]


# -- files made elsewhere -----------------------------------------------------------------
def test_transforms_above_the_root_and_resampling(tmp_path):
    """A parent 'Armature' node with a rotation and a uniform scale (as Z-up exporters write) is
    folded into the root; fps= resamples."""
    motion = random_motion(frames=9, fps=30.0, seed=1)
    write_gltf(motion, tmp_path / "plain.gltf")
    document = json.loads((tmp_path / "plain.gltf").read_text())
    quarter_x = [-math.sin(math.pi / 4), 0.0, 0.0, math.cos(math.pi / 4)]  # xyzw, -90 degrees about x
    document["nodes"].append({"name": "Armature", "children": [0], "rotation": quarter_x,
                              "scale": [0.5, 0.5, 0.5], "translation": [1.0, 2.0, 3.0]})
    scene = document["scenes"][0]
    scene["nodes"] = [len(document["nodes"]) - 1] + scene["nodes"][1:]
    (tmp_path / "wrapped.gltf").write_text(json.dumps(document))

    read = read_gltf_animation(tmp_path / "wrapped.gltf")
    q = rot.quat_identity()
    q[:] = torch.tensor([math.cos(math.pi / 4), -math.sin(math.pi / 4), 0.0, 0.0])
    expected = rot.quat_apply(q, motion.world_positions()) * 0.5 + torch.tensor([1.0, 2.0, 3.0])
    assert read.skeleton.names == motion.skeleton.names
    assert (read.world_positions() - expected).abs().max() < TOLERANCE

    half = read_gltf_animation(tmp_path / "wrapped.gltf", fps=15.0)
    assert half.num_frames == 5 and half.fps == 15.0
    assert (half.world_positions() - expected[::2]).abs().max() < TOLERANCE
    double = read_gltf_animation(tmp_path / "plain.gltf", fps=60.0)
    assert double.num_frames == 17
    assert (double.world_positions()[::2] - motion.world_positions()).abs().max() < TOLERANCE


# -- errors -----------------------------------------------------------------------------------
def test_errors(tmp_path):
    with pytest.raises(ValueError, match=".glb or .gltf"):
        write_gltf(random_motion(), tmp_path / "x.fbx")
    with pytest.raises(MotionFileError, match="writable: .bvh, .glb, .gltf"):
        save_motion(random_motion(), tmp_path / "x.fbx")
    (tmp_path / "garbage.glb").write_bytes(b"glTF\x02\x00\x00\x00\xff\xff\x00\x00junk")
    with pytest.raises(MotionFileError, match="garbage.glb"):
        read_gltf_animation(tmp_path / "garbage.glb")
    (tmp_path / "text.gltf").write_text("{not json")
    with pytest.raises(MotionFileError, match="not a readable glTF"):
        read_gltf_animation(tmp_path / "text.gltf")
    (tmp_path / "static.gltf").write_text(json.dumps({"asset": {"version": "2.0"}, "nodes": [{"name": "a"}]}))
    with pytest.raises(MotionFileError, match="no animation"):
        load_motion(tmp_path / "static.gltf")
    with pytest.raises(MotionFileError, match="cannot read"):
        read_gltf_animation(tmp_path / "missing.glb")


# -- the Khronos validator, when it is at hand ------------------------------------------------
VALIDATOR_JS = """
const v = require('gltf-validator'); const fs = require('fs');
v.validateBytes(new Uint8Array(fs.readFileSync(process.argv[1])))
  .then(r => console.log(JSON.stringify(r.issues)));
"""


def test_khronos_validator(demo, tmp_path):
    """Runs only when HUMOTION_GLTF_VALIDATOR names a folder where `npm install gltf-validator` ran."""
    folder = os.environ.get("HUMOTION_GLTF_VALIDATOR")
    if not folder or shutil.which("node") is None or not os.path.isdir(os.path.join(folder, "node_modules", "gltf-validator")):
        pytest.skip("set HUMOTION_GLTF_VALIDATOR to a folder holding node_modules/gltf-validator (and install node)")
    for name, motion in (("demo.glb", demo), ("random.gltf", random_motion(joint_offsets=True))):
        write_gltf(motion, tmp_path / name)
        result = subprocess.run(["node", "-e", VALIDATOR_JS, str(tmp_path / name)], cwd=folder,
                                capture_output=True, text=True, timeout=60, check=True)
        issues = json.loads(result.stdout)
        assert (issues["numErrors"], issues["numWarnings"], issues["numInfos"]) == (0, 0, 0), issues["messages"]

"""`humotion body`: bodies made as asked, a glTF skin that reproduces the body model, motions
on the body (real CMU clips), the OBJ, the viewer's mesh mode and clear errors.

The glTF files are read back with pygltflib and skinned here, independently of the writer:
node transforms of the animation at a frame, the file's inverse bind matrices, JOINTS/WEIGHTS
and morph targets, linear blend skinning as the glTF specification defines it."""

import json
import os
import shutil
import subprocess

import numpy as np
import pygltflib
import pytest
import torch
from click.testing import CliRunner

from humotion import rotations as rot
from humotion.body import model as model_module
from humotion.body.export import body_measurements, pose_motion, rest_body
from humotion.body.model import load_body_model, shipped_weights
from humotion.body.skin_export import four_joint_weights, moving_ancestors
from humotion.body.skinning import linear_blend_skinning
from humotion.canonical import canonical_skeleton
from humotion.capture.template import typical_bmi, typical_height
from humotion.cli import main
from humotion.io import load_motion, save_motion
from humotion.io.gltf import SkinnedMesh, skin_influences, write_gltf
from humotion.motion import Motion

pytestmark = pytest.mark.skipif(not shipped_weights("low").exists(), reason="no shipped body weights")

WALK = "cmu_mocgui_s02/02_01.amc"  # CMU subject 02 walking, 343 frames at 120 fps


def run(*args):
    return CliRunner().invoke(main, ["body", *[str(a) for a in args]])


def run_ok(*args):
    result = run(*args)
    assert result.exit_code == 0, result.output + repr(result.exception)
    return result


@pytest.fixture(scope="module")
def low():
    torch.set_num_threads(1)
    return load_body_model("low")


# -- reading a glTF file back and skinning it ------------------------------------------------

class GltfFile:
    """A .glb file read with pygltflib: accessors as numpy arrays, the skin evaluated at a frame."""

    def __init__(self, path):
        self.gltf = pygltflib.GLTF2.load(str(path))
        self.blob = self.gltf.binary_blob()
        self.mesh_node = next(i for i, n in enumerate(self.gltf.nodes) if n.mesh is not None)
        self.primitive = self.gltf.meshes[self.gltf.nodes[self.mesh_node].mesh].primitives[0]
        self.skin = self.gltf.skins[0]
        self.animation = self.gltf.animations[0]

    def accessor(self, index: int) -> np.ndarray:
        a = self.gltf.accessors[index]
        view = self.gltf.bufferViews[a.bufferView]
        width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}[a.type]
        dtype = {pygltflib.FLOAT: np.float32, pygltflib.UNSIGNED_BYTE: np.uint8,
                 pygltflib.UNSIGNED_SHORT: np.uint16, pygltflib.UNSIGNED_INT: np.uint32}[a.componentType]
        assert view.byteStride is None
        start = (view.byteOffset or 0) + (a.byteOffset or 0)
        assert start + a.count * width * np.dtype(dtype).itemsize <= (view.byteOffset or 0) + view.byteLength
        return np.frombuffer(self.blob, dtype=dtype, count=a.count * width, offset=start).reshape(a.count, width)

    def attribute(self, name: str) -> np.ndarray:
        return self.accessor(getattr(self.primitive.attributes, name))

    def influences(self) -> tuple[np.ndarray, np.ndarray]:
        """Joints (V, K) and weights (V, K) of all JOINTS_n / WEIGHTS_n sets."""
        sets = [k for k in range(4) if getattr(self.primitive.attributes, f"JOINTS_{k}", None) is not None]
        return (np.concatenate([self.attribute(f"JOINTS_{k}") for k in sets], axis=1).astype(np.int64),
                np.concatenate([self.attribute(f"WEIGHTS_{k}") for k in sets], axis=1).astype(np.float64))

    def channel(self, node: int, path: str) -> np.ndarray | None:
        for c in self.animation.channels:
            if c.target.node == node and c.target.path == path:
                return self.accessor(self.animation.samplers[c.sampler].output).astype(np.float64)
        return None

    def world_matrices(self, frame: int) -> np.ndarray:
        """(N, 4, 4) world transforms of all nodes at an animation key."""
        nodes = self.gltf.nodes
        local = np.tile(np.eye(4), (len(nodes), 1, 1))
        for i, node in enumerate(nodes):
            t = self.channel(i, "translation")
            q = self.channel(i, "rotation")
            translation = t[frame] if t is not None else (node.translation or [0.0, 0.0, 0.0])
            xyzw = q[frame] if q is not None else (node.rotation or [0.0, 0.0, 0.0, 1.0])
            local[i, :3, :3] = rot.quat_to_matrix(torch.tensor(np.roll(xyzw, 1))).numpy()
            local[i, :3, 3] = translation
        parent = {c: i for i, n in enumerate(nodes) for c in n.children or []}
        world = np.empty_like(local)
        for i in range(len(nodes)):  # parents come first in these files
            world[i] = world[parent[i]] @ local[i] if i in parent else local[i]
        return world

    def skinned(self, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """(posed vertices (V, 3), skin joints' world positions (J, 3)) at an animation key:
        morph targets blended, then linear blend skinning with the inverse bind matrices."""
        base = self.attribute("POSITION").astype(np.float64)
        weights = self.channel(self.mesh_node, "weights")
        for m, target in enumerate(self.primitive.targets or []):
            base = base + weights.reshape(-1, len(self.primitive.targets))[frame, m] * self.accessor(target["POSITION"])  # pygltflib reads targets as dicts
        world = self.world_matrices(frame)[self.skin.joints]
        inverse_bind = self.accessor(self.skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)
        matrices = world @ inverse_bind  # (J, 4, 4)
        joints, w = self.influences()
        blended = np.einsum("vk,vkij->vij", w, matrices[joints])
        vertices = np.einsum("vij,vj->vi", blended[:, :3, :3], base) + blended[:, :3, 3]
        return vertices, world[:, :3, 3]


def model_vertices(body, rotations, root, frames) -> np.ndarray:
    """(K, V, 3) the body model's own vertices at frames: its forward pass on the shape latent,
    in its own frame, lifted to the export frame."""
    with torch.no_grad():
        out = body.model(shape=body.shape, pose=rotations[frames], translation=root[frames] - body.joints[0])
    return out.vertices.numpy() + np.array([0.0, body.lift, 0.0])


# -- the body made as asked --------------------------------------------------------------------

def test_height_and_weight_as_asked_glb_and_obj(low, tmp_path):
    run_ok("-o", tmp_path / "alice", "--height", 1.68, "--weight", 60, "--obj")
    glb = GltfFile(tmp_path / "alice.glb")
    vertices = glb.attribute("POSITION")
    assert vertices[:, 1].max() - vertices[:, 1].min() == pytest.approx(1.68, abs=0.01)
    assert vertices[:, 1].min() == pytest.approx(0.0, abs=1e-6)  # soles on the floor
    facts = glb.gltf.meshes[0].extras["humotion_body"]
    assert facts["height_m"] == pytest.approx(1.68, abs=0.005) and facts["weight_kg"] == pytest.approx(60, abs=0.5)
    # the OBJ: the same rest mesh (6 decimals), its triangles and unit normals
    lines = (tmp_path / "alice.obj").read_text().splitlines()
    v = np.array([l.split()[1:] for l in lines if l.startswith("v ")], dtype=float)
    vn = np.array([l.split()[1:] for l in lines if l.startswith("vn ")], dtype=float)
    f = np.array([[c.split("//")[0] for c in l.split()[1:]] for l in lines if l.startswith("f ")], dtype=int) - 1
    np.testing.assert_allclose(v, vertices, atol=1e-6)
    np.testing.assert_array_equal(f, low.faces.numpy())
    np.testing.assert_allclose(np.linalg.norm(vn, axis=1), 1.0, atol=1e-5)
    measured = low.measure(torch.tensor(v, dtype=torch.float32)[None])
    assert float(measured["weight"][0]) == pytest.approx(60.0, abs=0.5)
    assert np.dot(vn[v[:, 1].argmax()], [0, 1, 0]) > 0.9  # the top of the head faces up: normals point out


def test_sex_and_age_give_typical_height_and_weight(tmp_path):
    # CDC 2000 medians: an 8-year-old girl 1.27 m and 25.6 kg; men keep the 20-year 1.77 m and 70.6 kg
    assert body_measurements(None, None, "female", 8) == pytest.approx((1.27, 25.6), abs=1e-9)
    assert body_measurements(None, None, "male", 40) == pytest.approx((1.77, 70.6), abs=1e-9)
    assert body_measurements(None, None, "male", 12.5) == pytest.approx((1.525, 43.05), abs=0.01)  # interpolated
    assert body_measurements(1.9, None, "male")[1] == pytest.approx(typical_bmi("male") * 1.9 ** 2)  # typical build
    assert body_measurements(None, 90.0, "female") == (typical_height("female"), 90.0)
    assert typical_bmi() == pytest.approx((typical_bmi("male") + typical_bmi("female")) / 2)
    for age in (1.0, -3.0, float("nan"), 130.0):   # checked even when height and weight are given
        with pytest.raises(ValueError, match="age must be"):
            body_measurements(1.0, 20.0, None, age)
    run_ok("-o", tmp_path / "kid.glb", "--sex", "female", "--age", 8)
    vertices = GltfFile(tmp_path / "kid.glb").attribute("POSITION")
    assert vertices[:, 1].max() - vertices[:, 1].min() == pytest.approx(typical_height("female", 8), abs=0.01)


def test_latent_and_sample_choose_the_shape(low, tmp_path):
    latent = low.sample_shapes(1, torch.Generator().manual_seed(5)).numpy()
    np.save(tmp_path / "shape.npy", latent[0])
    run_ok("-o", tmp_path / "from_latent.glb", "--latent", tmp_path / "shape.npy")
    run_ok("-o", tmp_path / "sampled.glb", "--sample", 5)
    a, b = (GltfFile(tmp_path / name) for name in ("from_latent.glb", "sampled.glb"))
    np.testing.assert_allclose(a.attribute("POSITION"), b.attribute("POSITION"))  # same seed, same body
    np.testing.assert_allclose(a.gltf.meshes[0].extras["humotion_body"]["shape_latent"], latent[0], atol=1e-6)
    with torch.no_grad():
        rest = low(shape=torch.tensor(latent)).rest_vertices[0].numpy()
    np.testing.assert_allclose(a.attribute("POSITION"), rest - [0, rest[:, 1].min(), 0], atol=1e-5)


# -- the glTF file ---------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def walk(mocap, low, tmp_path_factory):
    """A walking clip (at 30 fps) on a 1.85 m, 80 kg body, written with 4 and with 8 influences;
    the body and its pose as the command's functions make them."""
    folder = tmp_path_factory.mktemp("walk")
    files = {}
    for count in (4, 8):
        files[count] = folder / f"walk{count}.glb"
        run_ok("-o", files[count], "--height", 1.85, "--weight", 80, "--motion", mocap / WALK, "--fps", 30,
               "--influences", count, "--obj")
    body = rest_body(low, low.shape_from_measurements(1.85, 80.0))
    rotations, root = pose_motion(body, load_motion(mocap / WALK).resample(30))
    return files, body, rotations, root


def test_gltf_structure_accessors_and_skin(walk):
    files, body, rotations, _ = walk
    glb = GltfFile(files[4])
    V, J, F = body.model.num_vertices, body.model.num_joints, len(rotations)
    position = glb.gltf.accessors[glb.primitive.attributes.POSITION]
    values = glb.attribute("POSITION")
    assert position.count == V and position.min == values.min(0).tolist() and position.max == values.max(0).tolist()
    assert len(glb.accessor(glb.primitive.indices)) == 3 * len(body.model.faces)
    normals = glb.attribute("NORMAL")
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)
    joints, weights = glb.influences()
    assert joints.shape == (V, 4) and getattr(glb.primitive.attributes, "JOINTS_1", None) is None
    assert joints.min() >= 0 and joints.max() < J == len(glb.skin.joints)
    np.testing.assert_allclose(weights.sum(1), 1.0, atol=1e-6)
    assert (weights >= 0).all() and (np.diff(weights, axis=1) <= 0).all()  # heaviest first
    assert (joints[weights == 0] == 0).all()  # unused influences point at joint 0
    # each kept joint moves (no frozen joints: their weight is on their moving ancestors) and skins the
    # vertex in the model, itself or through frozen joints below it
    ancestors = moving_ancestors(body.model.parents, body.model.limits.frozen).numpy()
    model_weights = body.model.skinning_weights().numpy()
    skinned = np.zeros((V, J), dtype=bool)
    for j in range(J):
        skinned[:, ancestors[j]] |= model_weights[:, j] > 0
    assert np.take_along_axis(skinned, joints, axis=1)[weights > 0].all()
    # rest-pose bind matrices: a translation by minus each joint's rest position
    ibm = glb.accessor(glb.skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)
    np.testing.assert_allclose(ibm[:, :3, :3], np.broadcast_to(np.eye(3), (J, 3, 3)), atol=1e-7)
    np.testing.assert_allclose(ibm[:, :3, 3], -body.joints.numpy(), atol=1e-6)
    assert [glb.gltf.nodes[j].name for j in glb.skin.joints] == body.model.joint_names
    # animation: every joint's rotation, the root's translation, the correctives' weights; F keys
    targets = {(c.target.node, c.target.path) for c in glb.animation.channels}
    assert targets == {(j, "rotation") for j in range(J)} | {(0, "translation"), (glb.mesh_node, "weights")}
    times = glb.accessor(glb.animation.samplers[0].input)[:, 0]
    assert len(times) == F and times[-1] == pytest.approx((F - 1) / 30.0)
    assert len(glb.primitive.targets) == 32 == len(glb.gltf.meshes[0].extras["targetNames"])
    assert glb.channel(glb.mesh_node, "weights").size == F * 32
    for target in glb.primitive.targets:
        a = glb.gltf.accessors[target["POSITION"]]
        assert a.min is not None and a.max is not None
    material = glb.gltf.materials[glb.primitive.material].pbrMetallicRoughness
    assert material.metallicFactor == 0.0


def test_gltf_skin_reproduces_the_body_model(walk):
    """The file's skin (with the correctives as morph targets) against the model's own posed mesh:
    8 influences to well under a millimetre; 4 (the default: weights fitted to skin like the
    model's) within 6 mm at every vertex and 1.5 mm at 99% of them, on every frame of the walk
    (the model's heaviest 4 weights renormalised were 18 mm and 5.7 mm off)."""
    files, body, rotations, root = walk
    frames = [0, len(rotations) // 2, len(rotations) - 1]
    expected = model_vertices(body, rotations, root, frames)
    glb8, glb4 = GltfFile(files[8]), GltfFile(files[4])
    for k, frame in enumerate(frames):
        vertices, joints = glb8.skinned(frame)
        assert np.abs(vertices - expected[k]).max() < 1e-3
        with torch.no_grad():
            model_joints = body.model(shape=body.shape, pose=rotations[frame],
                                      translation=root[frame] - body.joints[0]).joints[0].numpy()
        np.testing.assert_allclose(joints, model_joints + [0, body.lift, 0], atol=1e-4)
        error = np.linalg.norm(glb4.skinned(frame)[0] - expected[k], axis=1)
        assert error.max() < 6e-3 and np.quantile(error, 0.99) < 1.5e-3
    # every frame: the model's bone transforms and correctives with the file's 4 weights (what
    # the file computes, as the frames above check) against the model's vertices
    ids, w = glb4.influences()
    dense = torch.zeros(body.model.num_vertices, body.model.num_joints, dtype=torch.float64)
    dense.scatter_add_(1, torch.tensor(ids), torch.tensor(w))
    with torch.no_grad():
        out = body.model(shape=body.shape, pose=rotations, translation=root - body.joints[0])
        surface = out.rest_vertices + body.model.corrective_offsets(rotations, out.rest_vertices)
        four = linear_blend_skinning(surface.double(), dense, out.world_rotations.double(), out.translations.double())
    error = (four - out.vertices.double()).norm(dim=-1)
    assert error.max() < 6e-3 and error.quantile(0.99) < 1.5e-3 and error.median() < 1e-5


def test_four_joint_weights(low):
    """At most 4 joints per vertex, non-negative, summing to 1; a frozen joint's weight goes to
    its moving ancestor, so vertices the model skins with 4 moving joints or fewer keep their
    weights, merged."""
    body = rest_body(low, low.shape_from_measurements(1.7, 65.0))
    weights = low.skinning_weights()
    fitted = four_joint_weights(weights, body.vertices, body.joints, low.parents, low.limits)
    assert fitted.shape == weights.shape and (fitted >= 0).all() and ((fitted > 0).sum(1) <= 4).all()
    torch.testing.assert_close(fitted.sum(1), torch.ones(len(fitted), dtype=torch.float64))
    merged = torch.zeros_like(fitted).index_add_(1, moving_ancestors(low.parents, low.limits.frozen), weights.double())
    assert (merged[:, low.limits.frozen] == 0).all()
    few = (merged > 0).sum(1) <= 4
    assert few.sum() > len(few) / 2
    torch.testing.assert_close(fitted[few], merged[few], rtol=0, atol=1e-5)


def test_motion_on_the_body_walks_on_the_floor(walk, mocap, tmp_path):
    files, body, rotations, root = walk
    glb = GltfFile(files[4])
    # the OBJ is the first frame of the motion
    lines = (files[4].with_suffix(".obj")).read_text().splitlines()
    v = np.array([l.split()[1:] for l in lines if l.startswith("v ")], dtype=float)
    np.testing.assert_allclose(v, model_vertices(body, rotations, root, [0])[0], atol=2e-6)
    # feet on the floor: the lowest point of the body within 3 cm of y = 0 on most frames
    lowest = np.array([glb.skinned(frame)[0][:, 1].min() for frame in range(0, len(rotations), 10)])
    assert np.abs(np.median(lowest)) < 0.03 and lowest.min() > -0.05
    # the walk covers ground in proportion to the body's legs: a 1.2 m child walks less far
    run_ok("-o", tmp_path / "child.glb", "--height", 1.2, "--weight", 24, "--motion", mocap / WALK, "--fps", 30)
    child = GltfFile(tmp_path / "child.glb")
    adult_path, child_path = (np.linalg.norm(np.diff(g.channel(0, "translation")[:, [0, 2]], axis=0), axis=1).sum()
                              for g in (glb, child))
    assert adult_path > 1.0 and child_path / adult_path == pytest.approx(0.64, abs=0.05)
    # humotion reads the file back: the rig's 76 joints moving as the body's joints
    read = load_motion(files[4])
    assert read.skeleton.num_joints == 76 and read.num_frames == len(rotations) and read.fps == 30
    _, joints = glb.skinned(5)
    np.testing.assert_allclose(read.world_positions()[5].numpy(), joints, atol=1e-4)


def test_t_pose_gives_horizontal_arms(tmp_path):
    """The canonical T pose (identity rotations) on the body: arms out sideways, level."""
    skeleton = canonical_skeleton()
    tpose = Motion(skeleton, rot.quat_identity(2, skeleton.num_joints), skeleton.offsets[0].expand(2, 3)
                   + torch.tensor([0.0, 1.0, 0.0]), 30.0, name="tpose")
    save_motion(tpose, tmp_path / "tpose.glb")  # glTF keeps the end sites' names, which to_canonical needs
    run_ok("-o", tmp_path / "t.glb", "--height", 1.75, "--weight", 70, "--motion", tmp_path / "tpose.glb")
    glb = GltfFile(tmp_path / "t.glb")
    vertices, joints = glb.skinned(0)
    names = [glb.gltf.nodes[j].name for j in glb.skin.joints]
    for side, sign in (("L", 1.0), ("R", -1.0)):
        shoulder, wrist = joints[names.index(f"upperarm01.{side}")], joints[names.index(f"wrist.{side}")]
        arm = wrist - shoulder
        assert np.degrees(np.arcsin(abs(arm[1]) / np.linalg.norm(arm))) < 5.0  # level
        assert sign * arm[0] > 0.9 * np.linalg.norm(arm)  # sideways: left arm to +X (the body faces +Z)
    # the hands' vertices are the body's outermost, at shoulder height
    hand = vertices[np.abs(vertices[:, 0]).argmax()]
    assert abs(hand[1] - joints[names.index("upperarm01.L"), 1]) < 0.1
    assert np.ptp(vertices[:, 0]) > 1.5  # arm span of a 1.75 m body
    assert vertices[:, 1].min() == pytest.approx(0.0, abs=0.03)


def test_skin_influences_and_mesh_checks(tmp_path):
    weights = np.array([[0.1, 0.4, 0.05, 0.3, 0.15], [0.0, 0.0, 1.0, 0.0, 0.0]])
    joints, kept = skin_influences(weights, 4)
    np.testing.assert_array_equal(joints, [[1, 3, 4, 0], [2, 0, 0, 0]])  # heaviest first; unused: joint 0
    np.testing.assert_allclose(kept[0], np.array([0.4, 0.3, 0.15, 0.1]) / 0.95, rtol=1e-6)
    assert kept.dtype == np.float32 and (kept.sum(1, dtype=np.float32) == 1).all()
    joints, kept = skin_influences(weights, 8)  # fewer joints than slots: padded
    assert joints.shape == (2, 8) and kept[0, 5:].sum() == 0
    skeleton = canonical_skeleton()
    motion = Motion(skeleton, rot.quat_identity(3, skeleton.num_joints), torch.zeros(3, 3), 30.0)
    triangle = np.eye(3), np.array([[0, 1, 2]])
    one_hot = np.eye(skeleton.num_joints + len(skeleton.end_site_parents))[:3]
    with pytest.raises(ValueError, match="weights over 22 joints, the skin has 27"):
        write_gltf(motion, tmp_path / "x.glb", mesh=SkinnedMesh(*triangle, np.eye(22)[:3]))
    with pytest.raises(ValueError, match="morph weights for 2 frames, the motion has 3"):
        write_gltf(motion, tmp_path / "x.glb", mesh=SkinnedMesh(*triangle, one_hot, morph_targets=np.zeros((1, 3, 3)),
                                                                morph_weights=np.zeros((2, 1))))
    with pytest.raises(ValueError, match="rows summing to 1"):
        SkinnedMesh(*triangle, one_hot * 0.5)
    with pytest.raises(ValueError, match="normals must be"):
        SkinnedMesh(*triangle, one_hot, normals=np.zeros((5, 3)))
    with pytest.raises(ValueError, match="face indices"):
        SkinnedMesh(np.eye(3), np.array([[0, 1, 3]]), one_hot)
    assert not list(tmp_path.iterdir())


# -- bad input ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("args, words", [
    (["--height", 2.5], ["--height", "height=2.5 m", "outside the model's range"]),
    (["--height", 1.7, "--weight", 300], ["--height/--weight", "weight=300 kg"]),
    (["--height", 1.7, "--weight", 20], ["BMI of 6.9"]),
    (["--weight", "nan"], ["--weight", "NaN"]),
    (["--age", 1], ["--age", "at least 2 years"]),
    (["--age", 130], ["--age", "at most 120"]),
    (["--sex", "female", "--age", 2], ["--sex/--age", "height=0.85 m", "outside the model's range", "typical of --sex/--age"]),
    (["--sex", "other"], ["--sex", "'other' is not one of 'female', 'male'"]),
    (["--sample", 1, "--height", 1.8], ["--sample and --height", "give one"]),
    (["--motion", "missing.bvh"], ["--motion", "does not exist"]),
])
def test_bad_input_names_the_parameter(tmp_path, args, words):
    result = run("-o", tmp_path / "x", *args)
    assert result.exit_code == 2
    for word in words:
        assert word in result.output
    assert not list(tmp_path.glob("x*"))


def test_bad_files(low, tmp_path, mocap, monkeypatch):
    motion = load_motion(mocap / "cmu_fairmotion/01_01.bvh")[:5]
    save_motion(motion, tmp_path / "short.bvh")
    lines = (tmp_path / "short.bvh").read_text().splitlines()
    lines[-2] = lines[-2].replace(lines[-2].split()[4], "nan", 1)
    (tmp_path / "nan.bvh").write_text("\n".join(lines) + "\n")
    result = run("-o", tmp_path / "x", "--motion", tmp_path / "nan.bvh")
    assert result.exit_code == 2 and "--motion" in result.output and "NaN" in result.output
    np.save(tmp_path / "short.npy", np.zeros(5))
    result = run("-o", tmp_path / "x", "--latent", tmp_path / "short.npy")
    assert result.exit_code == 2 and "--latent" in result.output and "16 numbers" in result.output
    result = run("-o", tmp_path / "x", "--motion", mocap / "cmu_fairmotion/01.asf")
    assert result.exit_code == 2 and "unknown motion format '.asf'" in result.output
    monkeypatch.setattr(model_module, "ASSETS", tmp_path / "nowhere")
    result = run("-o", tmp_path / "x", "--resolution", "full")
    assert result.exit_code == 2 and "--resolution" in result.output and "no body model weights" in result.output
    assert not list(tmp_path.glob("x*"))


# -- the viewer's mesh mode ----------------------------------------------------------------------

def test_viewer_mesh_mode_follows_the_frames(walk):
    from humotion.body.export import body_gltf, posed_vertices
    from humotion.viewer import MotionViewer

    _, body, rotations, root = walk
    motion, _ = body_gltf(body, rotations[:6], root[:6], 30.0, "walk")
    vertices = posed_vertices(body, rotations[:6], root[:6], progress=False).numpy()
    with pytest.raises(ValueError, match="mesh 0 must be vertices"):
        MotionViewer([motion], port=0, meshes=[(vertices[:3], body.model.faces.numpy())])
    viewer = MotionViewer([motion], port=0, meshes=[(vertices, body.model.faces.numpy())])
    try:
        viewer.set_frame(4)
        handle = viewer.server.scene.get_handle_by_name("/motions/0/mesh")
        np.testing.assert_allclose(handle.vertices, vertices[4] + viewer.offsets[0], atol=1e-6)
    finally:
        viewer.stop()


# -- the Khronos validator, when it is at hand ------------------------------------------------------

def test_khronos_validator(walk):
    """Runs only when HUMOTION_GLTF_VALIDATOR names a folder where `npm install gltf-validator` ran."""
    folder = os.environ.get("HUMOTION_GLTF_VALIDATOR")
    if not folder or shutil.which("node") is None or not os.path.isdir(os.path.join(folder, "node_modules", "gltf-validator")):
        pytest.skip("set HUMOTION_GLTF_VALIDATOR to a folder holding node_modules/gltf-validator (and install node)")
    from test_gltf import VALIDATOR_JS

    for path in walk[0].values():
        result = subprocess.run(["node", "-e", VALIDATOR_JS, str(path)], cwd=folder, capture_output=True, text=True,
                                timeout=60, check=True)
        issues = json.loads(result.stdout)
        assert (issues["numErrors"], issues["numWarnings"], issues["numInfos"]) == (0, 0, 0), issues["messages"]

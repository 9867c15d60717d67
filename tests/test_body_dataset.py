"""Body-model training data (humotion.body.dataset, .posing, .skinning, .files): the pure parts
always, generation with Anny when it is installed (pip install 'humotion[anny]')."""

import json
import os

import numpy as np
import pytest
import torch

from humotion import rotations as rot
from humotion.body import dataset as D
from humotion.body import files as F
from humotion.body import posing as P
from humotion.body import skinning as S
from humotion.canonical import JOINTS, canonical_skeleton
from humotion.skeleton import forward_kinematics


def random_rotations(rng, shape, max_angle=1.0):
    axis = rng.normal(size=shape + (3,))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    return axis_angle(axis, rng.uniform(0, max_angle, size=shape))


def axis_angle(axis, angle):
    """(..., 3, 3) rotations by angle (...) radians about unit axis (..., 3)."""
    return rot.convert(torch.as_tensor(axis * np.asarray(angle)[..., None]), "rotvec", "matrix").numpy()


# -- splits ---------------------------------------------------------------------------------------

def test_plan_splits_holds_out_shapes_and_poses():
    plan = D.plan_splits(20, 8, np.random.default_rng(0))
    assert plan.shape_held_out.sum() == 2
    assert len(plan.mesh_shape) == 160 and np.array_equal(plan.mesh_shape, np.repeat(np.arange(20), 8))
    # the last pose of every shape comes from held-out subjects (K // 8 = 1)
    assert np.array_equal(plan.mesh_pose_held_out.reshape(20, 8).sum(1), np.ones(20))
    for k, name in enumerate(F.SPLITS):
        rows = plan.mesh_split == k
        assert np.all(plan.shape_held_out[plan.mesh_shape[rows]] == (name in ("test_shapes", "test_both")))
        assert np.all(plan.mesh_pose_held_out[rows] == (name in ("test_poses", "test_both")))
    counts = [int((plan.mesh_split == k).sum()) for k in range(4)]
    assert counts == [18 * 7, 2 * 7, 18, 2]
    again = D.plan_splits(20, 8, np.random.default_rng(0))
    assert np.array_equal(again.shape_held_out, plan.shape_held_out)


def test_plan_splits_small_runs_still_have_every_split():
    plan = D.plan_splits(4, 2, np.random.default_rng(1))
    assert sorted(set(plan.mesh_split.tolist())) == [0, 1, 2, 3]
    assert D.plan_splits(1, 1, np.random.default_rng(0)).mesh_split.tolist() == [0]
    with pytest.raises(ValueError):
        D.plan_splits(4, 2, np.random.default_rng(0), held_out_poses=3)


# -- kinematics and skinning ----------------------------------------------------------------------

def test_skinning_transforms_follow_the_pose_convention():
    rng = np.random.default_rng(0)
    parents = [-1, 0, 1, 1, 3]
    rest = rng.normal(size=(5, 3))
    local = random_rotations(rng, (3, 5))
    translation = rng.normal(size=(3, 3))
    A, t, joints = S.skinning_transforms(rest, parents, local, translation)
    # A_j = A_parent L_j; p_j = p_parent + A_parent (rest_j - rest_parent); p_0 = rest_0 + translation
    assert np.allclose(A[:, 3], A[:, 1] @ local[:, 3])
    assert np.allclose(joints[:, 4], joints[:, 3] + np.einsum("kij,j->ki", A[:, 3], rest[4] - rest[3]))
    assert np.allclose(joints[:, 0], rest[0] + translation)
    # each bone's transform maps its rest joint onto its posed joint
    assert np.allclose(np.einsum("kjab,jb->kja", A, rest) + t, joints)
    quats = rot.matrix_to_quat(torch.as_tensor(local)).numpy()
    assert np.allclose(S.skinning_transforms(rest, parents, quats, translation)[2], joints)


def test_linear_blend_skinning_identity_and_rigid_motion():
    rng = np.random.default_rng(1)
    parents = [-1, 0, 1]
    rest = rng.normal(size=(3, 3))
    vertices = rng.normal(size=(50, 3))
    weights = rng.uniform(size=(50, 3))
    weights /= weights.sum(1, keepdims=True)
    identity = np.broadcast_to(np.eye(3), (1, 3, 3, 3))
    A, t, _ = S.skinning_transforms(rest, parents, identity, np.zeros((1, 3)))
    assert np.allclose(S.linear_blend_skinning(vertices, weights, A, t)[0], vertices)
    # a root turn and a translation move every vertex rigidly
    local = identity.copy()
    local[0, 0] = random_rotations(rng, ())
    shift = np.array([[0.3, -0.2, 1.0]])
    A, t, _ = S.skinning_transforms(rest, parents, local, shift)
    expected = (vertices - rest[0]) @ local[0, 0].T + rest[0] + shift
    assert np.allclose(S.linear_blend_skinning(vertices, weights, A, t)[0], expected)


def test_blend_zones_are_the_vertices_on_both_sides_of_a_joint():
    names = ["root", "upperarm01.L", "lowerarm01.L", "wrist.L", "upperarm01.R", "lowerarm01.R", "wrist.R",
             "upperleg01.L", "lowerleg01.L", "upperleg01.R", "lowerleg01.R"]
    parents = [-1, 0, 1, 2, 0, 4, 5, 0, 7, 0, 9]
    weights = np.zeros((3, len(names)))
    weights[0, [1, 2]] = 0.5          # elbow blend
    weights[1, 2] = 1.0               # forearm only
    weights[2, [0, 7]] = 0.5          # hip blend
    zones = S.blend_zones(weights, names, parents)
    assert zones["elbows"].tolist() == [True, False, False]
    assert zones["shoulders"].tolist() == [False, False, False]
    assert zones["hips"].tolist() == [False, False, True]


# -- retargeting ------------------------------------------------------------------------------------

def a_pose_rig():
    """The canonical template as a rig with Anny's bone names, arms lowered 45 degrees (an A-pose)
    and a twist bone in each upper arm: a stand-in for Anny's rig without Anny."""
    template = canonical_skeleton()
    rest = dict(zip(JOINTS, template.rest_positions(torch.float64)))
    ends = dict(zip(template.end_site_names, template.rest_end_site_positions(torch.float64)))
    names, parents, points = [], [], {}

    def add(name, parent, position):
        names.append(name)
        parents.append(names.index(parent) if parent else -1)
        points[name] = position

    def lowered(p, side):  # turn arm points 45 degrees down about the shoulder (+-Z axis)
        shoulder = rest[f"{side}_shoulder"]
        turn = torch.from_numpy(axis_angle(np.array([0.0, 0.0, -1.0 if side == "left" else 1.0]), np.array(np.pi / 4)))
        return shoulder + turn @ (p - shoulder)

    for canon, bone in P.CANONICAL_TO_RIG.items():
        side = "left" if canon.startswith("left") else "right" if canon.startswith("right") else None
        position = rest[canon]
        if side and canon.split("_")[1] in ("elbow", "wrist"):
            position = lowered(position, side)
        parent = {"pelvis": None, "spine1": "root", "spine2": "spine04", "spine3": "spine02", "neck": "spine01",
                  "head": "neck01"}.get(canon)
        if side:
            s = "L" if side == "left" else "R"
            parent = {"hip": "root", "knee": f"upperleg01.{s}", "ankle": f"lowerleg01.{s}", "collar": "spine01",
                      "shoulder": f"clavicle.{s}", "elbow": f"upperarm02.{s}", "wrist": f"lowerarm01.{s}"}[canon.split("_")[1]]
        add(bone, parent, position)
        if canon.endswith("_shoulder"):  # a twist bone half way down the upper arm
            add(f"upperarm02.{s}", bone, (position + lowered(rest[f"{side}_elbow"], side)) / 2)
        if canon.endswith("_wrist"):
            add(f"finger3-1.{s}", bone, lowered(ends[f"{side}_hand"], side))
    points["head_top"] = ends["head_top"]
    points["toe_tip.L"], points["toe_tip.R"] = ends["left_toe"], ends["right_toe"]
    order = sorted(range(len(names)), key=lambda j: _depth(parents, j))  # parents before children
    remap = {old: new for new, old in enumerate(order)}
    return [names[j] for j in order], [remap[parents[j]] if parents[j] >= 0 else -1 for j in order], points, template


def _depth(parents, j):
    return 0 if parents[j] < 0 else 1 + _depth(parents, parents[j])


def test_retarget_turns_an_a_pose_rig_into_the_mocap_pose():
    names, parents, points, template = a_pose_rig()
    rng = np.random.default_rng(2)
    count = 5
    canonical_local = random_rotations(rng, (count, len(JOINTS)), max_angle=1.2)
    world, positions = forward_kinematics(canonical_local, np.zeros((count, 3)), template.offsets, template.parents)
    canonical_rest = P._TEMPLATE_POINTS.expand((count,) + P._TEMPLATE_POINTS.shape)
    local = P.retarget(world, canonical_rest, points, names, parents)
    rest_joints = torch.stack([points[n] for n in names])
    A, _, joints = S.skinning_transforms(rest_joints, parents, local, torch.zeros(count, 3, dtype=torch.float64))
    errors = P.aim_errors(A, joints, points, names, world, canonical_rest)
    assert max(e.max() for e in errors.values()) < 1e-4
    # the posed rig's elbows and wrists lie along the mocap's arm directions
    elbow, wrist = names.index("lowerarm01.L"), names.index("wrist.L")
    mocap = positions[:, JOINTS.index("left_wrist")] - positions[:, JOINTS.index("left_elbow")]
    rig = joints[:, wrist] - joints[:, elbow]
    assert torch.allclose(rig / rig.norm(dim=-1, keepdim=True), mocap / mocap.norm(dim=-1, keepdim=True), atol=1e-6)
    # the canonical T-pose gives the rig a T-pose: arms horizontal, the twist bone not turned
    identity = torch.eye(3, dtype=torch.float64).expand(1, len(JOINTS), 3, 3)
    local = P.retarget(identity, canonical_rest[:1], points, names, parents)
    _, _, joints = S.skinning_transforms(rest_joints, parents, local, torch.zeros(1, 3, dtype=torch.float64))
    arm = joints[0, wrist] - joints[0, names.index("upperarm01.L")]
    assert abs(arm[1]) < 1e-9 and arm[0] > 0
    assert torch.allclose(local[0, names.index("upperarm02.L")], torch.eye(3, dtype=torch.float64))


def test_hand_and_eye_rotations():
    names = ["root", "wrist.L"] + [f"finger{f}-{k}.L" for f in range(1, 6) for k in range(1, 4)] + ["eye.L", "eye.R"]
    rest = torch.zeros(len(names), 3, dtype=torch.float64)
    for f in range(1, 6):  # a flat left hand along +X, palm down, thumb forward (+Z)
        for k in range(1, 4):
            rest[names.index(f"finger{f}-{k}.L")] = torch.tensor([0.05 + 0.03 * k, 0.0, 0.04 - 0.02 * (f - 1)])
    curl = torch.zeros(2, 2, 5, dtype=torch.float64)
    curl[1, 0] = 1.0
    out = P.hand_and_eye_rotations(rest, names, curl, torch.zeros(2, 2, dtype=torch.float64))
    eye = torch.eye(3, dtype=torch.float64)
    assert torch.allclose(out[0], eye)
    bone = names.index("finger3-2.L")
    angle = np.degrees(float(rot.convert(out[1, bone], "matrix", "rotvec").norm()))
    assert angle == pytest.approx(P.FINGER_MAX_DEGREES[3][1])
    # the finger tip turns towards the palm (down, -Y)
    assert (out[1, bone] @ torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))[1] < -0.5
    gaze = P.hand_and_eye_rotations(rest, names, torch.zeros(1, 2, 5, dtype=torch.float64),
                                    torch.tensor([[0.3, 0.0]], dtype=torch.float64))
    assert torch.allclose(gaze[0, names.index("eye.L")], gaze[0, names.index("eye.R")])
    assert not torch.allclose(gaze[0, names.index("eye.L")], eye)


def test_samplers_are_sparse_and_bounded():
    rng = np.random.default_rng(3)
    expression = P.sample_expressions(rng, 400, 52, fraction=0.5)
    active = (expression > 0).sum(1)
    assert 0.35 < (active > 0).double().mean() < 0.65 and active.max() <= 4
    assert expression[expression > 0].min() >= 0.3 and expression.max() <= 1.0
    curl, gaze = P.sample_hand_and_gaze(rng, 400)
    assert curl.shape == (400, 2, 5) and curl.min() >= 0 and curl.max() <= 1
    assert 0.2 < (curl.sum(-1) == 0).double().mean() < 0.4
    assert torch.all(torch.rad2deg(gaze).abs().amax(0) <= torch.tensor([20.0, 12.0], dtype=torch.float64))


def test_remove_heading_faces_plus_z():
    rng = np.random.default_rng(4)
    world = torch.from_numpy(random_rotations(rng, (6, 22)))
    fixed = P.remove_heading(world)[:, None] @ world
    forward = fixed[:, 0, :, 2]
    assert forward[:, 0].abs().max() < 1e-9 and torch.all(forward[:, 2] >= 0)


def test_sample_mocap_poses(mocap):
    from humotion.data import MotionCollection

    collection = MotionCollection.load(mocap, sources=["cmu_fairmotion"], progress=False)
    poses = P.sample_mocap_poses(collection.clips, 7, np.random.default_rng(0), root=collection.root)
    assert poses.world_rotations.shape == (7, 22, 3, 3) and poses.rest.shape == (7, 27, 3)
    assert poses.world_rotations.dtype == torch.float64 and poses.frame.dtype == torch.int64
    assert torch.allclose(poses.posed[:, 0], torch.zeros(7, 3, dtype=torch.float64))
    assert poses.world_rotations[:, 0, 0, 2].abs().max() < 1e-6  # heading removed
    assert all(c.startswith("cmu_fairmotion/") for c in poses.clip)
    again = P.sample_mocap_poses(collection.clips, 7, np.random.default_rng(0), root=collection.root)
    assert torch.equal(again.frame, poses.frame) and torch.equal(again.world_rotations, poses.world_rotations)


def test_mocap_poses_through_a_symlinked_root(mocap, tmp_path):
    """The dataset's pose draw on a mocap folder reached through a link (data on another drive)."""
    tree = tmp_path / "drive"
    tree.mkdir()
    for source in ("cmu_fairmotion", "cmu_mocgui_s02"):
        (tree / source).symlink_to(mocap / source, target_is_directory=True)
    (tmp_path / "mocap").symlink_to(tree, target_is_directory=True)
    poses, subjects = D.draw_mocap_poses(tmp_path / "mocap", np.zeros(3, dtype=bool), np.random.default_rng(0))
    assert poses["world_rotations"].shape == (3, 22, 3, 3)
    assert all(name.startswith(("cmu_fairmotion/", "cmu_mocgui_s02/")) for name in poses["clip"])
    assert set(poses["subject"]) <= set(subjects["train"])


# -- files --------------------------------------------------------------------------------------------

def test_save_npz_leaves_no_partial_file(tmp_path):
    path = tmp_path / "sub" / "a.npz"
    F.save_npz(path, {"x": np.arange(3), "names": np.array(["a", "bc"])})
    assert [p.name for p in path.parent.iterdir()] == ["a.npz"]
    with np.load(path, allow_pickle=False) as data:
        assert data["names"].tolist() == ["a", "bc"]


def test_readers_say_what_is_missing(tmp_path):
    with pytest.raises(FileNotFoundError, match="humotion.body.command data"):
        F.load_split(tmp_path, "full", "train")
    with pytest.raises(FileNotFoundError, match="manifest"):
        F.read_manifest(tmp_path)
    with pytest.raises(ValueError, match="split"):
        F.load_split(tmp_path, "full", "validation")
    with pytest.raises(ValueError, match="resolution"):
        F.load_model_file(tmp_path, "medium")


# -- generation with Anny ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def anny_source():
    pytest.importorskip("anny")
    torch.set_num_threads(1)
    from humotion.body import anny_source

    return anny_source


@pytest.fixture(scope="module")
def tiny(anny_source, tmp_path_factory):
    if not D.DEFAULT_MOCAP.is_dir():
        pytest.skip(f"mocap data not found at {D.DEFAULT_MOCAP}")
    out = tmp_path_factory.mktemp("body_data")
    settings = D.Settings(out=str(out), shapes=4, poses_per_shape=2, seed=5, chunk=2)
    manifest = D.generate(settings, command="test", progress=False)
    return out, manifest


def test_generated_folder(tiny):
    out, manifest = tiny
    assert manifest == F.read_manifest(out)
    assert manifest["meshes"] == 8 and sum(manifest["splits"].values()) == 8
    assert all(manifest["splits"][s] > 0 for s in F.SPLITS)
    assert manifest["joints"] == 76 and manifest["anny_version"] == "0.6.2"
    assert "CC0" in manifest["licence"] and "CMU" in manifest["licence"]
    assert max(manifest["retarget_aim_error_deg_p99"].values()) < 0.01
    assert not list(out.rglob("*.tmp")) and not (out / ".parts").exists()
    shapes, poses = F.load_shapes(out), F.load_poses(out)
    assert shapes["phenotypes"].shape == (4, 6) and np.all((shapes["height"] > 0.8) & (shapes["height"] < 2.2))
    held_subjects = set(manifest["mocap_subjects"]["held_out"])
    assert all((s in held_subjects) == h for s, h in zip(poses["subject"], poses["held_out"]))
    seen = []
    for k, split in enumerate(F.SPLITS):
        full, low = F.load_split(out, "full", split), F.load_split(out, "low", split)
        assert full["vertices"].dtype == np.float32 and full["vertices"].shape[1:] == (13718, 3)
        assert low["vertices"].shape[1:] == (1229, 3)
        for key in ("mesh_id", "shape_id", "pose_id", "rotations", "translation", "joints", "expression"):
            assert np.array_equal(full[key], low[key])
        assert np.all(shapes["held_out"][full["shape_id"]] == (split in ("test_shapes", "test_both")))
        assert np.all(poses["held_out"][full["pose_id"]] == (split in ("test_poses", "test_both")))
        assert np.allclose(np.linalg.norm(full["rotations"], axis=-1), 1, atol=1e-5)
        assert np.allclose(full["vertices"][..., 1].min(1), 0, atol=1e-5)  # standing on the floor
        seen += full["mesh_id"].tolist()
    assert sorted(seen) == list(range(8))


def test_meshes_match_their_parameters(tiny):
    out, _ = tiny
    for resolution in F.RESOLUTIONS:
        model = F.load_model_file(out, resolution)
        assert model["rest_vertices"].shape[0] == 4 and model["rest_joints"].shape == (4, 76, 3)
        assert np.allclose(model["skin_weights"].sum(1), 1, atol=1e-5)
        regions = model["region_body"].astype(int) + model["region_face"] + model["region_hands"]
        assert np.all(regions == 1)  # the three regions split the vertices
        split = F.load_split(out, resolution, "train")
        # plain LBS of the rest shape under the stored pose parameters is within a few mm of the
        # dual-quaternion mesh: the parameters, joints and expression offsets are the ones used
        assert rest_gap_ok(F.rest_pose_check(model, split))
        A, t, joints = S.skinning_transforms(model["rest_joints"][split["shape_id"][0]], model["parents"],
                                             split["rotations"][:1], split["translation"][:1])
        assert np.allclose(joints[0], split["joints"][0], atol=1e-5)


def rest_gap_ok(gaps):
    return bool(np.all(gaps < 0.005))


def test_rest_faces_plus_z_and_expressions_are_linear(anny_source):
    body = anny_source.AnnyBody("anny")
    phenotypes = np.array([[0.2, 0.7, 0.5, 0.6, 0.4, 0.5]])
    rest = body.rest(phenotypes)
    labels, names = body.part_labels()
    head = rest.vertices[0][labels == names.index("head")]
    nose = head[head[:, 2].argmax()]
    assert nose[2] > rest.joints[0, body.joint_names.index("head"), 2] + 0.05  # the face looks to +Z
    assert rest.vertices[0][:, 1].argmax() in np.flatnonzero(labels == names.index("head"))  # Y up
    expression = np.zeros((1, 52))
    expression[0, body.facial_action_names.index("jawOpen")] = 0.7
    expression[0, body.facial_action_names.index("mouthSmileLeft")] = 0.4
    expressive = body.rest(phenotypes, expression)
    offsets = np.einsum("ke,evc->kvc", expression, body.expression_basis())
    assert np.allclose(expressive.vertices, rest.vertices + offsets, atol=1e-6)
    assert np.allclose(expressive.joints, rest.joints)


def test_posing_anny_matches_the_pose_convention(anny_source):
    body = anny_source.AnnyBody("notoes_collapse10pc")
    phenotypes = np.array([0.6, 0.3, 0.5, 0.5, 0.5, 0.5])
    rest = body.rest(phenotypes[None])
    J = len(body.joint_names)
    identity = np.broadcast_to(np.eye(3), (1, J, 3, 3))
    assert np.allclose(body.pose(phenotypes, None, identity, np.zeros((1, 3))), rest.vertices, atol=1e-9)
    rng = np.random.default_rng(6)
    local = random_rotations(rng, (2, J), max_angle=0.5)
    translation = rng.normal(size=(2, 3))
    A, t, _ = S.skinning_transforms(rest.joints[0], body.parents, local, translation)
    ours = S.linear_blend_skinning(rest.vertices[0], body.skin_weights().astype(np.float64), A, t)
    assert np.allclose(body.pose(phenotypes, None, local, translation, skinning="lbs"), ours, atol=1e-5)
    dqs = body.pose(phenotypes, None, local, translation)
    gap = np.linalg.norm(dqs - ours, axis=-1)
    assert 0 < gap.mean() < 0.02


def test_interrupted_run_resumes(anny_source, tiny, tmp_path, monkeypatch):
    fresh, _ = tiny
    settings = D.Settings(out=str(tmp_path), shapes=4, poses_per_shape=2, seed=5, chunk=2)
    made = []
    original = D.Generator.make_chunk

    def fail_on_second(self, plan, shapes):
        if made:
            raise KeyboardInterrupt
        made.append(shapes)
        return original(self, plan, shapes)

    monkeypatch.setattr(D.Generator, "make_chunk", fail_on_second)
    with pytest.raises(KeyboardInterrupt):
        D.generate(settings, progress=False)
    assert (tmp_path / ".parts" / "chunk-0000.npz").exists() and not (tmp_path / "manifest.json").exists()
    assert json.loads((tmp_path / ".parts" / "settings.json").read_text())["key"] == settings.key()
    calls = []
    monkeypatch.setattr(D.Generator, "make_chunk", lambda self, plan, shapes: calls.append(shapes) or original(self, plan, shapes))
    D.generate(settings, progress=False)
    assert calls == [range(2, 4)]  # the first chunk came from the parts
    for split in F.SPLITS:
        a, b = F.load_split(fresh, "full", split), F.load_split(tmp_path, "full", split)
        assert all(np.array_equal(a[k], b[k]) for k in a)


def test_an_empty_anny_cache_variable_counts_as_unset(anny_source, monkeypatch):
    # anny would take "" for the working directory and write its ~1 GB cache there
    monkeypatch.setenv("ANNY_CACHE_DIR", "")
    anny_source._import_anny()
    assert "ANNY_CACHE_DIR" not in os.environ
    monkeypatch.setenv("ANNY_CACHE_DIR", "/somewhere/cache")
    anny_source._import_anny()
    assert os.environ["ANNY_CACHE_DIR"] == "/somewhere/cache"

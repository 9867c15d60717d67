"""AMASS .npz files: written here from a CMU clip (canonical motion -> SMPL-H axis-angles, Z up),
read back onto the canonical body; bone lengths from a tiny SMPL-H model made in the test."""

import numpy as np
import pytest
import torch

from humotion import rotations as rot
from humotion.assets import demo_clip_path
from humotion.canonical import PARENTS, canonical_skeleton, to_canonical
from humotion.io import load_motion
from humotion.io.amass import DEFAULT_HEIGHT, MODEL_ENV, Z_UP_TO_Y_UP, read_amass, using_body_model
from humotion.io.errors import MotionFileError
from humotion.motion import Motion
from humotion.skeleton import Skeleton

FINGER_PARENTS = [20] * 15 + [21] * 15        # enough of SMPL-H's hand tree: every finger joint on its wrist


@pytest.fixture(scope="module")
def clip():
    """A CMU take (the bundled demo clip) on the canonical body, 1 s."""
    return to_canonical(load_motion(demo_clip_path()))[:30]


def write_amass(motion: Motion, path, pelvis_origin=np.zeros(3), betas=np.zeros(16), **extra):
    """The motion as AMASS stores it: SMPL-H axis-angles (F, 156; fingers at rest), the root turned
    into AMASS's Z-up world, trans = pelvis - the model's pelvis joint J[0]."""
    matrices = motion.rotations_as("matrix").double().numpy()
    matrices[:, 0] = Z_UP_TO_Y_UP.T @ matrices[:, 0]
    poses = np.zeros((motion.num_frames, 156))
    poses[:, :66] = rot.convert(torch.from_numpy(matrices), "matrix", "rotvec").reshape(motion.num_frames, 66).numpy()
    trans = motion.root_positions.double().numpy() @ Z_UP_TO_Y_UP - pelvis_origin
    fields = dict(poses=poses, trans=trans, mocap_framerate=np.array(motion.fps), betas=betas, gender=np.array("neutral"))
    np.savez(path, **(fields | extra))
    return path


def fake_model(path, rest: np.ndarray, growth: float):
    """A SMPL-H model with one vertex per joint (J_regressor the identity): v_template holds the
    22 body joints at rest (Y up, +Z forward), the fingers on the wrists; the first shape
    direction scales the body about the pelvis by growth per unit of betas[0]."""
    template = np.concatenate([rest, rest[[20] * 15 + [21] * 15]])
    shapedirs = np.zeros((52, 3, 10))
    shapedirs[:, :, 0] = (template - template[0]) * growth
    kintree = np.array([[2**32 - 1] + list(PARENTS[1:]) + FINGER_PARENTS, list(range(52))], dtype=np.int64)
    np.savez(path, J_regressor=np.eye(52), v_template=template, shapedirs=shapedirs, kintree_table=kintree)
    return path


def test_a_cmu_clip_comes_back_within_a_millimetre(clip, tmp_path):
    """Without a model: the canonical proportions at the default height, the pelvis at trans."""
    path = write_amass(clip, tmp_path / "01_01_poses.npz")
    motion = read_amass(path)
    expected = Motion(canonical_skeleton(DEFAULT_HEIGHT), clip.rotations, clip.root_positions, clip.fps)
    assert motion.fps == clip.fps and motion.num_frames == clip.num_frames and motion.name == "01_01"
    assert motion.skeleton.names == expected.skeleton.names
    error = (motion.world_positions() - expected.world_positions()).norm(dim=-1).max()
    assert error < 1e-3, f"{error * 1000:.2f} mm"
    # The file is Z up as AMASS's are (its trans[:, 2] is the pelvis height); C is a proper
    # rotation taking AMASS's up (+Z) to humotion's (+Y).
    assert np.allclose(np.load(path)["trans"][:, 2], clip.root_positions[:, 1].double().numpy(), atol=1e-6)
    assert np.allclose(Z_UP_TO_Y_UP @ [0, 0, 1], [0, 1, 0]) and np.isclose(np.linalg.det(Z_UP_TO_Y_UP), 1.0)


def test_bone_lengths_come_from_the_model_and_the_betas(clip, tmp_path):
    own = clip.skeleton.rest_positions().double().numpy() + np.array([0.002, -0.25, 0.03])    # the model's origin is not the pelvis
    model = fake_model(tmp_path / "model.npz", own, growth=0.1)
    betas = np.array([1.0, 0.0, 0.0])
    path = write_amass(clip, tmp_path / "take_poses.npz", pelvis_origin=own[0], betas=betas)
    motion = read_amass(path, body_model=model)
    lengths = motion.skeleton.offsets[1:].norm(dim=1)
    assert torch.allclose(lengths, 1.1 * clip.skeleton.offsets[1:].norm(dim=1), atol=1e-6)
    grown = Skeleton(clip.skeleton.names, clip.skeleton.parents, clip.skeleton.offsets * 1.1)
    expected = Motion(grown, clip.rotations, clip.root_positions, clip.fps)
    error = (motion.world_positions() - expected.world_positions()).norm(dim=-1).max()
    assert error < 1e-3, f"{error * 1000:.2f} mm"
    with using_body_model(model):                          # what collections and their workers read with
        assert torch.allclose(load_motion(path).world_positions(), motion.world_positions())
    assert torch.allclose(read_amass(path).skeleton.offsets[1:].norm(dim=1),
                          canonical_skeleton(DEFAULT_HEIGHT).offsets[1:].norm(dim=1))


def test_a_folder_of_amass_files_is_a_collection_split_by_subject(clip, tmp_path, monkeypatch):
    from humotion.data import MotionCollection

    monkeypatch.delenv(MODEL_ENV, raising=False)
    root = tmp_path / "AMASS"
    for relative in ("BMLmovi/Subject_1/walk_poses.npz", "BMLmovi/Subject_1/run_poses.npz",
                     "BMLmovi/Subject_2/walk_poses.npz", "CMU/01/01_01_poses.npz"):
        (root / relative).parent.mkdir(parents=True, exist_ok=True)
        write_amass(clip, root / relative)
    np.savez(root / "BMLmovi" / "Subject_1" / "shape.npz", betas=np.zeros(16), gender=np.array("female"))
    collection = MotionCollection.load(root, cache_dir=tmp_path / "cache", workers=1, progress=False)
    assert len(collection) == 4 and not collection.skipped          # shape.npz is no motion, and not an error
    assert collection.subjects() == ["BMLmovi-Subject_1", "BMLmovi-Subject_2", "cmu-01"]
    assert collection.clips[0].frames == clip.num_frames and collection.clips[0].fps == clip.fps
    windows = collection.windows(10, 30.0, stride=10, transform=to_canonical)
    assert len(windows) == 4 * 3


@pytest.mark.parametrize("fields, problem", [
    ({"poses": None}, "no poses"),
    ({"mocap_framerate": None}, "no mocap_framerate"),
    ({"poses": np.zeros((30, 12))}, "expected (F, 156)"),
    ({"trans": np.zeros((29, 3))}, "trans has shape (29, 3)"),
    ({"mocap_framerate": np.array(0.0)}, "positive frame rate"),
    ({"trans": np.full((30, 3), np.nan)}, "frame 0: poses or trans hold NaN"),
])
def test_malformed_files_are_named_with_the_problem(clip, tmp_path, fields, problem):
    path = write_amass(clip, tmp_path / "bad.npz", **{k: v for k, v in fields.items() if v is not None})
    if any(v is None for v in fields.values()):
        data = dict(np.load(path))
        np.savez(path, **{k: v for k, v in data.items() if fields.get(k, 0) is not None})
    with pytest.raises(MotionFileError, match="bad.npz: .*" + problem.replace("(", r"\(").replace(")", r"\)")):
        read_amass(path)


def test_files_that_are_not_amass_motions_are_refused(clip, tmp_path):
    (tmp_path / "text.npz").write_text("not a zip")
    with pytest.raises(MotionFileError, match="not a readable .npz"):
        read_amass(tmp_path / "text.npz")
    np.savez(tmp_path / "shape.npz", betas=np.zeros(16))
    with pytest.raises(MotionFileError, match="shape file"):
        read_amass(tmp_path / "shape.npz")
    path = write_amass(clip, tmp_path / "take.npz")
    np.savez(tmp_path / "model.npz", v_template=np.zeros((4, 3)))
    with pytest.raises(MotionFileError, match="model.npz: not a SMPL-H model .npz: no J_regressor, shapedirs"):
        read_amass(path, body_model=tmp_path / "model.npz")
    with pytest.raises(MotionFileError, match="no such file"):
        read_amass(path, body_model=tmp_path / "missing.npz")


def test_train_sparse_reads_a_folder_of_amass_files(clip, tmp_path, monkeypatch):
    """`humotion train sparse --data AMASS --smplh-model model.npz` trains on them (one step here)."""
    from click.testing import CliRunner

    from humotion.cli import main

    monkeypatch.setenv("HUMOTION_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv(MODEL_ENV, raising=False)
    model = fake_model(tmp_path / "model.npz", clip.skeleton.rest_positions().double().numpy(), growth=0.1)
    for subject in range(6):
        folder = tmp_path / "AMASS" / "Dataset" / f"Subject_{subject}"
        folder.mkdir(parents=True)
        write_amass(clip, folder / "take_poses.npz", pelvis_origin=clip.skeleton.rest_positions()[0].double().numpy(),
                    betas=np.array([subject / 5]))
    common = ["train", "sparse", "--data", str(tmp_path / "AMASS"), "--out", str(tmp_path / "run"), "--steps", "1",
              "--batch-size", "2", "--length", "10", "--stride", "10", "--hidden", "8", "--embed", "4", "--threads", "1"]
    result = CliRunner().invoke(main, common + ["--smplh-model", str(model)])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "run" / "sparse_poser.pt").is_file()
    np.savez(tmp_path / "not_a_model.npz", v_template=np.zeros((4, 3)))
    result = CliRunner().invoke(main, common + ["--smplh-model", str(tmp_path / "not_a_model.npz")])
    assert result.exit_code == 1 and "not a SMPL-H model" in result.output and "Traceback" not in result.output

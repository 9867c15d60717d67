"""AMASS motion files (.npz, SMPL-H parameters) -> Motion on the canonical 22-joint body.

AMASS (https://amass.is.tue.mpg.de, non-commercial licence; download it yourself, nothing here
fetches it) stores each take as a NumPy .npz with

    poses            (T, 156) axis-angle, SMPL-H joint order: root orientation, 21 body joints,
                     then 30 finger joints (SMPL-X files: (T, 165), same first 66 numbers)
    trans            (T, 3) metres: translation of the body model's origin
    mocap_framerate  frames per second (SMPL-X files: mocap_frame_rate)
    betas            (16,) body shape coefficients; gender: 'male', 'female' or 'neutral'

The first 22 SMPL-H joints are humotion's canonical joints, same names, same order, same parents
(humotion.canonical.JOINTS), and SMPL's rest pose is, like the canonical one, a T-pose facing
+Z with Y up, so the body joints' axis-angles are the canonical local rotations as they are; the
fingers are dropped. AMASS puts the world Z up: humotion's frame is Y up, +Z forward, so the root
orientation and the translation are turned by C = a quarter turn about X, (x, y, z) -> (x, z, -y).

Bone lengths: with a SMPL-H model file (``body_model``: an .npz with J_regressor (52, V),
v_template (V, 3), shapedirs (V, 3, S) and kintree_table (2, 52), e.g. the model.npz of the
SMPL-H release), the joints of the subject's own shape, J = J_regressor (v_template + shapedirs
betas), give each bone, and the pelvis is placed where SMPL-H places it (trans + J[0]). Without
one, the canonical skeleton's proportions at DEFAULT_HEIGHT are used and the pelvis is taken to be
at trans (SMPL-H's pelvis joint sits a few centimetres from the model's origin, so the trajectory
is off by that constant offset, which training does not see: it recentres every window).

The model file for reading through collections (training on a folder of AMASS files) is named by
$HUMOTION_SMPLH_MODEL (:func:`using_body_model` sets it), so reader processes see it too.

    motion = read_amass("CMU/01/01_01_poses.npz")                     # canonical proportions
    motion = read_amass(path, body_model="smplh/neutral/model.npz")   # the subject's own bones
"""

from __future__ import annotations

import contextlib
import os
import zipfile
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from humotion import rotations as rot
from humotion.canonical import END_SITE_PARENTS, END_SITES, JOINTS, PARENTS, TEMPLATE_HEIGHT, canonical_skeleton
from humotion.io.errors import MotionFileError
from humotion.motion import Motion
from humotion.skeleton import Skeleton

BODY_JOINTS = len(JOINTS)                # 22: SMPL-H's body joints, the canonical ones
DEFAULT_HEIGHT = TEMPLATE_HEIGHT         # metres, the canonical template's, for files read without a model
MODEL_ENV = "HUMOTION_SMPLH_MODEL"
Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
"""C: AMASS world (Z up) -> humotion's (Y up, +Z forward): (x, y, z) -> (x, z, -y)."""
SHAPE_FILE = "shape.npz"
"""Each AMASS subject folder also holds this file (betas and gender only): not a motion."""


@dataclass(frozen=True)
class BodyModel:
    """What the reader needs of a SMPL-H model: J_regressor (J, V), v_template (V, 3),
    shapedirs (V, 3, S), parents (J,) from kintree_table (-1 for the root)."""

    j_regressor: np.ndarray
    v_template: np.ndarray
    shapedirs: np.ndarray
    parents: tuple[int, ...]

    def joints(self, betas: np.ndarray) -> np.ndarray:
        """(J, 3) rest joint positions (model frame: Y up, facing +Z, metres) of a body shape."""
        n = min(len(betas), self.shapedirs.shape[-1])
        vertices = self.v_template + self.shapedirs[..., :n] @ betas[:n]
        return self.j_regressor @ vertices


def load_body_model(path: str | Path) -> BodyModel:
    """A SMPL-H model from an .npz (module docstring). Raises MotionFileError naming the file and
    the missing or malformed entry."""
    return _load_body_model(str(Path(path).expanduser().resolve()))


@lru_cache(maxsize=4)
def _load_body_model(path: str) -> BodyModel:
    data = _open_npz(Path(path), "a SMPL-H model")
    names = ("J_regressor", "v_template", "shapedirs", "kintree_table")
    missing = [k for k in names if k not in data.files]
    if missing:
        raise MotionFileError(path, f"not a SMPL-H model .npz: no {', '.join(missing)} "
                                    f"(it has {', '.join(sorted(data.files)) or 'nothing'})")
    try:
        regressor, template, shapedirs, kintree = (np.asarray(data[k], dtype=np.float64) for k in names)
    except (ValueError, TypeError) as error:
        raise MotionFileError(path, f"a SMPL-H model entry is not a numeric array ({error})") from None
    vertices = template.shape[0]
    if template.ndim != 2 or template.shape[1] != 3:
        raise MotionFileError(path, f"v_template has shape {template.shape}, expected (V, 3)")
    if regressor.ndim != 2 or regressor.shape[1] != vertices or regressor.shape[0] < BODY_JOINTS:
        raise MotionFileError(path, f"J_regressor has shape {regressor.shape}, expected (J >= {BODY_JOINTS}, {vertices})")
    if shapedirs.ndim != 3 or shapedirs.shape[:2] != (vertices, 3):
        raise MotionFileError(path, f"shapedirs has shape {shapedirs.shape}, expected ({vertices}, 3, S)")
    if kintree.ndim != 2 or kintree.shape[0] != 2 or kintree.shape[1] != regressor.shape[0]:
        raise MotionFileError(path, f"kintree_table has shape {kintree.shape}, expected (2, {regressor.shape[0]})")
    parents = tuple(-1 if j == 0 else int(p) for j, p in enumerate(kintree[0]))
    if parents[:BODY_JOINTS] != PARENTS:
        raise MotionFileError(path, "kintree_table's first 22 joints are not SMPL-H's body tree "
                                    f"(parents {parents[:BODY_JOINTS]}, expected {PARENTS})")
    return BodyModel(regressor, template, shapedirs, parents)


def default_body_model() -> str | None:
    """The model file named by $HUMOTION_SMPLH_MODEL, or None."""
    return os.environ.get(MODEL_ENV) or None


@contextlib.contextmanager
def using_body_model(path: str | Path | None):
    """Within the block, AMASS files read without an explicit body_model (load_motion, motion
    collections, their worker processes) use this SMPL-H model file; None changes nothing."""
    if path is None:
        yield
        return
    load_body_model(path)               # a bad file is reported here, once, not per motion file
    before = os.environ.get(MODEL_ENV)
    os.environ[MODEL_ENV] = str(Path(path).expanduser().resolve())
    try:
        yield
    finally:
        if before is None:
            os.environ.pop(MODEL_ENV, None)
        else:
            os.environ[MODEL_ENV] = before


def companion_files(path: str | Path) -> list[Path]:
    """Files besides path that change what read_amass gives for it (the model of $HUMOTION_SMPLH_MODEL,
    for .npz motion files): for the keys of caches of parsed motions."""
    model = default_body_model()
    return [Path(model)] if model and str(path).lower().endswith(".npz") else []


# -- reading ------------------------------------------------------------------------------------

def read_amass(path: str | Path, body_model: str | Path | BodyModel | None = None,
               height: float = DEFAULT_HEIGHT) -> Motion:
    """Read an AMASS .npz (module docstring) into a Motion on the canonical 22 joints, in
    humotion's frame (metres, Y up, +Z forward) at the file's frame rate.

    body_model: a SMPL-H model (file or BodyModel) giving the subject's bone lengths from its
        betas; None: $HUMOTION_SMPLH_MODEL when set, else the canonical skeleton at height (m).
    Raises MotionFileError naming the file and the problem.
    """
    path = Path(path)
    poses, trans, fps, betas = _fields(path)
    if body_model is None:
        body_model = default_body_model()
    model = load_body_model(body_model) if isinstance(body_model, (str, Path)) else body_model
    skeleton, pelvis = _skeleton(model, betas, height)
    rotations, root_positions = _to_y_up(poses[:, :3 * BODY_JOINTS].reshape(-1, BODY_JOINTS, 3), trans + pelvis)
    name = path.name[: -len("_poses.npz")] if path.name.endswith("_poses.npz") else path.stem
    return Motion(skeleton, rotations, root_positions, fps, name=name)


def _open_npz(path: Path, what: str):
    if path.name == SHAPE_FILE and what == "an AMASS motion":
        raise MotionFileError(path, "an AMASS shape file (betas and gender), not a motion")
    try:
        return np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise MotionFileError(path, "no such file") from None
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as error:
        raise MotionFileError(path, f"not a readable .npz file ({what}): {error}") from None


def _fields(path: Path) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Step 1: poses (T, >= 66), trans (T, 3), fps and betas (S,), checked."""
    data = _open_npz(path, "an AMASS motion")
    rate_key = next((k for k in ("mocap_framerate", "mocap_frame_rate") if k in data.files), None)
    missing = [k for k in ("poses", "trans") if k not in data.files] + ([] if rate_key else ["mocap_framerate"])
    if missing:
        raise MotionFileError(path, f"not an AMASS motion file: no {', '.join(missing)} "
                                    f"(it has {', '.join(sorted(data.files)) or 'nothing'})")
    try:
        poses, trans = np.asarray(data["poses"], dtype=np.float64), np.asarray(data["trans"], dtype=np.float64)
        fps = float(np.asarray(data[rate_key]).reshape(-1)[0])
        betas = np.asarray(data["betas"], dtype=np.float64).reshape(-1) if "betas" in data.files else np.zeros(0)
    except (ValueError, TypeError, IndexError) as error:
        raise MotionFileError(path, f"an AMASS entry is not numeric ({error})") from None
    if poses.ndim != 2 or poses.shape[1] < 3 * BODY_JOINTS:
        raise MotionFileError(path, f"poses has shape {poses.shape}, expected (F, 156) SMPL-H axis-angles "
                                    f"(at least {3 * BODY_JOINTS} numbers per frame)")
    if trans.shape != (poses.shape[0], 3):
        raise MotionFileError(path, f"trans has shape {trans.shape}, expected ({poses.shape[0]}, 3) like poses")
    if poses.shape[0] == 0:
        raise MotionFileError(path, "no frames")
    if not (np.isfinite(fps) and fps > 0):
        raise MotionFileError(path, f"{rate_key} is {fps}, expected a positive frame rate")
    bad = ~(np.isfinite(poses[:, :3 * BODY_JOINTS]).all(1) & np.isfinite(trans).all(1))
    if bad.any():
        raise MotionFileError(path, f"frame {int(np.argmax(bad))}: poses or trans hold NaN or infinity")
    return poses, trans, fps, betas


def _skeleton(model: BodyModel | None, betas: np.ndarray, height: float) -> tuple[Skeleton, np.ndarray]:
    """Step 2: the canonical skeleton with the subject's bones (from the model) or the template's
    at height, and the pelvis's offset from the model's origin in AMASS's world frame."""
    if model is None:
        return canonical_skeleton(height), np.zeros(3)
    joints = model.joints(betas)[:BODY_JOINTS]
    offsets = joints - np.where(np.array(PARENTS)[:, None] >= 0, joints[[max(p, 0) for p in PARENTS]], 0.0)
    # End sites (head top, knuckles, toe tips) are not SMPL-H joints: the template's, scaled by
    # the subject's leg-to-head length against the template's.
    template = canonical_skeleton()
    rest = template.rest_positions(torch.float64).numpy()
    head, ankle = JOINTS.index("head"), JOINTS.index("left_ankle")
    scale = (joints[head, 1] - joints[ankle, 1]) / (rest[head, 1] - rest[ankle, 1])
    end_offsets = template.end_site_offsets.double().numpy() * scale
    lowest = min((joints - joints[0])[:, 1].min(), (joints[list(END_SITE_PARENTS)] + end_offsets - joints[0])[:, 1].min())
    offsets[0] = (0.0, -lowest, 0.0)          # the rest pose stands on y = 0, as the template's does
    skeleton = Skeleton(JOINTS, PARENTS, offsets, END_SITE_PARENTS, end_offsets, END_SITES)
    # SMPL-H turns the root about J[0] and adds trans: the pelvis is at trans + J[0] in the file's
    # world, J[0] not turned by the root orientation (which holds the Y-up -> Z-up turn).
    return skeleton, joints[0]


def _to_y_up(axis_angles: np.ndarray, pelvis: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """Step 3: (T, 22, 3) axis-angles and (T, 3) pelvis positions, Z up -> local wxyz quaternions
    (T, 22, 4) and root positions (T, 3) in humotion's frame (joint 0's turned by C)."""
    matrices = rot.convert(torch.from_numpy(axis_angles), "rotvec", "matrix")
    c = torch.from_numpy(Z_UP_TO_Y_UP)
    matrices[:, 0] = c @ matrices[:, 0]
    return rot.matrix_to_quat(matrices).float(), torch.from_numpy(pelvis @ Z_UP_TO_Y_UP.T).float()

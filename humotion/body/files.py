"""The files of a body data folder (see :mod:`humotion.body.dataset`): writers (whole files or
none, :func:`humotion.atomic.atomic_file`) and readers that need neither Anny nor pickle.

    data = load_split("runs/body_data", "full", "train")     # vertices (M, V, 3), shape_id, rotations, ...
    model = load_model_file("runs/body_data", "full")        # faces, rest shapes, skinning weights, masks
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from humotion.atomic import atomic_file
from humotion.body.skinning import linear_blend_skinning, skinning_transforms

SPLITS = ("train", "test_shapes", "test_poses", "test_both")
"""Mesh splits by (shape held out, pose held out): (no, no), (yes, no), (no, yes), (yes, yes)."""

RESOLUTIONS = ("full", "low")


def save_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """np.savez of arrays (any shapes and dtypes) to path (its folder made when missing), atomically:
    never a half-written file under the name."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(path) as file:
        np.savez(file, **arrays)


def save_json(path: Path, data: dict) -> None:
    """JSON to path, atomically."""
    with atomic_file(path) as file:
        file.write((json.dumps(data, indent=2) + "\n").encode())


def load_npz(path: Path) -> dict[str, np.ndarray]:
    """Every array of an .npz file by name (any shapes, as saved; no pickle);
    FileNotFoundError saying how to make the data."""
    if not path.exists():
        raise FileNotFoundError(f"{path} not found: make the data with `python -m humotion.body.command data --out {path.parent}`")
    with np.load(path, allow_pickle=False) as data:
        return {k: data[k] for k in data.files}


def read_manifest(folder: str | Path) -> dict:
    """The run's manifest.json."""
    path = Path(folder) / "manifest.json"
    if not path.exists():
        raise FileNotFoundError(f"no manifest.json in {folder}: not a body data folder (or its run did not finish)")
    return json.loads(path.read_text())


def load_split(folder: str | Path, resolution: str = "full", split: str = "train") -> dict[str, np.ndarray]:
    """Meshes of one split at one resolution: vertices (M, V, 3), mesh_id, shape_id, pose_id,
    rotations (M, J, 4), translation (M, 3), joints (M, J, 3), expression (M, 52), ..."""
    if resolution not in RESOLUTIONS:
        raise ValueError(f"resolution must be one of {RESOLUTIONS}, got {resolution!r}")
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    return load_npz(Path(folder) / resolution / f"{split}.npz")


def load_model_file(folder: str | Path, resolution: str = "full") -> dict[str, np.ndarray]:
    """Topology and per-shape rest data of one resolution (see :mod:`humotion.body.dataset`):
    faces (faces, 3) int32, rest_vertices (N, V, 3), rest_joints (N, J, 3) metres, skin_weights
    (V, J), expression_basis (52, V, 3), part (V,), region_* (V,) bool, names and parents."""
    if resolution not in RESOLUTIONS:
        raise ValueError(f"resolution must be one of {RESOLUTIONS}, got {resolution!r}")
    return load_npz(Path(folder) / resolution / "model.npz")


def load_shapes(folder: str | Path) -> dict[str, np.ndarray]:
    """shapes.npz: per shape (N of them) phenotypes (N, 6), age_years (N,), height (N,) metres,
    mass (N,) kg, bmi, ..., held_out (N,) bool."""
    return load_npz(Path(folder) / "shapes.npz")


def load_poses(folder: str | Path) -> dict[str, np.ndarray]:
    """poses.npz: per pose (P of them) its mocap source (clip, frame, subject), canonical_rotations
    (P, 22, 4) wxyz, finger_curl (P, 2, 5) in [0, 1] and gaze (P, 2) radians."""
    return load_npz(Path(folder) / "poses.npz")


def load_rest_shapes(folder: str | Path, resolution: str = "full") -> dict[str, np.ndarray] | None:
    """The extra rest shapes of :mod:`humotion.body.rest_shapes` at one resolution (rest_vertices
    (N, V, 3), rest_joints (N, J, 3), height, mass, ...), or None when the folder has none."""
    if resolution not in RESOLUTIONS:
        raise ValueError(f"resolution must be one of {RESOLUTIONS}, got {resolution!r}")
    path = Path(folder) / "rest_shapes.npz"
    if not path.exists():
        return None
    with np.load(path, allow_pickle=False) as data:
        keys = [k for k in data.files if not k.startswith("rest_vertices_")]
        out = {k: data[k] for k in keys}
        out["rest_vertices"] = data[f"rest_vertices_{resolution}"]
    return out


def expression_offsets(model: dict[str, np.ndarray], expression: np.ndarray) -> np.ndarray:
    """Rest-pose expression offsets (M, V, 3) of activations (M, 52): expressive rest mesh minus
    the neutral one."""
    return np.einsum("me,evc->mvc", np.asarray(expression, dtype=np.float32), model["expression_basis"])


def rest_pose_check(model: dict[str, np.ndarray], split: dict[str, np.ndarray], rows=slice(None)) -> np.ndarray:
    """(M,) mean distance in metres between each of the split's M meshes (or its `rows`) and plain
    LBS of its rest shape under its pose parameters: a consistency check of a data folder (a few
    mm to cm: the DQS-vs-LBS gap)."""
    rest = model["rest_vertices"][split["shape_id"][rows]] + expression_offsets(model, split["expression"][rows])
    out = []
    for i in range(len(rest)):
        A, t, _ = skinning_transforms(model["rest_joints"][split["shape_id"][rows][i]], model["parents"],
                                      split["rotations"][rows][i:i + 1], split["translation"][rows][i:i + 1])
        lbs = linear_blend_skinning(rest[i], model["skin_weights"], A, t)[0]
        out.append(np.linalg.norm(lbs - split["vertices"][rows][i], axis=-1).mean())
    return np.array(out)


"""The CMU exponential-map text format of Li et al. (CVPR 2018), as in data cmu_expmap_li2018.

One frame per line, comma-separated: columns 0-2 the root position, then 3 per joint, the
exponential map (axis * angle, radians) of each of the J joints (joint 0: the root's
orientation). The joint tree and bone offsets are not in the motion files; they come from a
skeleton.json beside the data (parent array, raw offsets in CMU ASF length units, 1/0.45 inch).

The 38-joint tree is the one of CMU's cgspeed BVH conversion: the ASF bones plus end sites,
each joint at the START of the ASF bone it is named after, "<bone>_end" at a bone's end. As in
that BVH, two ASF bones have no length here: the thorax (lowerneck and the clavicles start where
the thorax starts, at the end of upperback) and the wrists (lhand and lthumb start where lwrist
starts, at the end of lradius). End joints are kept as joints because the file gives them a
rotation column (zero in the data).

Rotation convention. The source code (src/forward_kinematics_cmu.py of the Li et al. repo) uses
row vectors: R_glob[j] = R(e_j) @ R_glob[parent], xyz[j] = offset[j] @ R_glob[parent] +
xyz[parent], with R(e) the usual Rodrigues matrix. Transposed to humotion's column vectors that
is W[j] = W[parent] @ R(e_j)^T, so the local rotation of joint j is R(-e_j), and offsets stay as
given. tests/test_expmap.py checks this against the row-vector formula computed in numpy.
Axes are CMU's (Y up, +Z forward, left = +X), which are humotion's; lengths are scaled to metres.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from humotion import rotations as rot
from humotion.io.errors import MotionFileError, file_stem, read_text
from humotion.motion import Motion
from humotion.skeleton import Skeleton

__all__ = ["read_expmap", "read_expmap_skeleton", "find_skeleton_json", "CMU_EXPMAP_JOINTS", "CMU_UNIT"]

CMU_UNIT = 0.0254 / 0.45  # metres per CMU ASF length unit (CMU FAQ)

CMU_EXPMAP_JOINTS = (
    "root",
    "lhipjoint", "lfemur", "ltibia", "lfoot", "ltoes", "ltoes_end",
    "rhipjoint", "rfemur", "rtibia", "rfoot", "rtoes", "rtoes_end",
    "lowerback", "upperback", "thorax", "lowerneck", "upperneck", "head", "head_end",
    "lclavicle", "lhumerus", "lradius", "lwrist", "lhand", "lfingers", "lfingers_end", "lthumb", "lthumb_end",
    "rclavicle", "rhumerus", "rradius", "rwrist", "rhand", "rfingers", "rfingers_end", "rthumb", "rthumb_end",
)
# The parent array these names belong to (that of the Li et al. skeleton.json).
_CMU_EXPMAP_PARENTS = (-1, 0, 1, 2, 3, 4, 5, 0, 7, 8, 9, 10, 11, 0, 13, 14, 15, 16, 17, 18, 15, 20, 21, 22, 23,
                       24, 25, 23, 27, 15, 29, 30, 31, 32, 33, 34, 32, 36)


def find_skeleton_json(path: str | Path) -> Path:
    """The skeleton.json for a motion file: in its folder or the nearest folder above it."""
    path = Path(path)
    folder = path.resolve().parent
    for place in (folder, *folder.parents):
        candidate = place / "skeleton.json"
        if candidate.is_file():
            return candidate
    raise MotionFileError(path, f"no skeleton.json found in {folder} or any folder above it; pass skeleton_json=PATH")


def read_expmap_skeleton(path: str | Path, units: float = CMU_UNIT) -> tuple[Skeleton, np.ndarray]:
    """(Skeleton in metres, (3,) root offset in metres) from a skeleton.json.

    The json holds "parent" (J ints, -1 for the root, parents first) and "offset_raw" (J x 3,
    file length units); optional "names" (J strings). Without names, the 38-joint CMU tree gets
    :data:`CMU_EXPMAP_JOINTS` and any other tree "joint0", "joint1", ...
    """
    path = Path(path)
    try:
        data = json.loads(read_text(path))
    except json.JSONDecodeError as error:
        raise MotionFileError(path, f"not valid JSON ({error.msg})", line=error.lineno) from None
    if not isinstance(data, dict) or "parent" not in data or "offset_raw" not in data:
        raise MotionFileError(path, "skeleton json needs 'parent' and 'offset_raw' entries")
    try:
        parents = [int(p) for p in data["parent"]]
        offsets = np.asarray(data["offset_raw"], dtype=np.float64)
    except (TypeError, ValueError):
        raise MotionFileError(path, "'parent' must be integers and 'offset_raw' rows of 3 numbers") from None
    joints = len(parents)
    if joints == 0 or offsets.shape != (joints, 3) or not np.isfinite(offsets).all():
        raise MotionFileError(path, f"'offset_raw' must be {joints} finite rows of 3 numbers, got shape {offsets.shape}")
    names = data.get("names")
    if names is None:
        names = CMU_EXPMAP_JOINTS if tuple(parents) == _CMU_EXPMAP_PARENTS else tuple(f"joint{j}" for j in range(joints))
    if not (isinstance(names, (list, tuple)) and len(names) == joints and all(isinstance(n, str) for n in names)):
        raise MotionFileError(path, f"'names' must be {joints} strings")
    try:
        skeleton = Skeleton(names=names, parents=parents, offsets=offsets * units)
    except ValueError as error:
        raise MotionFileError(path, f"bad skeleton: {error}") from None
    return skeleton, offsets[0] * units


def read_expmap(path: str | Path, skeleton_json: str | Path | None = None, fps: float = 120.0,
                units: float = CMU_UNIT) -> Motion:
    """Read an exp-map text file (.txt, optionally gzip-compressed) into a Motion in metres.

    skeleton_json: the skeleton file; found in the motion file's folder or above when None.
    fps: the files carry no rate; the CMU data is 120 Hz.
    units: metres per file length unit (CMU ASF units by default).
    Raises MotionFileError naming the file, 1-based line and problem (wrong column count,
    non-numeric, NaN or infinite values, empty file, ...).
    """
    path = Path(path)
    if not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0):
        raise MotionFileError(path, f"fps must be a positive number, got {fps!r}")
    skeleton, root_offset = read_expmap_skeleton(find_skeleton_json(path) if skeleton_json is None else skeleton_json, units)
    columns = 3 + 3 * skeleton.num_joints
    lines = read_text(path).split("\n")
    numbers = [i for i, line in enumerate(lines) if line.strip()]
    for i in numbers:
        found = lines[i].count(",") + 1
        if found != columns:
            raise MotionFileError(path, f"{found} comma-separated values, expected {columns} "
                                  f"(3 root position + 3 x {skeleton.num_joints} joints)", line=i + 1)
    try:
        values = np.array(",".join(lines[i] for i in numbers).split(","), dtype=np.float64).reshape(len(numbers), columns)
    except ValueError:
        for i in numbers:
            for field in lines[i].split(","):
                try:
                    float(field)
                except ValueError:
                    raise MotionFileError(path, f"non-numeric value {field.strip()[:30]!r}", line=i + 1) from None
        raise MotionFileError(path, "unreadable values") from None  # not reached
    bad = ~np.isfinite(values).all(axis=1)
    if bad.any():
        raise MotionFileError(path, "NaN or infinite value", line=numbers[int(np.argmax(bad))] + 1)
    frames = len(numbers)
    rotvecs = torch.from_numpy(values[:, 3:].reshape(frames, skeleton.num_joints, 3))
    local = rot.convert(-rotvecs, "rotvec", "quat")  # column-vector local = R(e)^T = R(-e)
    root = values[:, :3] * units + root_offset
    name = file_stem(path, ".txt")
    try:
        return Motion(skeleton=skeleton, rotations=local.float(), root_positions=root, fps=float(fps), name=name)
    except ValueError as error:  # values too large for float32
        raise MotionFileError(path, f"values out of range: {error}") from None

"""Geometric quality of posed bodies: local edge stretch against the rest mesh, per region, on a
standard set of real CMU poses (arms down, arms up, T, squat, sitting, reaching across, looking
over the shoulder), and the feet's height above the floor.

    poses = pose_set(mocap_root)                          # {name: (22, 4) canonical rotations}
    regions = region_masks(rest_vertices, rest_joints, names)   # {region: (V,) bool}
    stretch = edge_stretch(posed, rest, mesh_edges(faces))      # (B, E) distortion factors

The mean vertex error of a held-out test (bench/body_eval.py's tables) is blind to a few
vertices that fold into a peak; these measures look at the worst edges instead. A region is a
ball around its joints (radius scaled by the body's height), so it does not depend on the
skinning weights being judged. Edge stretch is reported as a distortion factor max(r, 1 / r) of
the length ratio r (1: the edge keeps its rest length; 2: doubled or halved).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

REGION_JOINTS = {
    "shoulders": (("clavicle", "shoulder01", "upperarm01"), 0.10),
    "armpits": (("clavicle", "shoulder01", "upperarm01"), 0.10),
    "neck": (("neck01", "neck02"), 0.07),
    "elbows": (("lowerarm01",), 0.07),
    "wrists": (("wrist",), 0.05),
    "hips": (("upperleg01",), 0.11),
    "knees": (("lowerleg01",), 0.08),
}
"""Region -> (rig bones, radius in metres for a 1.75 m body): the vertices within the radius of a
bone's rest joint (either side; unsided bones as named). The shoulders are the part of that ball
above the upper arm's joint (upperarm01; the tops of the shoulders, where a wrong clavicle makes
peaks), the armpits the part below it (which folds whenever an arm is lowered)."""


@dataclass(frozen=True)
class StandardPose:
    """One pose of the standard set: a frame of a real CMU take (ASF/AMC at 120 Hz).

    name; clip and asf: paths under the mocap root; frame: index at 120 Hz; what: the pose."""

    name: str
    clip: str
    asf: str
    frame: int
    what: str


POSE_SET = (
    StandardPose("arms_down", "cmu_mocgui_s02/02_01.amc", "cmu_mocgui_s02/02.asf", 220,
                 "walk, both arms hanging at the sides"),
    StandardPose("arms_up", "cmu_cyun9601/amc/01/01_11.amc.gz", "cmu_cyun9601/asf/01.asf", 2484,
                 "playground, both hands above the head"),
    StandardPose("t_pose", "cmu_cyun9601/amc/03/03_02.amc.gz", "cmu_cyun9601/asf/03.asf", 24,
                 "arms stretched out sideways"),
    StandardPose("squat", "cmu_sxaxmz/amc/105/105_41.amc.gz", "cmu_sxaxmz/asf/105.asf", 360,
                 "lowest pelvis with the feet on the ground and the hands below the head"),
    StandardPose("sitting", "cmu_cyun9601/amc/01/01_09.amc.gz", "cmu_cyun9601/asf/01.asf", 3636,
                 "playground, torso upright, thighs near level, hands low"),
    StandardPose("reach_across", "cmu_mocgui_s02/02_07.amc", "cmu_mocgui_s02/02.asf", 1332,
                 "swordplay, standing, a hand far across the body's midline"),
    StandardPose("look_over_shoulder", "cmu_cyun9601/amc/01/01_03.amc.gz", "cmu_cyun9601/asf/01.asf", 4332,
                 "playground, standing upright, head turned about 95 degrees from the pelvis"),
)
"""The standard pose set (CMU subject, take and frame at 120 Hz written out; chosen by scanning the
takes for the pose's geometric signature, bench/body_eval.py --pose-set)."""


def pose_set(mocap_root: str | Path, poses=POSE_SET) -> dict[str, torch.Tensor]:
    """{name: (22, 4) wxyz canonical local rotations} of the standard poses, read from the CMU
    takes under mocap_root (humotion's data folder's mocap/); the root's rotation is turned to
    face +Z (heading removed)."""
    from humotion import rotations as rot
    from humotion.body.posing import remove_heading
    from humotion.canonical import to_canonical
    from humotion.io import load_motion

    root = Path(mocap_root)
    out = {}
    for pose in poses:
        motion = load_motion(root / pose.clip, asf=root / pose.asf)
        canonical = to_canonical(motion)
        rotations = canonical.rotations[pose.frame].double().clone()
        world = rot.quat_to_matrix(rotations[:1])
        rotations[0] = rot.matrix_to_quat(remove_heading(world[:, None])[0] @ world[0])
        out[pose.name] = rotations.float()
    return out


def region_masks(rest_vertices, rest_joints, joint_names, height: float | None = None) -> dict[str, np.ndarray]:
    """{region: (V,) bool} of :data:`REGION_JOINTS` for one rest body: rest_vertices (V, 3),
    rest_joints (J, 3), metres; height (m, default the mesh's vertical extent) scales the radii."""
    vertices = np.asarray(rest_vertices, dtype=np.float64)
    joints = np.asarray(rest_joints, dtype=np.float64)
    names = list(joint_names)
    scale = (float(np.ptp(vertices[:, 1])) if height is None else height) / 1.75
    masks = {}
    for region, (bones, radius) in REGION_JOINTS.items():
        mask = np.zeros(len(vertices), dtype=bool)
        for bone in bones:
            for name in (f"{bone}.L", f"{bone}.R", bone):
                if name in names:
                    mask |= np.linalg.norm(vertices - joints[names.index(name)], axis=-1) < radius * scale
        if region in ("shoulders", "armpits"):
            above = np.zeros(len(vertices), dtype=bool)
            for side in ("L", "R"):
                joint = joints[names.index(f"upperarm01.{side}")]
                near = vertices[:, 0] * joint[0] > 0          # that side of the body
                above |= near & (vertices[:, 1] > joint[1])
            mask &= above if region == "shoulders" else ~above
        masks[region] = mask
    return masks


def mesh_edges(faces) -> np.ndarray:
    """(E, 2) the unique edges of triangles faces (n, 3), smaller index first."""
    faces = np.asarray(faces, dtype=np.int64)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(edges, axis=1), axis=0)


def edge_stretch(posed, rest, edges) -> np.ndarray:
    """(B, E) distortion factors max(r, 1 / r) of the edges' length ratios r = posed / rest:
    posed (B, V, 3), rest (V, 3) or (B, V, 3), edges (E, 2)."""
    posed = np.asarray(posed, dtype=np.float64)
    rest = np.asarray(rest, dtype=np.float64)
    length = np.linalg.norm(posed[..., edges[:, 0], :] - posed[..., edges[:, 1], :], axis=-1)
    rest_length = np.linalg.norm(rest[..., edges[:, 0], :] - rest[..., edges[:, 1], :], axis=-1)
    ratio = length / np.maximum(rest_length, 1e-9)
    return np.maximum(ratio, 1.0 / np.maximum(ratio, 1e-9))


def region_stretch(stretch: np.ndarray, edges: np.ndarray, mask: np.ndarray) -> dict[str, float]:
    """Worst and 99th-percentile distortion (:func:`edge_stretch`, (B, E) or (E,)) over the edges
    with an end in the region mask (V,) bool."""
    keep = mask[edges[:, 0]] | mask[edges[:, 1]]
    values = np.asarray(stretch)[..., keep]
    return {"worst": float(values.max()), "p99": float(np.quantile(values, 0.99))}


def region_errors(errors, mask: np.ndarray) -> dict[str, float]:
    """Worst and 99th-percentile vertex error (same unit as errors (B, V) or (V,)) in a region."""
    values = np.asarray(errors)[..., mask]
    return {"worst": float(values.max()), "p99": float(np.quantile(values, 0.99))}


def render_poses(meshes, faces, titles, path, size: float = 1.6, dpi: int = 60, top: float | None = None) -> None:
    """A PNG of posed meshes (list of (V, 3), m, y up, facing +Z) seen from the front (top row)
    and the left side (bottom row), orthographic, flat-shaded by one light (matplotlib, faces
    drawn back to front); top: show only the top `top` metres of each mesh (a close-up)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    faces = np.asarray(faces)
    fig, axes = plt.subplots(2, len(meshes), figsize=(size * len(meshes), 2 * size), squeeze=False)
    for column, (vertices, title) in enumerate(zip(meshes, titles)):
        vertices = np.asarray(vertices, dtype=np.float64)
        vertices = vertices - (vertices.max(0) + vertices.min(0)) / 2
        for row, (right, depth) in enumerate(((0, 2), (2, 0))):
            sign = 1.0 if row == 0 else -1.0        # side view: looking along -X, +Z to the left
            x, y, z = sign * vertices[:, right], vertices[:, 1], vertices[:, depth]
            normal = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]])
            normal /= np.linalg.norm(normal, axis=1, keepdims=True) + 1e-12
            view = np.zeros(3)
            view[depth] = 1.0
            light = view + np.array([0.0, 0.5, 0.0]) + 0.3 * np.eye(3)[right] * sign
            shade = 0.25 + 0.75 * np.clip(normal @ (light / np.linalg.norm(light)), 0.0, 1.0)
            order = np.argsort(z[faces].mean(1))
            order = order[(normal @ view)[order] > 0]
            colour = np.clip(np.array([0.78, 0.74, 0.70]) * shade[order, None], 0.0, 1.0)
            ax = axes[row, column]
            ax.add_collection(PolyCollection(np.stack([x, y], 1)[faces[order]], facecolors=colour, edgecolors=colour,
                                             linewidths=0.1))
            if top is None:
                half = max(np.ptp(x), np.ptp(y)) / 2 + 0.05
                ax.set_xlim(-half, half)
                ax.set_ylim(-half, half)
            else:
                ax.set_xlim(x.mean() - top / 2 - 0.02, x.mean() + top / 2 + 0.02)
                ax.set_ylim(y.max() - top, y.max() + 0.02)
            ax.set_aspect("equal")
            ax.axis("off")
            if row == 0:
                ax.set_title(title, fontsize=7)
    fig.subplots_adjust(wspace=0.02, hspace=0.02, left=0, right=1, top=0.93, bottom=0)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)

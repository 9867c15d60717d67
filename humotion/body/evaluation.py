"""Evaluating a body model on registered meshes of a body data folder (:mod:`humotion.body.dataset`).

    meshes = load_meshes("runs/body_data", "low", "test_shapes")
    errors = vertex_errors(body, meshes)                 # (M, V) mm
    summarise(errors, body, meshes)                      # {"all": .., "body": .., "face": .., "hands": .., "elbows": ..}

Protocol: each mesh's shape latent is the shape encoder's mean for its subject's rest mesh (the
model's input, per the spec: the rest shape in the neutral A pose), its expression latent the
expression encoder's mean for its expression offsets, its pose the data's pose parameters
("given", as they are, even where a held-out pose leaves the joint limits), or those refined by
L-BFGS within the joint limits with the model fixed ("fitted", what a registration error usually
means). Errors are per-vertex distances to the registered mesh.
"""

from __future__ import annotations

import numpy as np
import torch

from humotion import rotations as rot
from humotion.body import files
from humotion.body.fitting import fit_pose_to_vertices
from humotion.body.model import REGIONS, BodyModel
from humotion.body.skinning import GAP_JOINTS, blend_zones


def load_meshes(folder, resolution: str, split: str, max_meshes: int | None = None, shapes=None) -> dict:
    """One split's meshes (its first max_meshes; only those of the subjects `shapes` (shape ids)
    when given) as float32 tensors: vertices (M, V, 3), rest_vertices (M, V, 3) (the
    subject's neutral rest mesh), rest_joints (M, J, 3), expression_offsets (M, V, 3),
    rotvec (M, J, 3), translation (M, 3), shape_id, mesh_id; plus zones {name: (V,) bool} (the
    joint blend zones of :data:`GAP_JOINTS` under Anny's weights)."""
    model = files.load_model_file(folder, resolution)
    split_data = files.load_split(folder, resolution, split)
    rows = np.arange(len(split_data["shape_id"]))
    if shapes is not None:
        rows = rows[np.isin(split_data["shape_id"], np.asarray(shapes))]
    rows = rows[:max_meshes]
    shape_id = split_data["shape_id"][rows]
    offsets = files.expression_offsets(model, split_data["expression"][rows])
    rotations = torch.as_tensor(split_data["rotations"][rows])
    zones = blend_zones(model["skin_weights"], model["joint_names"], model["parents"])
    return {
        "vertices": torch.as_tensor(split_data["vertices"][rows]),
        "rest_vertices": torch.as_tensor(model["rest_vertices"][shape_id]),
        "rest_joints": torch.as_tensor(model["rest_joints"][shape_id]),
        "expression_offsets": torch.as_tensor(offsets),
        "rotvec": rot.convert(rotations.double(), "quat", "rotvec").float(),
        "translation": torch.as_tensor(split_data["translation"][rows]),
        "shape_id": torch.as_tensor(shape_id), "mesh_id": torch.as_tensor(split_data["mesh_id"][rows]),
        "zones": {k: torch.as_tensor(v) for k, v in zones.items()},
    }


def vertex_errors(body: BodyModel, meshes: dict, fit_pose: bool = False, correctives: bool = True,
                  iterations: int = 20, batch: int = 32, rest: str = "encoded") -> torch.Tensor:
    """(M, V) per-vertex distances (mm) of the model's meshes from the registered ones (see the
    module docstring). rest: "encoded" (decode the encoder's latent) or "true" (pose the
    subject's actual rest mesh: skinning, correctives and joints only)."""
    out = []
    for start in range(0, len(meshes["vertices"]), batch):
        rows = slice(start, start + batch)
        with torch.no_grad():
            if rest == "true":
                rest_vertices = meshes["rest_vertices"][rows]
            else:
                mu, _ = body.encode_shape(meshes["rest_vertices"][rows])
                rest_vertices = body.decode_shape(mu)
            expression, _ = body.encode_expression(meshes["expression_offsets"][rows])
            pose, translation = meshes["rotvec"][rows], meshes["translation"][rows]
        if fit_pose:
            free, translation, _, _ = fit_pose_to_vertices(body, meshes["vertices"][rows], rest_vertices,
                                                           body.limits.to_free(pose), translation, expression,
                                                           iterations, correctives)
            pose = body.limits.to_matrix(free)
        with torch.no_grad():
            posed = body(expression=expression, pose=pose, translation=translation,
                         rest_vertices=rest_vertices, correctives=correctives).vertices
            out.append((posed - meshes["vertices"][rows]).norm(dim=-1) * 1000.0)
    return torch.cat(out)


def summarise(errors: torch.Tensor, body: BodyModel, meshes: dict | None = None) -> dict[str, float]:
    """Mean of errors (M, V) in mm (per mesh and vertex, :func:`vertex_errors`) over all vertices,
    per region (body, face, hands) and, given the meshes' zones, per joint blend zone (shoulders,
    elbows, wrists, hips, knees)."""
    summary = {"all": float(errors.mean())}
    for region in REGIONS:
        summary[region] = float(errors[:, body.region(region)].mean())
    if meshes is not None:
        for zone in GAP_JOINTS:
            summary[zone] = float(errors[:, meshes["zones"][zone]].mean())
    return summary

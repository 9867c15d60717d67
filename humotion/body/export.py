"""A body of the learned body model in the export frame, posed by a motion and made into a
skinned glTF character: what `humotion body`, `humotion capture --body` and the live avatar share.

The body: :func:`rest_body` of a shape latent (from measurements, :func:`body_measurements`). The
motion is mapped onto humotion's canonical body, then onto the body's 76-joint rig
(:meth:`BodyModel.pose_from_canonical`); its root trajectory is scaled by the ratio of the body's
leg length to the motion's, its feet put on the floor on every frame with a foot contact
(:func:`pose_motion`).

The export frame: metres, Y up, facing +Z, the rest (A-pose) body's soles on y = 0 (the model's
own frame shifted up, see :func:`rest_body`). The glTF file holds the rest mesh bound to the rig
(rest-pose inverse bind matrices; skinning weights: with 8 joints per vertex the model's learned
ones, with 4 ones fitted to skin like them, :mod:`humotion.body.skin_export`), the pose
correctives as morph targets whose weights are animated (so the file reproduces the model's
pose-dependent shapes, not only its skinning), and the motion as joint rotations plus the root's
translation. :func:`body_gltf` builds it; the tests evaluate the file's skin and compare it with
the model's vertices.
"""

from __future__ import annotations

from __future__ import annotations

from dataclasses import dataclass

import torch
from tqdm.auto import tqdm

from humotion import rotations as rot
from humotion.body.checks import checked
from humotion.body.floor import floor_offsets, lowest_foot_points
from humotion.body.model import BodyModel
from humotion.body.skin_export import four_joint_weights
from humotion.canonical import JOINTS, to_canonical
from humotion.capture.template import typical_bmi, typical_height
from humotion.io.gltf import SkinnedMesh
from humotion.io.obj import vertex_normals
from humotion.motion import Motion
from humotion.skeleton import Skeleton


COLOR = (0.78, 0.74, 0.70)
"""The glTF material's base colour (RGB in [0, 1]): a light clay, non-metallic."""


# -- the body's shape ----------------------------------------------------------------------------

def body_measurements(height: float | None, weight: float | None, sex: str | None = None,
                      age: float | None = None) -> tuple[float, float]:
    """(height m, weight kg) of a body: those given; a missing height is typical of sex and age
    (:func:`~humotion.capture.template.typical_height`; neither given: 1.65 m), a missing weight
    the typical BMI of sex and age at the height (so with neither given, their median weight).
    ValueError for an unknown sex or an age under 2 or over 120 years."""
    typical = typical_bmi(sex, age)   # checks sex and age whatever is given
    height = typical_height(sex, age) if height is None else height
    return height, typical * height ** 2 if weight is None else weight


# -- the rest body in the export frame -----------------------------------------------------------

@dataclass
class RestBody:
    """One body at rest in the export frame (the model's frame lifted by `lift` metres along Y,
    so the rest body's lowest vertex is on y = 0).

    model; shape (1, shape_latent); vertices (V, 3) and joints (J, 3) of the rest (A-pose)
    mesh, metres; lift: metres added to the model frame's Y."""

    model: BodyModel
    shape: torch.Tensor
    vertices: torch.Tensor
    joints: torch.Tensor
    lift: float

    def measurements(self) -> dict[str, float]:
        """Height (m), weight (kg) and BMI of the rest mesh, as the model measures them."""
        return {k: float(v) for k, v in self.model.measure(self.vertices[None]).items()}

    def skeleton(self) -> Skeleton:
        """The 76-joint rig at rest: offsets from each parent (the root's: its rest position)."""
        parents = self.model.parents
        joints = self.joints.double().numpy()
        offsets = joints - joints[[max(p, 0) for p in parents]]
        offsets[0] = joints[0]
        return Skeleton(self.model.joint_names, parents, offsets)


def rest_body(model: BodyModel, shape: torch.Tensor) -> RestBody:
    """The body of a shape latent (1, shape_latent) at rest, in the export frame."""
    with torch.no_grad():
        rest = model.decode_shape(checked("shape", shape, (model.config.shape_latent,), model.template))[0]
    lift = -float(rest[:, 1].min())
    vertices = rest + torch.tensor([0.0, lift, 0.0])
    return RestBody(model, shape, vertices, model.rest_joints(vertices[None])[0], lift)


# -- posing ----------------------------------------------------------------------------------

def pose_motion(body: RestBody, motion: Motion, floor: bool = True,
                overrides: dict | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """A motion on the body: local rig rotations (T, J, 3, 3) and the root's world positions
    (T, 3) in the export frame.

    The motion goes to the canonical body (:func:`humotion.canonical.to_canonical`, its key joints
    found as the retargeter finds them, with overrides as humotion.retarget.Rig.of takes them;
    ValueError naming the joints it cannot find), then onto the rig (:meth:`BodyModel.pose_from_canonical`). Its
    root (pelvis) trajectory is scaled by the body's leg length over the motion's (rest pelvis
    height above the ankles) and moved vertically so that the ankles stand on the floor at the
    body's rest ankle height: the motion's ankle height on the ground is taken as the 5th
    percentile over frames of the lower ankle's height (robust to a floor not at y = 0 in the
    file, and to a few frames below it). Then, with floor=True, each frame is moved vertically so
    that the feet in contact with the floor stand on it (:func:`feet_on_floor`): the body's own
    feet, not the source's ankles, on every frame, not only the first."""
    canonical = to_canonical(motion, overrides=overrides)
    rotations = body.model.pose_from_canonical(canonical.rotations, body.shape)
    ankles = [JOINTS.index("left_ankle"), JOINTS.index("right_ankle")]
    source_rest = canonical.skeleton.rest_positions()
    source_leg = float(source_rest[0, 1] - source_rest[ankles, 1].mean())
    names = body.model.joint_names
    body_ankle = float(body.joints[[names.index("foot.L"), names.index("foot.R")], 1].mean())
    scale = (float(body.joints[0, 1]) - body_ankle) / source_leg
    ground = torch.quantile(canonical.world_positions()[:, ankles, 1].amin(1), 0.05)
    root = canonical.root_positions * scale
    root[:, 1] += body_ankle - scale * ground
    if floor:
        root[:, 1] += torch.as_tensor(feet_on_floor(body, rotations, root, motion.fps)[0], dtype=root.dtype)
    return rotations, root


def feet_on_floor(body: RestBody, rotations: torch.Tensor, root: torch.Tensor, fps: float):
    """(offsets (T,) m, contacts (T, 2) bool): the vertical root offsets that keep the body's feet
    on the floor (y = 0) on every frame where a foot is in contact, from the feet's lowest
    vertices (:mod:`humotion.body.floor`); rotations (T, J, 3, 3) local rig rotations, root (T, 3)
    root world positions (export frame), fps the motion's frame rate."""
    points = lowest_foot_points(body.model, body.vertices, body.joints, rotations, root - body.joints[0])
    return floor_offsets(points.double().numpy(), fps)


def posed_vertices(body: RestBody, rotations: torch.Tensor, root: torch.Tensor, correctives: bool = True,
                   chunk: int = 64, progress: bool = True) -> torch.Tensor:
    """(T, V, 3) vertices of the body posed by rig rotations (T, J, 3, 3) with its root at
    world positions root (T, 3), export frame, metres; chunk frames at a time (progress bar)."""
    out = []
    translation = root - body.joints[0]
    with torch.no_grad(), tqdm(total=len(rotations), desc="posing", unit="frame", disable=not progress) as bar:
        for start in range(0, len(rotations), chunk):
            stop = start + chunk
            out.append(body.model(rest_vertices=body.vertices[None], pose=rotations[start:stop],
                                  translation=translation[start:stop], correctives=correctives).vertices)
            bar.update(len(out[-1]))
    return torch.cat(out)


# -- the files ---------------------------------------------------------------------------------

def body_gltf(body: RestBody, rotations: torch.Tensor, root: torch.Tensor, fps: float, name: str,
              influences: int = 4, correctives: bool = True) -> tuple[Motion, SkinnedMesh]:
    """The rig's motion and the skinned body mesh that :func:`humotion.io.gltf.write_gltf` writes.

    rotations (T, J, 3, 3) local rig rotations; root (T, 3) root world positions (m, export
    frame); fps; name of the motion. The mesh: the rest mesh, skinning weights (`influences` per
    vertex in the file: 8, the model's learned weights; 4, weights fitted to skin like them,
    :func:`~humotion.body.skin_export.four_joint_weights`), smooth normals and, with
    correctives, the model's pose correctives as morph targets: the correctives are a linear map
    (regressor) of a hidden pose code, so each hidden unit's column is a target (offsets scaled
    by the body's height as the model scales them) and the code of each frame its weights (zero
    at rest)."""
    model = body.model
    motion = Motion(body.skeleton(), rot.matrix_to_quat(rotations), root, fps, name=name)
    targets = weights = None
    if correctives and model.correctives is not None:
        c = model.correctives
        with torch.no_grad():
            targets = (c.targets() * model.corrective_scale(body.vertices[None])).numpy()
            weights = c.hidden(rotations).numpy()
    vertices = body.vertices.numpy()
    faces = model.faces.numpy()
    facts = body.measurements()
    extras = {"humotion_body": {"resolution": model.config.resolution, "height_m": round(facts["height"], 4),
                                "weight_kg": round(facts["weight"], 2), "shape_latent": body.shape[0].tolist(),
                                "lift_m": body.lift}}
    skin = model.skinning_weights()
    if influences == 4:
        skin = four_joint_weights(skin, body.vertices, body.joints, model.parents, model.limits)
    mesh = SkinnedMesh(vertices, faces, skin.numpy(), influences=influences,
                       normals=vertex_normals(vertices, faces), morph_targets=targets, morph_weights=weights,
                       morph_names=None if targets is None else [f"corrective_{k:02d}" for k in range(len(targets))],
                       color=COLOR, name="body", extras=extras)
    return motion, mesh


def animated_body(model: BodyModel, height: float, motion: Motion) -> tuple[RestBody, Motion, SkinnedMesh]:
    """A body of this standing height (metres; of typical weight at that height,
    :func:`body_measurements`) moved by motion (any rig humotion maps onto the canonical body):
    the body at rest, and the rig's motion and skinned mesh as :func:`body_gltf` makes them (4
    joints per vertex, correctives as morph targets) for humotion.io.gltf.write_gltf. ValueError
    for a height outside the model's range or a skeleton it cannot map."""
    body = rest_body(model, model.shape_from_measurements(*body_measurements(height, None)))
    rotations, root = pose_motion(body, motion)
    return (body, *body_gltf(body, rotations, root, motion.fps, motion.name or "body"))

"""`humotion body`: a body of the learned body model as a skinned glTF character, optionally
animated by a motion file, an OBJ, and a view in the browser.

    humotion body -o alice.glb --height 1.68 --weight 60 --motion walk.bvh --obj --view

The body: from --height/--weight (the model's anthropometric controls), from --sex/--age (their
typical height and weight where not given), from a shape latent (--latent) or a random one
(--sample). The motion is mapped onto humotion's canonical body, then onto the body's 76-joint rig
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

from dataclasses import dataclass
from pathlib import Path

import click
import numpy as np
import torch
from tqdm.auto import tqdm

from humotion import rotations as rot
from humotion.body.floor import floor_offsets, lowest_foot_points
from humotion.body.model import BodyModel, load_body_model
from humotion.body.skin_export import four_joint_weights
from humotion.canonical import JOINTS, to_canonical
from humotion.capture.template import typical_bmi, typical_height
from humotion.io import MotionFileError, load_motion
from humotion.io.errors import OutputPathError
from humotion.io.gltf import SkinnedMesh, write_gltf
from humotion.io.obj import vertex_normals, write_obj
from humotion.motion import Motion
from humotion.outputs import check_outputs, force_option
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
        rest = model.decode_shape(model.checked("shape", shape, (model.config.shape_latent,)))[0]
    lift = -float(rest[:, 1].min())
    vertices = rest + torch.tensor([0.0, lift, 0.0])
    return RestBody(model, shape, vertices, model.rest_joints(vertices[None])[0], lift)


# -- posing ----------------------------------------------------------------------------------

def pose_motion(body: RestBody, motion: Motion, floor: bool = True,
                overrides: dict | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """A motion on the body: local rig rotations (F, J, 3, 3) and the root's world positions
    (F, 3) in the export frame.

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
    source_leg = source_rest[0, 1] - source_rest[ankles, 1].mean()
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
    """(offsets (F,) m, contacts (F, 2) bool): the vertical root offsets that keep the body's feet
    on the floor (y = 0) on every frame where a foot is in contact, from the feet's lowest
    vertices (:mod:`humotion.body.floor`); rotations (F, J, 3, 3) local rig rotations, root (F, 3)
    root world positions (export frame), fps the motion's frame rate."""
    points = lowest_foot_points(body.model, body.vertices, body.joints, rotations, root - body.joints[0])
    return floor_offsets(points.double().numpy(), fps)


def posed_vertices(body: RestBody, rotations: torch.Tensor, root: torch.Tensor, correctives: bool = True,
                   chunk: int = 64, progress: bool = True) -> torch.Tensor:
    """(F, V, 3) vertices of the body posed by rig rotations (F, J, 3, 3) with its root at
    world positions root (F, 3), export frame, metres; chunk frames at a time (progress bar)."""
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

    rotations (F, J, 3, 3) local rig rotations; root (F, 3) root world positions (m, export
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


def output_paths(out: str) -> tuple[Path, Path]:
    """(glTF path, OBJ path) of -o OUT: OUT itself when it ends in .glb or .gltf, else OUT.glb;
    the OBJ beside it with the suffix .obj."""
    path = Path(out)
    if path.suffix.lower() not in (".glb", ".gltf"):
        path = path.with_name(path.name + ".glb")
    return path, path.with_suffix(".obj")


# -- the command -------------------------------------------------------------------------------

EPILOG = """\b
Examples:
  humotion body -o alice --height 1.68 --weight 60 --obj          # alice.glb, alice.obj (A pose)
  humotion body -o kid.glb --sex female --age 8                   # typical height and weight
  humotion body -o walker.glb --sample 3 --motion 02_01.amc --asf 02.asf --view
  humotion body -o bob.gltf --latent bob_shape.npy --motion take.bvh --fps 30 --resolution full

\b
Writes OUT.glb (or OUT.gltf): the body's mesh skinned to its 76-joint rig (rest A pose, Y up,
facing +Z, soles on y = 0), the model's pose correctives as animated morph targets, and with
--motion the motion as an animation (joint rotations, root translation); its rig's key joints
are found as `humotion retarget` finds them (--overrides names those it misses). --obj adds OUT.obj:
the rest mesh, or the first frame of the motion. Height and weight range: what the model was
trained on (printed when out of range).
"""


def _shape(model: BodyModel, height, weight, sex, age, latent, sample) -> tuple[torch.Tensor, str]:
    """The shape latent (1, shape_latent) the options ask for, and how it was chosen."""
    chosen = [name for name, value in (("--latent", latent), ("--sample", sample)) if value is not None]
    measures = [name for name, value in (("--height", height), ("--weight", weight), ("--sex", sex), ("--age", age))
                if value is not None]
    if len(chosen) + bool(measures) > 1:
        raise click.UsageError(f"{' and '.join(chosen + measures[:1])} choose the body in different ways; give one")
    if latent is not None:
        try:
            shape = torch.as_tensor(np.load(latent, allow_pickle=False), dtype=torch.float32).reshape(-1, model.config.shape_latent)
        except (ValueError, OSError, RuntimeError) as error:
            raise click.BadParameter(f"{latent}: not a .npy array of {model.config.shape_latent} numbers ({error})",
                                     param_hint="--latent") from None
        if len(shape) != 1 or not torch.isfinite(shape).all():
            raise click.BadParameter(f"{latent}: needs one finite shape latent of {model.config.shape_latent} numbers",
                                     param_hint="--latent")
        return shape, f"shape latent from {latent}"
    if sample is not None:
        return model.sample_shapes(1, torch.Generator().manual_seed(sample)), f"random shape, seed {sample}"
    try:
        target = body_measurements(height, weight, sex, age)
    except ValueError as error:  # typical_height's checks of --sex / --age
        raise click.BadParameter(str(error), param_hint="--age") from None
    try:
        shape = model.shape_from_measurements(*target)
    except ValueError as error:  # outside the trained range; say where the numbers came from
        typical = (height is None or weight is None) and (sex is not None or age is not None)
        origin = f" (typical of --sex/--age: {target[0]:.2f} m, {target[1]:.1f} kg)" if typical else ""
        raise click.BadParameter(f"{error}{origin}", param_hint="/".join(measures) or "--height/--weight") from None
    return shape, f"asked for {target[0]:.2f} m, {target[1]:.1f} kg"


@click.command("body", epilog=EPILOG)
@click.option("-o", "--out", required=True, type=click.Path(dir_okay=False), help="glTF file to write (.glb or .gltf; .glb added otherwise).")
@click.option("--height", type=float, help="Standing height, metres.")
@click.option("--weight", type=float, help="Body weight, kg (default: the typical BMI of --sex/--age at the height).")
@click.option("--sex", type=click.Choice(("female", "male")), help="For a typical height and weight (CDC growth-chart medians).")
@click.option("--age", type=float, help="Years, 2 or more, for a typical height and weight (adults: the 20-year medians).")
@click.option("--latent", type=click.Path(exists=True, dir_okay=False), help="Shape latent (.npy, 16 numbers) instead of measurements.")
@click.option("--sample", type=int, metavar="SEED", help="A random body shape (the training subjects' distribution).")
@click.option("--resolution", type=click.Choice(("low", "full")), default="low", show_default=True,
              help="Mesh resolution: low (1,229 vertices) or full (13,718; if its weights are installed).")
@click.option("--motion", type=click.Path(exists=True, dir_okay=False), help="Motion file to animate the body with (BVH, AMC, glTF, ...).")
@click.option("--asf", type=click.Path(exists=True, dir_okay=False), help="ASF skeleton for an AMC motion (default: found beside it).")
@click.option("--source-fps", type=float, help="Frame rate of motion formats that store none (AMC, exp-map). Default 120.")
@click.option("--units", default="auto", show_default=True, help="BVH length unit of the motion: auto, m, cm, mm, inch, cmu.")
@click.option("--fps", "out_fps", type=float, help="Resample the motion to this frame rate (default: its own).")
@click.option("--overrides", type=click.Path(exists=True, dir_okay=False),
              help="Override file (JSON/TOML) naming the motion rig's key joints, as for `humotion retarget`.")
@click.option("--influences", type=click.Choice(("4", "8")), default="4", show_default=True,
              help="Joints per vertex in the file: 4 (every engine; fitted to the model, within a few mm) or 8 "
                   "(exact to the model; Blender, Unreal).")
@click.option("--correctives/--no-correctives", default=True, show_default=True,
              help="Pose correctives as animated morph targets (off: plain skinning).")
@click.option("--obj", "write_obj_file", is_flag=True, help="Also write OUT.obj: the rest mesh, or the motion's first frame.")
@click.option("--view/--no-view", default=False, show_default=True, help="Show the posed body in the browser viewer.")
@click.option("--port", default=8080, show_default=True)
@force_option
def body_command(out, height, weight, sex, age, latent, sample, resolution, motion, asf, source_fps, units, out_fps,
                 overrides, influences, correctives, write_obj_file, view, port, force):
    """Make a body with the learned body model and write it as a skinned glTF character."""
    gltf_path, obj_path = output_paths(out)
    check_outputs([gltf_path, obj_path if write_obj_file else None], inputs=[motion, asf, latent, overrides], force=force)
    torch.set_num_threads(1)
    source = _read_motion(motion, asf, source_fps, units, out_fps) if motion else None
    try:
        model = load_body_model(resolution)
    except FileNotFoundError as error:
        raise click.BadParameter(f"{resolution}: {error}", param_hint="--resolution") from None
    shape, how = _shape(model, height, weight, sex, age, latent, sample)
    body = rest_body(model, shape)
    facts = body.measurements()
    click.echo(f"body ({how}): {facts['height']:.3f} m, {facts['weight']:.1f} kg, BMI {facts['bmi']:.1f}, "
               f"{model.num_vertices} vertices, {model.num_joints} joints")
    if source is not None:
        from humotion.retarget.parts import load_overrides

        try:
            rotations, root = pose_motion(body, source, overrides=overrides and load_overrides(overrides))
        except ValueError as error:  # a skeleton whose key joints cannot be found, a bad override file
            raise click.BadParameter(f"{motion}: {error}", param_hint="--motion") from None
        fps, name = source.fps, source.name or Path(motion).name.split(".")[0]
    else:
        rotations, root = torch.eye(3).expand(1, model.num_joints, 3, 3), body.joints[:1]
        fps, name = 30.0, "rest"

    rig_motion, mesh = body_gltf(body, rotations, root, fps, name, int(influences), correctives)
    try:
        write_gltf(rig_motion, gltf_path, mesh=mesh)
        click.echo(f"wrote {gltf_path}: {rig_motion.num_frames} frame(s) at {fps:g} fps, {influences} joints per vertex"
                   + (f", {len(mesh.morph_targets)} corrective morph targets" if mesh.morph_targets is not None else ""))
        if write_obj_file:
            first = posed_vertices(body, rotations[:1], root[:1], correctives, progress=False)[0]
            write_obj(obj_path, first.numpy(), model.faces.numpy(), name="body")
            click.echo(f"wrote {obj_path}: {'the first frame of the motion' if source is not None else 'the rest pose'}")
    except OutputPathError as error:  # checked before the work; the folder changed since
        raise click.ClickException(str(error)) from None
    if view:
        import webbrowser

        from humotion.viewer import MotionViewer

        vertices = posed_vertices(body, rotations, root, correctives, progress=len(rotations) > 1)
        viewer = MotionViewer([rig_motion], [f"body: {name}"], port=port, meshes=[(vertices.numpy(), model.faces.numpy())])
        webbrowser.open(viewer.url)
        viewer.run()  # prints the address; serves until Ctrl-C


def _read_motion(path: str, asf, source_fps, units, out_fps) -> Motion:
    """The --motion file, resampled to --fps; BadParameter naming the file and its problem
    (unreadable, NaN or infinite values, ...)."""
    try:
        motion = load_motion(path, asf=asf, fps=source_fps, units=units)
        return motion.resample(out_fps) if out_fps else motion
    except (MotionFileError, ValueError) as error:
        raise click.BadParameter(str(error) if str(path) in str(error) else f"{path}: {error}",
                                 param_hint="--motion") from None

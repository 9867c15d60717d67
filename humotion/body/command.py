"""`humotion body`: a body of the learned body model as a skinned glTF character, optionally
animated by a motion file, an OBJ, and a view in the browser.

    humotion body -o alice.glb --height 1.68 --weight 60 --motion walk.bvh --obj --view

The body: from --height/--weight (the model's anthropometric controls), from --sex/--age (their
typical height and weight where not given), from a shape latent (--latent) or a random one
(--sample); posed and written by :mod:`humotion.body.export`.

Also the body model's other command lines: `humotion train body`, and the training data's
``python -m humotion.body.command data`` (:func:`body_data_command`) and ``python -m
humotion.body.command rest-shapes`` (:func:`body_rest_shapes_command`).
"""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path

import click
import numpy as np
import torch

from humotion.body.export import body_gltf, body_measurements, pose_motion, posed_vertices, rest_body
from humotion.body import files
from humotion.body.dataset import LOW_TOPOLOGIES, Settings, generate
from humotion.body.rest_shapes import make_rest_shapes
from humotion.body.model import BodyConfig, BodyModel, load_body_model
from humotion.body.train import BodyTrainConfig, train
from humotion.io import MotionFileError, load_motion
from humotion.io.errors import OutputPathError
from humotion.io.gltf import write_gltf
from humotion.io.obj import write_obj
from humotion.motion import Motion
from humotion.options import config_options, echo_summary, input_options, reported, view_options
from humotion.outputs import check_outputs, force_option


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
@input_options
@click.option("--fps", "out_fps", type=float, help="Resample the motion to this frame rate (default: its own).")
@click.option("--overrides", type=click.Path(exists=True, dir_okay=False),
              help="Override file (JSON/TOML) naming the motion rig's key joints, as for `humotion retarget`.")
@click.option("--influences", type=click.Choice(("4", "8")), default="4", show_default=True,
              help="Joints per vertex in the file: 4 (every engine; fitted to the model, within a few mm) or 8 "
                   "(exact to the model; Blender, Unreal).")
@click.option("--correctives/--no-correctives", default=True, show_default=True,
              help="Pose correctives as animated morph targets (off: plain skinning).")
@click.option("--obj", "write_obj_file", is_flag=True, help="Also write OUT.obj: the rest mesh, or the motion's first frame.")
@view_options(help="Show the posed body in the browser viewer.")
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
    with reported(OutputPathError):   # checked before the work; the folder may have changed since
        write_gltf(rig_motion, gltf_path, mesh=mesh)
        click.echo(f"wrote {gltf_path}: {rig_motion.num_frames} frame(s) at {fps:g} fps, {influences} joints per vertex"
                   + (f", {len(mesh.morph_targets)} corrective morph targets" if mesh.morph_targets is not None else ""))
        if write_obj_file:
            first = posed_vertices(body, rotations[:1], root[:1], correctives, progress=False)[0]
            write_obj(obj_path, first.numpy(), model.faces.numpy(), name="body")
            click.echo(f"wrote {obj_path}: {'the first frame of the motion' if source is not None else 'the rest pose'}")
    if view:
        from humotion.viewer import serve

        vertices = posed_vertices(body, rotations, root, correctives, progress=len(rotations) > 1)
        serve([rig_motion], [f"body: {name}"], port=port, open_browser=True, meshes=[(vertices.numpy(), model.faces.numpy())])


def _read_motion(path: str, asf, source_fps, units, out_fps) -> Motion:
    """The --motion file, resampled to --fps; BadParameter naming the file and its problem
    (unreadable, NaN or infinite values, ...)."""
    try:
        motion = load_motion(path, asf=asf, fps=source_fps, units=units)
        return motion.resample(out_fps) if out_fps else motion
    except (MotionFileError, ValueError) as error:
        raise click.BadParameter(str(error) if str(path) in str(error) else f"{path}: {error}",
                                 param_hint="--motion") from None


@click.command("body", context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@config_options(BodyTrainConfig, "data_root", "resolution", "out_dir", "epochs", "steps", "batch_size", "lr", "lr_final",
                data_root={"decls": ("--data", "data_root"), "type": click.Path(file_okay=False)},
                resolution={"type": click.Choice(files.RESOLUTIONS)},
                out_dir={"decls": ("--out", "out_dir"), "default": None,
                         "help": "Output folder (checkpoints, log, weights)  [default: runs/body/<resolution>]."})
@config_options(BodyConfig, "shape_latent", "expression_latent", "correctives")
@config_options(BodyTrainConfig, "pose_every", "pose_start", "pose_iterations", "warmup_steps", "seed", "device",
                "threads", "checkpoint_every", "resume")
def train_body_command(resolution, out_dir, shape_latent, expression_latent, correctives, **options):
    """Train the learned body model (shape and expression VAEs, joint regressor, pose
    correctives, skinning weights) end to end on registered meshes, alternating L-BFGS pose
    re-optimisation within joint limits with Adam model updates.

    \b
    Examples:
      humotion train body --resolution low --threads 1
      humotion train body --resolution full --out runs/body/full --epochs 40
      humotion train body --steps 20 --out /tmp/quick --pose-start 0 --pose-every 1
      humotion train body --no-correctives --out runs/body/low_nocorr
    """
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    model = BodyConfig(shape_latent=shape_latent, expression_latent=expression_latent, correctives=correctives)
    config = BodyTrainConfig(resolution=resolution, out_dir=out_dir or f"runs/body/{resolution}", model=model, **options)
    echo_summary(train(config))


# -- the training data -------------------------------------------------------------------------

@click.command("body-data", context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100},
               epilog="\b\nExamples:\n  python -m humotion.body.command data --out runs/body_data\n"
                      "  python -m humotion.body.command data --out /tmp/tiny --shapes 4 --poses-per-shape 2")
@config_options(Settings, "out", "shapes", "poses_per_shape", "seed", "topology", "mocap", "held_out_shapes",
                "held_out_poses", "expression_fraction", "min_age", "max_age", "chunk",
                out={"required": True, "default": None, "type": click.Path(file_okay=False)},
                topology={"type": click.Choice(LOW_TOPOLOGIES)},
                mocap={"type": click.Path(exists=True, file_okay=False)})
@click.option("--threads", default=1, show_default=True, help="torch CPU threads.")
@click.option("--anny-cache", type=click.Path(file_okay=False), help="Anny's model cache (default $ANNY_CACHE_DIR or ~/.cache/anny).")
def body_data_command(threads, anny_cache, **settings):
    """Generate registered body meshes (Anny shapes x CMU poses x facial expressions, DQS-skinned,
    two resolutions sharing one skeleton) with held-out shapes and poses."""
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    torch.set_num_threads(threads)
    if anny_cache:
        os.environ["ANNY_CACHE_DIR"] = anny_cache
    manifest = generate(Settings(**settings), command="python -m humotion.body.command data " + " ".join(sys.argv[1:]))
    click.echo(f"wrote {manifest['meshes']} meshes ({manifest['splits']}) to {settings['out']}: "
               f"{manifest['bytes'] / 1e6:.1f} MB; LBS vs DQS mean gap {manifest['lbs_vs_dqs_mean_mm']['all']:.2f} mm")


@click.command("body-rest-shapes", context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.option("--data", required=True, type=click.Path(exists=True, file_okay=False), help="Body data folder.")
@click.option("--count", default=2000, show_default=True, help="Rest shapes to add.")
@click.option("--threads", default=1, show_default=True, help="torch CPU threads.")
def body_rest_shapes_command(data, count, threads):
    """Add extra neutral rest shapes (more subjects for the shape space) to a body data folder."""
    torch.set_num_threads(threads)
    entry = make_rest_shapes(data, count, command="python -m humotion.body.command rest-shapes " + " ".join(sys.argv[1:]))
    click.echo(f"wrote {entry['count']} rest shapes to {Path(data) / 'rest_shapes.npz'} in {entry['seconds']} s")


@click.group(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
def body_data_commands():
    """The body model's training data: `data` makes it, `rest-shapes` adds neutral rest shapes."""


body_data_commands.add_command(body_data_command, "data")
body_data_commands.add_command(body_rest_shapes_command, "rest-shapes")

if __name__ == "__main__":
    body_data_commands()

"""`humotion retarget`: a motion file onto another skeleton (any BVH/ASF rig or a built-in one)
or onto a rigged character (glTF, VRM, FBX), written back as the animated character."""

from __future__ import annotations

import logging
from pathlib import Path

import click

from humotion.io import WRITABLE, MotionFileError, load_motion, save_motion
from humotion.io.character import SUFFIXES as CHARACTER_SUFFIXES
from humotion.io.errors import base_suffix
from humotion.io.errors import OutputPathError
from humotion.options import (RenamedOption, config_options, echo_summary, input_options, reported, run_options,
                              run_settings, view_options)
from humotion.outputs import check_outputs, force_option
from humotion.retarget.networks import RetargetConfig
from humotion.retarget.train import WEIGHTS, RetargetTrainConfig, train

BUILT_IN = ("canonical", "cmu")

EPILOG = """\b
Examples:
  humotion retarget walk.amc --to game_character.bvh -o walk_game.bvh
  humotion retarget take.bvh --to canonical --height 1.80 -o body.bvh --view
  humotion retarget take.bvh --to cmu -o cmu.bvh --fps 30
  humotion retarget take.bvh --to odd_rig.bvh --overrides odd_rig.json -o out.bvh
  humotion retarget walk.amc --to game_character.bvh --method learned -o walk_game.bvh
  humotion retarget take.bvh --to avatar.vrm -o avatar_take.vrm --view
  humotion retarget take.bvh --to hero.glb -o hero_take.glb

\b
A character (.glb, .gltf, .vrm; .fbx with humotion[fbx]): its skin's skeleton and bind pose
are the rig (a VRM's humanoid bone map names the key joints), and OUT (.glb, .gltf, .vrm or
.fbx) is the character itself, mesh, materials and skin kept, with the motion as its first
animation (.bvh: the skeleton's motion alone).

\b
TARGET_RIG is a BVH, ASF (or any motion file: its skeleton is the rig) or a built-in rig:
canonical (humotion's 22-joint body) or cmu (CMU's 31-joint skeleton, subject 02).
The result keeps the source's frame rate unless --fps is given.

\b
--method learned uses the learned retargeter (humotion.retarget.learned): source and target must
be skeletons of the weights' domains (shipped weights: the 31-joint CMU ASF skeleton and the
100-joint iClone game rig, any bone lengths); --retargeter picks other weights.

\b
Override file (JSON or TOML) for rigs whose joints are not found automatically:
  {"joints": {"left_knee": "Knee_L", "left_wrist": "Hand_L"},   key joint -> joint name
   "parts": {"Tail1": "torso"}}                                  joint -> body part
Key joints: pelvis spine1 spine2 spine3 neck head, and left_/right_ with collar shoulder elbow
wrist hip knee ankle foot (toes); body parts: left_arm right_arm left_leg right_leg torso head.
"""


def is_character(spec: str) -> bool:
    """Whether TARGET_RIG names a character file (glTF, VRM, FBX) rather than a motion's rig."""
    return base_suffix(Path(spec)) in CHARACTER_SUFFIXES


def target_skeleton(spec: str, height: float | None):
    """The rig named by TARGET_RIG, a built-in name or a file's skeleton, optionally resized,
    and the frame rate of the file it came from (None for a built-in, an ASF or a character)."""
    from humotion.retarget.rig import Rig

    if spec == "canonical":
        from humotion.canonical import canonical_skeleton

        skeleton, fps = canonical_skeleton(), None
    elif spec == "cmu":
        from humotion.assets import demo_clip_path

        skeleton, fps = load_motion(demo_clip_path()).skeleton, None
    elif not Path(spec).is_file():
        raise click.BadParameter(f"{spec!r} is neither a file nor a built-in rig ({', '.join(BUILT_IN)})",
                                 param_hint="--to")
    elif spec.lower().removesuffix(".gz").endswith(".asf"):
        from humotion.io.asf_amc import read_asf

        skeleton, fps = read_asf(spec).skeleton, None
    else:
        rig_motion = load_motion(spec)
        skeleton, fps = rig_motion.skeleton, rig_motion.fps
    if height:
        skeleton = skeleton.scaled(height / Rig.of(skeleton, label=spec).standing_height())
    return skeleton, fps


@click.command("retarget", epilog=EPILOG)
@click.argument("source", type=click.Path(exists=True, dir_okay=False))
@click.option("--to", "target", required=True, metavar="TARGET_RIG", help="Rig file (BVH, ASF, ...), character (.glb, .gltf, .vrm, .fbx) or canonical / cmu.")
@click.option("-o", "--out", required=True, type=click.Path(dir_okay=False),
              help="Output file (.bvh, .glb, .gltf; a character also .vrm, .fbx).")
@input_options
@click.option("--fps", "out_fps", type=float, help="Resample to this frame rate (default: the source's).")
@click.option("--height", type=float, help="Resize the target rig to this standing height, metres.")
@click.option("--overrides", type=click.Path(exists=True, dir_okay=False), help="Override file for the target rig (JSON/TOML).")
@click.option("--source-overrides", type=click.Path(exists=True, dir_okay=False), help="Override file for the source's rig.")
@click.option("--feet/--no-feet", default=True, show_default=True, help="Keep the source's foot contacts with leg IK.")
@click.option("--method", type=click.Choice(("classical", "learned")), default="classical", show_default=True,
              help="classical: key-joint transfer with IK; learned: the trained networks.")
@click.option("--retargeter", "--weights", "weights", cls=RenamedOption, old="--weights",
              type=click.Path(exists=True, dir_okay=False),
              help="Retargeting network weights for --method learned (default: the shipped ones).")
@view_options(help="Show source and result side by side in the browser viewer.")
@force_option
def retarget_command(source, target, out, asf, source_fps, units, out_fps, height, overrides, source_overrides,
                     feet, method, weights, view, port, force):
    """Move a motion onto another skeleton: any joint count, hierarchy, proportions or rest pose."""
    if weights and method != "learned":
        raise click.UsageError("--retargeter goes with --method learned")
    character = is_character(target) and Path(target).is_file()
    if character and height:
        raise click.UsageError("--height resizes a skeleton rig, not a character (its mesh keeps its size)")
    check_outputs([out], inputs=[source, target, asf, overrides, source_overrides, weights], force=force,
                  formats=tuple(dict.fromkeys(WRITABLE + CHARACTER_SUFFIXES)) if character else WRITABLE)
    from humotion.retarget.classical import check_finite, retarget
    from humotion.retarget.parts import load_overrides
    from humotion.retarget.rig import Rig, rest_difference

    with reported(MotionFileError, OutputPathError, ValueError, FileNotFoundError):   # each names its file or skeleton
        motion = load_motion(source, asf=asf, fps=source_fps, units=units)
        check_finite(motion, source)
        if character:
            from humotion.io.character import read_character

            model = read_character(target)
            skeleton, rig_fps = model.skeleton, None
        else:
            skeleton, rig_fps = target_skeleton(target, height)
        if out_fps:
            motion = motion.resample(out_fps)
        source_rig = Rig.of(motion.skeleton, source_overrides and load_overrides(source_overrides), label=source)
        if character:
            from humotion.retarget.character import character_rig

            target_rig = character_rig(model, overrides and load_overrides(overrides))
        else:
            target_rig = Rig.of(skeleton, overrides and load_overrides(overrides), label=target)
        if method == "learned":
            from humotion.retarget.learned import retarget_learned

            result = retarget_learned(motion, target_rig, weights, source_rig=source_rig, feet=feet)
        else:
            # A rig file with a clip: stand where that clip stands (a resized rig: on y = 0).
            floor = target_rig.floor_of(load_motion(target)) if rig_fps and not height else 0.0
            result = retarget(motion, target_rig, source_rig=source_rig, feet=feet, floor=floor)
        if character:
            from humotion.io.character import write_character
            from humotion.retarget.character import on_floor

            result = on_floor(result, model, target_rig, feet)
        if character and base_suffix(Path(out)) != ".bvh":
            write_character(model, result, out, name=Path(source).name.split(".")[0])
        else:
            save_motion(result, out)
    if method == "classical":
        worst = max(rest_difference(source_rig, target_rig).items(), key=lambda kv: kv[1])
        click.echo(f"rest poses differ by up to {worst[1]:.0f} deg ({worst[0]}); aligned before transfer")
    if rig_fps and rig_fps != result.fps:
        click.echo(f"note: {target} runs at {rig_fps:g} fps; the result keeps {result.fps:g} fps (--fps to change)")
    click.echo(f"wrote {out}: {result.num_frames} frames at {result.fps:g} fps on {skeleton.num_joints} joints")
    if view:
        from humotion.viewer import serve

        mesh = None
        if character:
            from humotion.retarget.character import viewer_mesh

            mesh = viewer_mesh(model, result)
        serve([motion, result], [f"source: {Path(source).name}", f"on {Path(target).name}"], port=port, open_browser=True,
              meshes=[None, mesh])


@click.command("retarget", context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@run_options(RetargetTrainConfig)
@config_options(RetargetTrainConfig, "length", "stride", "fps", "held_out")
@config_options(RetargetConfig, "width", "hidden")
@click.option("--adversarial", default=WEIGHTS["adversarial"], show_default=True, help="Weight of the adversarial term.")
def train_retarget_command(width, hidden, adversarial, held_out, **options):
    """Train the learned retargeter (CMU ASF skeletons <-> the 100-joint game rig), unpaired.

    \b
    Examples:
      humotion train retarget --threads 1 --steps 3000
      humotion train retarget --steps 20 --max-clips 4 --out /tmp/quick
    """
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    config = RetargetTrainConfig(model=RetargetConfig(width=width, hidden=hidden), held_out=tuple(held_out),
                                 weights={**WEIGHTS, "adversarial": adversarial}, **run_settings(options), **options)
    echo_summary(train(config))

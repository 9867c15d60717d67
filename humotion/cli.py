"""The `humotion` command line: one entry point, one subcommand per job."""

from __future__ import annotations

import functools
import json
import sys
from pathlib import Path

import click

from humotion.capture.filters import OneEuroConfig
from humotion.capture.follow import DETECTORS
from humotion.capture.pipeline import CaptureConfig   # capture's options are made from its fields (and OneEuroConfig's)
from humotion.io import WRITABLE, MotionFileError, load_motion, save_motion
from humotion.io.bvh import BvhOutline, read_bvh_outline
from humotion.io.errors import OutputPathError, base_suffix
from humotion.options import (RenamedOption, config_options, host_option, input_options, port_option, reported,
                              show_log, sparse_weights_option, view_options)
from humotion.outputs import check_outputs, force_option

EPILOG = """\b
Examples:
  humotion demo                                   # bundled CMU clip: info, BVH export, browser viewer
  humotion info walk.bvh                          # skeleton, joints, frames, fps, duration
  humotion info 01_01.amc --asf 01.asf --json     # the same as JSON, for scripts
  humotion convert 01_01.amc out.bvh --asf 01.asf # AMC -> BVH, same skeleton and positions
  humotion convert take.bvh.gz body.bvh --canonical --fps 30
  humotion view take.bvh                          # 3D skeleton with a timeline in the browser
  humotion data ../shared/data/mocap              # index a mocap folder tree, split by subject

Conventions: metres, seconds, Y up, characters face +Z. Readers take .bvh, .amc (+ .asf),
and the CMU exp-map .txt, each optionally gzip-compressed (.bvh.gz, .amc.gz, ...).
Outputs are checked before any work: an output file's folder must exist and be writable, an
output folder (capture, demo, train) is made; an output that is an input file is refused without --force.
"""


def _read(path: str, asf: str | None, fps: float | None, units: str = "auto"):
    """Load a motion or exit with the reader's message (file, line, problem)."""
    with reported(MotionFileError):
        return load_motion(path, asf=asf, fps=fps, units=units)


def _native_logs(ctx, param, verbose: bool) -> None:
    from humotion.io.video import show_native_logs

    show_native_logs(verbose)


verbose_option = click.option(
    "-v", "--verbose", is_flag=True, expose_value=False, callback=_native_logs,
    help="Show what OpenCV, FFmpeg and MediaPipe log themselves (hidden: humotion reports the problems).")


@click.group(epilog=EPILOG, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(package_name="humotion")
def main():
    """humotion: full-body 3D motion from partial observations of people.

    Read, inspect, convert and watch motion capture; every command works offline.
    Run `humotion COMMAND --help` for the options and examples of a command.
    """
    show_log("humotion.viewer")     # its address


def motion_info(motion, path: str) -> dict:
    """The facts `humotion info` prints, as a JSON-ready dict."""
    skeleton = motion.skeleton
    from humotion.canonical import detect_layout

    try:
        layout = detect_layout(skeleton)
    except ValueError:
        layout = None
    return {
        "file": path,
        "name": motion.name,
        "frames": motion.num_frames,
        "fps": motion.fps,
        "duration_s": round(motion.duration, 4),
        "joints": skeleton.num_joints,
        "joint_names": list(skeleton.names),
        "parents": list(skeleton.parents),
        "end_sites": list(skeleton.end_site_names),
        "height_m": round(skeleton.height(), 4),
        "root": skeleton.names[0],
        "canonical_layout": layout,
        "animated_joint_offsets": (motion.animated_joint_offsets if isinstance(motion, BvhOutline)
                                   else motion.joint_offsets is not None),
    }


@main.command(epilog="\b\nExample:\n  humotion info ../shared/data/mocap/cmu_fairmotion/01_01.bvh --json")
@click.argument("file", type=click.Path(exists=True, dir_okay=False))
@input_options
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object instead of text.")
def info(file, asf, source_fps, units, as_json):
    """Show a motion file's skeleton, joints, frames, frame rate and duration."""
    if base_suffix(file) == ".bvh":  # the header and a count of the rows: no rotations built
        with reported(MotionFileError):
            motion = read_bvh_outline(file, units=units)
    else:
        motion = _read(file, asf, source_fps, units)
    facts = motion_info(motion, file)
    if as_json:
        click.echo(json.dumps(facts, indent=2))
        return
    click.echo(f"{file}")
    click.echo(f"  frames    {facts['frames']} at {facts['fps']:g} fps = {facts['duration_s']:.2f} s")
    click.echo(f"  skeleton  {facts['joints']} joints, root {facts['root']!r}, {len(facts['end_sites'])} end sites, "
               f"rest height {facts['height_m']:.2f} m")
    click.echo(f"  layout    {facts['canonical_layout'] or 'not a known rig (key joints found by name or shape)'}")
    depth = motion.skeleton.depth()
    click.echo("  joints")
    for j, name in enumerate(motion.skeleton.names):
        click.echo(f"    {'  ' * int(depth[j])}{name}")


@main.command(epilog="\b\nExamples:\n  humotion convert 01_01.amc 01_01.bvh --asf 01.asf\n  humotion convert take.bvh body.bvh --canonical --fps 30"
               "\n\n\b\nBVH -> BVH keeps the file's units and rotation orders. --canonical finds the rig's key joints as\n"
               "`humotion retarget` does (joint names, else the tree's shape); --overrides names those it misses.")
@click.argument("source", type=click.Path(exists=True, dir_okay=False))
@click.argument("target", type=click.Path(dir_okay=False))
@input_options
@click.option("--fps", "target_fps", type=float, help="Resample to this frame rate (slerp).")
@click.option("--canonical", is_flag=True, help="Map onto humotion's 22-joint canonical body first.")
@click.option("--overrides", type=click.Path(exists=True, dir_okay=False),
              help="With --canonical: override file (JSON/TOML) naming key joints, as for `humotion retarget`.")
@force_option
def convert(source, target, asf, source_fps, units, target_fps, canonical, overrides, force):
    """Convert a motion file to BVH or glTF (AMC -> BVH keeps the source skeleton)."""
    if overrides and not canonical:
        raise click.UsageError("--overrides goes with --canonical")
    check_outputs([target], inputs=[source, asf, overrides], force=force, formats=WRITABLE)
    motion = _read(source, asf, source_fps, units)
    if canonical:
        from humotion.canonical import to_canonical
        from humotion.retarget.parts import load_overrides

        try:
            motion = to_canonical(motion, overrides=overrides and load_overrides(overrides))
        except ValueError as error:
            raise click.ClickException(f"{source}: {error}") from None
    if target_fps:
        motion = motion.resample(target_fps)
    with reported(MotionFileError, OutputPathError):
        save_motion(motion, target)
    click.echo(f"wrote {target}: {motion.num_frames} frames at {motion.fps:g} fps, {motion.skeleton.num_joints} joints")


@main.command(epilog="\b\nExamples:\n  humotion view walk.bvh\n  humotion view a.bvh b.bvh --canonical   # side by side")
@click.argument("files", nargs=-1, required=True, type=click.Path(exists=True, dir_okay=False))
@input_options
@click.option("--canonical", is_flag=True, help="Show the motions mapped onto the canonical body.")
@host_option()
@port_option()
@click.option("--open/--no-open", "open_browser", default=True, help="Open a browser tab.")
def view(files, asf, source_fps, units, canonical, host, port, open_browser):
    """Play motions as 3D skeletons in the browser, with a timeline (Ctrl-C stops)."""
    motions = [_read(f, asf, source_fps, units) for f in files]
    if canonical:
        from humotion.canonical import to_canonical

        motions = [to_canonical(m) for m in motions]
    from humotion.viewer import serve

    serve(motions, [Path(f).name for f in files], host, port, open_browser)


@main.command("data", epilog="\b\nExample:\n  humotion data ../shared/data/mocap --exclude hdm05_jointlearning")
@click.argument("root", type=click.Path(exists=True, file_okay=False))
@click.option("--exclude", multiple=True, help="Leave out a source folder (repeatable).")
@click.option("--cache-dir", type=click.Path(file_okay=False), help="Where parsed arrays are cached (default $HUMOTION_CACHE or ~/.cache/humotion).")
@click.option("--json", "as_json", is_flag=True, help="Print the index and split as JSON.")
def data_command(root, exclude, cache_dir, as_json):
    """Index every motion under a folder: subjects, durations, rates, split by subject.

    Prints the index (a table, or JSON with --json); writes nothing but its cache of parsed
    arrays (--cache-dir), which makes the next run fast."""
    from humotion.data import MotionCollection

    progress = not as_json or sys.stderr.isatty()     # bars on stderr; kept out of captured --json output
    collection = MotionCollection.load(root, exclude=exclude, cache_dir=cache_dir, progress=progress)
    split = collection.split()
    if as_json:
        clips = [{"path": str(c.path), "source": c.source, "subject": c.subject, "frames": c.frames,
                  "fps": c.fps, "duration_s": round(c.duration, 4), "joints": c.num_joints} for c in collection.clips]
        skipped = [{"path": str(s.path), "reason": s.reason} for s in collection.skipped]
        click.echo(json.dumps({"clips": clips, "split": split, "skipped": skipped}, indent=2))
        return
    click.echo(collection.summary())
    for name, subjects in split.items():
        click.echo(f"{name:>5}: {', '.join(subjects)}")


@main.group()
def train():
    """Train humotion's models (progress bar, checkpoints, resume)."""


def _register_training() -> None:
    from humotion.body.command import train_body_command
    from humotion.capture.command import train_lift_command, train_prior_command
    from humotion.retarget.command import train_retarget_command
    from humotion.sparse.command import train_sparse_command

    for name, command in (("sparse", train_sparse_command), ("lift", train_lift_command), ("prior", train_prior_command),
                          ("retarget", train_retarget_command), ("body", train_body_command)):
        train.add_command(_output_checked_first(command), name=name)


def _output_checked_first(command: click.Command) -> click.Command:
    """The training command with its output checked (humotion.outputs) before it loads any data:
    --out as a folder (out_dir: checkpoints, log, weights) or as a file (out: the prior's .npz)."""
    run = command.callback

    @functools.wraps(run)
    def checked(**options):
        check_outputs([options.get("out")], folders=[options["out_dir"]] if options.get("out_dir") else [])
        return run(**options)

    command.callback = checked
    return command


_register_training()


EVAL_EPILOG = """\b
Examples:
  humotion eval sparse --json                                   # CMU test subjects and HDM05
  humotion eval sparse ../shared/data/mocap/hdm05_jointlearning --scenario HT
  humotion eval sparse take.bvh --weights runs/sparse/sparse_poser_best.pt
"""


@main.group("eval")
def evaluate():
    """Measure humotion's models on motion capture (metrics as in bench/)."""


@evaluate.command("sparse", epilog=EVAL_EPILOG)
@click.argument("data", nargs=-1, type=click.Path(exists=True))
@sparse_weights_option
@click.option("--scenario", "scenarios", multiple=True, type=click.Choice(("MC", "HT")),
              help="Controllers (MC) and/or hand tracking (HT); default both.")
@click.option("--baselines/--no-baselines", default=False, help="Add the hold-last-hand and own-trajectory rows.")
@click.option("--max-seconds", type=float, default=60.0, show_default=True, help="Cut clips to this length (0: whole).")
@click.option("--json", "as_json", is_flag=True, help="Print the rows as JSON.")
def eval_sparse(data, weights, scenarios, baselines, max_seconds, as_json):
    """Sparse-tracking accuracy: headset signals synthesised from motion capture (files or
    folders; default the CMU test subjects and HDM05 of ../shared/data/mocap), the tracked body
    compared with the truth: MPJRE (deg), MPJPE, hand, upper, lower (cm), MPJVE (cm/s), Jitter."""
    import torch

    from humotion.sparse.batches import DEFAULT_DATA
    from humotion.sparse.evaluation import evaluate_models, format_table, test_sets
    from humotion.sparse.tracker import load_weights

    with reported(FileNotFoundError):
        model = load_weights(weights)
    progress = not as_json or sys.stderr.isatty()     # bars on stderr; kept out of captured --json output
    with reported(MotionFileError, ValueError, KeyError):
        sets = ({Path(p).name: _clips_at(Path(p), progress) for p in data} if data
                else test_sets(DEFAULT_DATA, progress=progress))
        with torch.no_grad():
            rows = evaluate_models({"network": model}, sets, scenarios or ("MC", "HT"), max_seconds or None,
                                   baselines=baselines, progress=progress)
    click.echo(json.dumps(rows, indent=1) if as_json else format_table(rows))


def _clips_at(path: Path, progress: bool = False) -> list:
    """Every motion clip in a folder tree (unreadable files reported and skipped), or one file."""
    if path.is_file():
        return [load_motion(path)]
    from humotion.data import MotionCollection

    collection = MotionCollection.load(path, progress=progress)
    for skipped in collection.skipped:
        click.echo(f"skipped {skipped.path}: {skipped.reason}", err=True)
    if not len(collection):
        raise click.ClickException(f"no readable motion files under {path}")
    return collection.clips


@main.group("export")
def export():
    """Export humotion's models for other runtimes."""


@export.command("sparse", epilog="\b\nExample:\n  humotion export sparse -o tracker.onnx   # Unity Sentis, Unreal NNE, onnxruntime")
@click.option("-o", "--out", required=True, type=click.Path(dir_okay=False), help="ONNX file to write.")
@sparse_weights_option
@click.option("--anchor/--no-anchor", default=True, show_default=True, help="Root placed so the eyes meet the headset.")
@force_option
def export_sparse(out, weights, anchor, force):
    """The sparse tracker's per-frame function (head + hands + state -> body pose + state) as ONNX;
    inputs and outputs are listed in humotion.sparse.frame."""
    check_outputs([out], inputs=[weights], force=force)
    from humotion.sparse.frame import export_onnx
    from humotion.sparse.tracker import load_weights

    with reported(FileNotFoundError):
        model = load_weights(weights)
    click.echo(f"wrote {export_onnx(model, out, anchor)}")


from humotion.live.command import send_vmc, vmc_address  # noqa: E402  (capture/track --vmc; the live commands' module)

CAPTURE_EPILOG = """\b
Examples:
  humotion capture humotion/assets/samples/hikers_3s.mp4 -o hikers   # the shipped 3 s sample
  humotion capture dance.mp4 -o dance_out --height 1.72
  humotion capture duet.mp4 -o duet_out --height 0=1.85 --height 1=1.62   # per person id
  humotion capture kid.mp4 -o kid_out --sex female --age 7   # a typical height for them (1.21 m)
  humotion capture family.mp4 -o family_out --height 0=1.80 --height-reference 0   # others relative to person 0
  humotion capture photo.jpg -o photo_out --view
  humotion capture 0 -o live_out --live      # camera 0 until Ctrl-C, people in 3D in the browser meanwhile
  humotion capture 0 -o live_out --live --vmc 127.0.0.1:39539   # and the body as VMC (VSeeFace, Warudo, EVMC4U)
  humotion capture videos/ -o batch_out --workers 2            # every video in a folder (also 'videos/*.mp4', list.txt)
  humotion capture videos/ -o /shared/out --ray-address head:6379   # on a Ray cluster (docs/batch.md)

\b
Writes per person (id N; a person who leaves and comes back gets one file per stretch):
personN.bvh and personN.glb on the canonical skeleton, capture.json (per frame 2D keypoints in
pixels with confidences and 3D joints in metres, by joint name) and overlay.mp4 (the 2D skeletons).
"""


@main.command(epilog=CAPTURE_EPILOG)
@click.argument("source")
@click.option("-o", "--out", "out_dir", required=True, type=click.Path(file_okay=False),
              help="Output folder (made if missing).")
@click.option("--height", "heights", multiple=True, metavar="[ID=]METRES",
              help="Standing height in metres: everyone's, or person ID's (repeatable). Default "
                   f"{CaptureConfig.height_m:g}, or one typical of --sex and --age.")
@config_options(CaptureConfig, "height_reference", height_reference={"metavar": "ID", "help": (
    "Estimate the heights of people without --height relative to person ID (give theirs with --height ID=METRES): "
    "all on one flat floor, a static camera; about 10% error, so a child is told from an adult but adults hardly "
    "from each other.")})
@click.option("--sex", type=click.Choice(("female", "male")), help="For a typical height (CDC growth-chart medians).")
@click.option("--age", type=float, help="Years, 2 or more: for a typical height (with --sex, or the mean of both).")
@config_options(
    CaptureConfig, "hfov_deg", "focal_px", "camera_height", "pitch_deg", "max_people", "detector",
    hfov_deg={"decls": ("--fov", "hfov_deg")},
    focal_px={"decls": ("--focal", "focal_px"), "help": "Camera's focal length in pixels (instead of --fov)."},
    camera_height={"metavar": "METRES"},
    pitch_deg={"decls": ("--pitch", "pitch_deg"), "metavar": "DEGREES"},
    detector={"type": click.Choice(DETECTORS)})
@click.option("--no-filter", is_flag=True, help="Do not smooth the 2D keypoints (One-Euro filter).")
@config_options(OneEuroConfig, "min_cutoff", "beta", min_cutoff={"decls": ("--filter-cutoff", "min_cutoff")},
                beta={"decls": ("--filter-beta", "beta")})
@click.option("--no-refine", is_flag=True, help="Skip the refinement (faster, less accurate).")
@config_options(CaptureConfig, "body", body={"type": click.Choice(("low", "full"))})
@click.option("--lifter", "--weights", "weights", cls=RenamedOption, old="--weights", type=click.Path(exists=True, dir_okay=False),
              help="Lifting network weights (default: shipped).")
@click.option("--live", is_flag=True, help="Show everyone in 3D in the browser while frames are read (causal "
              "lifting, no refinement; for a camera). The files are written as without it.")
@click.option("--vmc", metavar="HOST:PORT", callback=vmc_address, help="Send the body of the person followed longest "
              "(the lowest id in the frame) as VMC (OSC/UDP) while frames are read, joint angles from the live "
              "3D joints (docs/live.md).")
@click.option("--character", type=click.Path(exists=True, dir_okay=False), help="Also write each person on this "
              "rigged character (.glb, .gltf, .vrm; .fbx with humotion[fbx]): personN_<character>.glb (.vrm, .fbx).")
@view_options()
@click.option("--workers", type=click.IntRange(min=1), help="Batches: videos captured at once (default: the number "
              "of cores, or of the cluster's CPUs with --ray-address).")
@click.option("--ray-address", metavar="HOST:PORT", help="Batches: run on this Ray cluster (humotion[cluster]); the "
              "videos and -o must be on storage every node sees at the same path.")
@force_option
@verbose_option
def capture(source, out_dir, heights, sex, age, no_filter, min_cutoff, beta, no_refine, weights, live, vmc, character,
            view, port, workers, ray_address, force, **settings):
    """3D motion of the people in a video, an image or a camera (its index) from one ordinary camera;
    or of every video of a batch (a folder, a quoted glob, a .txt list), each into its own folder
    under -o, with summary.csv and summary.json, finished videos skipped on a rerun."""
    from humotion.capture.batch import is_batch
    from humotion.capture.lifting import load_lifter
    from humotion.capture.pipeline import capture as run_capture
    from humotion.capture.template import typical_height

    with reported(MotionFileError, OutputPathError, FileNotFoundError, ValueError):
        everyone, per_person = _parse_heights(heights)
        config = CaptureConfig(height_m=everyone or typical_height(sex, age), heights=per_person,
                               filter=OneEuroConfig(enabled=not no_filter, min_cutoff=min_cutoff, beta=beta),
                               **({"refine": None} if no_refine else {}), **settings)
        if is_batch(source):
            if live or view or vmc:
                raise ValueError("--live, --vmc and --view show one video; a batch (folder, glob, .txt list) takes none")
            if character:
                raise ValueError("--character is not applied to a batch: capture the batch, then `humotion retarget` "
                                 "the person files you need onto the character")
            return _capture_batch(source, out_dir, config, weights, workers, ray_address)
        camera = source.isdigit()
        if not camera:
            _check_video(source)
        check_outputs(folders=[out_dir], inputs=[None if camera else source], force=force,
                      written=[Path(out_dir) / name for name in ("overlay.mp4", "overlay.png")])
        lifter = load_lifter(weights)
        live_view = _live_outputs(port if live else None, vmc, config)
        try:
            result = run_capture(int(source) if camera else source, out_dir, config, lifter=lifter,
                                 live_view=live_view)
        finally:
            if live_view:
                live_view.stop()
    for warning in result.warnings:
        click.echo(f"warning: {warning}", err=True)
    for person, height in sorted(result.estimated_heights.items()):
        click.echo(f"person {person}: height {height:.2f} m (estimated relative to person "
                   f"{config.height_reference})")
    for path in result.files:
        click.echo(f"wrote {path}")
    if result.interrupted:      # Ctrl-C in the 3D stage: what was finished is written
        raise SystemExit(130)
    motions, meshes = [p.motion for p in result.people], None
    if character and motions:
        motions, meshes = _on_character(motions, character, [Path(out_dir) / p.motion.name for p in result.people])
    if view and motions:
        from humotion.viewer import serve

        serve(motions, [p.motion.name for p in result.people], port=port, open_browser=True, meshes=meshes)


def _on_character(motions, character, stems):
    """Each motion retargeted onto the character file and written to stem_<character>.glb
    (.vrm, .fbx as the character); the results and their posed meshes for the viewer."""
    from humotion.io.character import read_character
    from humotion.retarget.character import animate_character, viewer_mesh

    suffix = Path(character).suffix.lower() if Path(character).suffix.lower() in (".vrm", ".fbx") else ".glb"
    with reported(MotionFileError, OutputPathError, ValueError):
        model = read_character(character)
        results = []
        for motion, stem in zip(motions, stems):
            path = Path(stem).parent / f"{Path(stem).name}_{Path(character).stem}{suffix}"
            results.append(animate_character(motion, model, path)[0])
            click.echo(f"wrote {path}")
    return results, [viewer_mesh(model, r) for r in results]


def _capture_batch(source: str, out_dir: str, config, weights, workers: int | None, ray_address: str | None) -> None:
    """capture on a batch of videos (humotion.capture.batch): one bar over the batch, the failures
    and where the summary is; exit code 1 when a video failed, 130 on Ctrl-C."""
    from tqdm import tqdm

    from humotion.capture.batch import find_videos, run_batch

    videos = find_videos(source, exclude=out_dir)
    check_outputs(folders=[out_dir])
    with tqdm(total=len(videos), desc="capturing videos", unit="video") as bar:
        report = run_batch(videos, out_dir, config, weights, workers, address=ray_address,
                           on_result=lambda result: bar.update())
    failed = [r for r in report.results if r.status == "failed"]
    for result in failed:
        click.echo(f"failed: {result.video}: {result.error}", err=True)
    click.echo(f"{report.count('done')} of {len(videos)} videos done ({sum(r.skipped for r in report.results)} by an "
               f"earlier run), {len(failed)} failed; summary: {report.summary_csv}, {report.summary_json.name}")
    if report.interrupted:
        raise SystemExit(130)
    if failed:
        raise SystemExit(1)


def _check_video(source: str) -> None:
    """Open a video or image file and close it: VideoSourceError naming the file when it is
    missing or cannot be decoded, before anything is made."""
    from humotion.io.video import open_frames

    open_frames(source).close()


def _parse_heights(values: tuple[str, ...]) -> tuple[float | None, dict[int, float]]:
    """--height values ("1.72" or "3=1.80") -> (everyone's height or None, {person id: height})."""
    everyone, per_person = None, {}
    for value in values:
        person, _, metres = value.rpartition("=")
        try:
            height = float(metres)
            if person:
                per_person[int(person)] = height
            else:
                everyone = height
        except ValueError:
            raise click.BadParameter(f"{value!r} is not METRES or ID=METRES (e.g. 1.72 or 0=1.80)",
                                     param_hint="--height") from None
    return everyone, per_person


def _live_outputs(port: int | None, vmc: tuple[str, int] | None, config):
    """capture's live sinks: the browser view on port (None: none) and VMC to vmc (None: none)."""
    from humotion.capture.live import LiveOutputs, VmcOutput

    outputs = []
    if port is not None:
        from humotion.viewer.live import LiveView

        outputs.append(LiveView(port=port))
        click.echo(f"live view: {outputs[-1].url}")
    if vmc is not None:
        outputs.append(VmcOutput(vmc, config.height_m, config.heights))
        click.echo(f"VMC: the body of the person followed longest to {vmc[0]}:{vmc[1]}")
    return LiveOutputs(*outputs) if outputs else None



TRACK_EPILOG = """\b
Examples:
  humotion track humotion/assets/samples/headset_cmu_03_03.csv -o walk.bvh   # the shipped sample
  humotion track session.csv -o body.bvh --gltf body.glb             # OpenXR axes (default)
  humotion track session.json -o body.bvh --convention unity --refine
  humotion track --demo                                              # held-out CMU clip, prediction vs truth

The recording format (CSV or JSON; head, wrists, visibility flags, timestamps) is documented in
humotion.sparse.recording: `python -c "import humotion.sparse.recording as r; help(r)"`.
"""


@main.command(epilog=TRACK_EPILOG)
@click.argument("recording", required=False, type=click.Path(exists=True, dir_okay=False))
@click.option("-o", "--out", type=click.Path(dir_okay=False), help="BVH file for the body motion.")
@click.option("--gltf", type=click.Path(dir_okay=False), help="Also write a glTF animation (.glb or .gltf).")
@click.option("--convention", type=click.Choice(("openxr", "unity", "humotion")),
              help="Axes of the recording: openxr (right-handed, -Z forward; default), unity (left-handed, +Z forward).")
@click.option("--hand-frame", type=click.Choice(("tpose", "forward")),
              help="What a hand's identity orientation means in the recording (default tpose).")
@sparse_weights_option
@click.option("--height", type=float, help="User's standing height in metres (default: from the eye height).")
@click.option("--refine", is_flag=True, help="Fit the upper body to the observed head and hands after the network.")
@click.option("--demo", is_flag=True, help="Synthesise a stream from a held-out CMU clip and compare with the truth.")
@click.option("--scenario", type=click.Choice(("HT", "MC")), default="HT", show_default=True, help="With --demo: hand tracking or controllers.")
@click.option("--character", type=click.Path(exists=True, dir_okay=False), help="Also write the body on this rigged "
              "character (.glb, .gltf, .vrm; .fbx with humotion[fbx]) beside -o: <OUT>_<character>.glb (.vrm, .fbx).")
@view_options(default=None, help="Open the result in the browser viewer (default: with --demo).")
@click.option("--vmc", metavar="HOST:PORT", callback=vmc_address,
              help="Also stream the body as VMC (OSC/UDP; VSeeFace, Warudo, EVMC4U; usually port 39539) in real time.")
@click.option("--vmc-rate", type=float, metavar="FPS", help="VMC frames per second (default the recording's; 0: as fast as possible).")
@force_option
def track(recording, out, gltf, convention, hand_frame, weights, height, refine, demo, scenario, character, view, port,
          force, vmc=None, vmc_rate=None):
    """Full-body motion from a recorded headset stream (head + hands when seen).

    Writes the body (humotion's 22-joint canonical skeleton at the network's rate, 30 fps) as BVH
    (-o) and as a glTF skeleton animation (--gltf); with neither, it only tracks (and shows or
    streams the result)."""
    from humotion.sparse.tracker import SparseTracker

    if bool(recording) == demo:
        raise click.UsageError("give a RECORDING file, or --demo")
    if character and not out:
        raise click.UsageError("--character writes beside -o: give -o")
    check_outputs([out, gltf], inputs=[recording, weights], force=force, formats=WRITABLE)
    with reported(FileNotFoundError):
        tracker = SparseTracker(weights, height=height)
    truth = None
    if demo:
        stream, truth = _demo_stream(scenario)
    else:
        from humotion.sparse.recording import read_recording

        with reported(MotionFileError, ValueError):
            stream = read_recording(recording, convention=convention, hand_frame=hand_frame)
    body = _tracked(tracker, stream)
    if refine:
        body = _refined(body, stream, tracker.fps)
    click.echo(f"tracked {len(stream)} headset frames -> {body}")
    for path in filter(None, (out, gltf)):
        with reported(OutputPathError):
            save_motion(body, path)
        click.echo(f"wrote {path}")
    if vmc:
        send_vmc(body, vmc, stream.fps, vmc_rate)
    meshes = None
    if character:
        shown, meshes = _on_character([body], character, [Path(out).with_suffix("")])
    if view or (view is None and demo):
        motions, labels = ([body, truth], ["prediction", "truth"]) if truth is not None else ([body], ["prediction"])
        if character:
            motions, meshes = [shown[0]] + motions[1:], meshes + [None] * (len(motions) - 1)
        from humotion.viewer import serve

        serve(motions, labels, port=port, open_browser=True, meshes=meshes)


def _tracked(tracker, stream):
    """tracker.track(stream), the gate's rejections said in one line (stderr); a motion that is
    not finite everywhere is an error (exit 1), never a file written silently."""
    import warnings

    import torch

    from humotion.sparse.gate import TrackingWarning

    with reported(ValueError):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", TrackingWarning)      # summed up below
            body = tracker.track(stream)
    if tracker.rejected:
        click.echo(f"warning: {tracker.rejected} (humotion.sparse.gate: implausible samples held or read as unseen)",
                   err=True)
    if not (torch.isfinite(body.rotations).all() and torch.isfinite(body.root_positions).all()):
        raise click.ClickException("the tracked motion holds NaN or infinity; nothing written")
    return body


def _demo_stream(scenario: str):
    """A headset stream synthesised from a clip of a test subject (or the bundled clip)."""
    import torch

    from humotion.canonical import to_canonical
    from humotion.sparse.recording import stream_from_motion
    from humotion.sparse.train import DEFAULT_DATA

    clip = DEFAULT_DATA / "cmu_cyun9601" / "amc" / "03" / "03_01.amc.gz"   # CMU subject 03: a test subject
    if not clip.is_file():
        from humotion.assets import demo_clip_path

        clip = demo_clip_path()
    truth = to_canonical(load_motion(clip)).resample(30.0)
    click.echo(f"demo: {clip.name} ({truth.duration:.1f} s), scenario {scenario}")
    return stream_from_motion(truth, scenario, generator=torch.Generator().manual_seed(0)), truth


def _refined(body, stream, fps):
    """The tracked body refined against the stream's observations (robust when hands drop out)."""
    from humotion.sparse.refine import RefineConfig, refine
    from humotion.sparse.signals import eye_offset
    from humotion.sparse.tracker import resample_stream

    stream = resample_stream(stream, fps)
    robust = bool((~stream.visible).any())
    return refine(body, stream.rotations.float(), stream.positions.float(), stream.visible,
                  eye_offset(body.skeleton), RefineConfig(robust=robust))


def _demo_capture(out_dir: Path):
    """Video capture on the bundled photo: the person's 3D pose (None if the lifter is missing)."""
    from humotion.assets import demo_photo_path
    from humotion.capture.lifting import DEFAULT_WEIGHTS as LIFTER
    from humotion.capture.pipeline import capture as run_capture

    if not LIFTER.is_file():
        return None
    result = run_capture(demo_photo_path(), out_dir, progress=False)
    click.echo(f"video capture on {demo_photo_path().name}: {len(result.people)} person(s) -> {out_dir}/")
    return result.people[0].motion if result.people else None


@main.command(epilog="\b\nExample:\n  humotion demo --no-view -o demo_out")
@click.option("-o", "--out", "out_dir", default="humotion_demo", show_default=True, type=click.Path(file_okay=False),
              help="Folder for the demo's files.")
@view_options(default=True, help="Open the browser viewer at the end.")
@verbose_option
def demo(out_dir, view, port):
    """Run humotion on its bundled CMU clip: facts, exports, headset tracking, browser viewer.

    Writes the clip as BVH (its own skeleton) and as the canonical body (BVH and glTF); then, as a
    VR headset with hand tracking would see it (head always, hands inside the cameras' view),
    rebuilds the whole body with the shipped sparse-tracking model and puts that motion on a learned
    body mesh (from_headset_body.glb); then captures the 3D pose of the person in a bundled photo (video
    capture); and shows all side by side.
    """
    import torch

    from humotion.assets import demo_clip_path
    from humotion.canonical import to_canonical
    from humotion.sparse.recording import stream_from_motion
    from humotion.sparse.tracker import DEFAULT_WEIGHTS, SparseTracker

    check_outputs(folders=[out_dir])
    clip = demo_clip_path()
    motion = _read(str(clip), None, None)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    click.echo(f"bundled clip {clip.name}: {motion}")
    canonical = to_canonical(motion)
    shown, labels = [motion, canonical], ["CMU source", "canonical body"]
    outputs = {"source.bvh": motion, "canonical.bvh": canonical, "canonical.glb": canonical}
    if DEFAULT_WEIGHTS.is_file():
        stream = stream_from_motion(canonical, "HT", generator=torch.Generator().manual_seed(0))
        tracked = SparseTracker().track(stream)
        seen = stream.visible.float().mean(0)
        click.echo(f"headset tracking (hands in view {seen[0]:.0%} / {seen[1]:.0%} of the time): {tracked}")
        shown.append(tracked)
        labels.append("from headset")
        outputs["from_headset.bvh"] = tracked
    for name, result in outputs.items():
        save_motion(result, out / name)
        click.echo(f"wrote {out / name} ({result.skeleton.num_joints} joints)")
    meshes = [None] * len(shown)
    if DEFAULT_WEIGHTS.is_file():
        body, rig = _demo_body(tracked, out / "from_headset_body.glb")
        shown.append(rig)
        labels.append("on a body")
        meshes.append((body, rig))
    photo = _demo_capture(out / "photo")
    if photo is not None:
        shown.append(photo)
        labels.append("from a photo")
        meshes.append(None)
    if view:
        from humotion.viewer import serve

        serve(shown, labels, port=port, open_browser=True, meshes=[m and _body_mesh(*m) for m in meshes])


def _demo_body(motion, path: Path):
    """The motion on a learned body of the motion's height, written to path (skinned glTF):
    (the body at rest, the rig's motion)."""
    from humotion.body.export import animated_body
    from humotion.body.model import load_body_model
    from humotion.io.gltf import write_gltf

    body, rig, mesh = animated_body(load_body_model("low"), motion.skeleton.height(), motion)
    write_gltf(rig, path, mesh=mesh)
    facts = body.measurements()
    click.echo(f"wrote {path} (the headset's motion on a learned body: {facts['height']:.2f} m, "
               f"{facts['weight']:.0f} kg, {body.model.num_vertices} vertices)")
    return body, rig


def _body_mesh(body, rig):
    """(vertices (T, V, 3), faces (faces, 3)) of the body moved by its rig's motion, for the viewer."""
    from humotion import rotations as rot
    from humotion.body.export import posed_vertices

    vertices = posed_vertices(body, rot.quat_to_matrix(rig.rotations), rig.root_positions, progress=False)
    return vertices.numpy(), body.model.faces.numpy()


from humotion.retarget.command import retarget_command  # noqa: E402  (the command lives beside the retargeter)
main.add_command(retarget_command)
from humotion.body.command import body_command  # noqa: E402  (the command lives beside the body model)
main.add_command(body_command)
from humotion.live.command import serve_command  # noqa: E402  (the command lives beside the live server)
main.add_command(serve_command)


if __name__ == "__main__":
    sys.exit(main())

"""Every command's outputs are checked before its work (issue 20): a missing or unwritable folder
is one line naming the path, an output that is an input is refused without --force, the atomic
writer names the user's path, and the native libraries' own log lines stay hidden unless --verbose."""

import os
import shutil

import pytest
import torch
from click.testing import CliRunner

from humotion.assets import demo_clip_path, demo_photo_path
from humotion.cli import main
from humotion.io import load_motion, save_motion
from humotion.io.errors import OutputPathError

as_root = os.geteuid() == 0


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def one_line_error(result, *words):
    """The command failed with one 'Error: ...' line holding every word, and no traceback."""
    assert result.exit_code == 1, result.output
    errors = [line for line in result.output.splitlines() if line.startswith("Error: ")]
    assert len(errors) == 1 and all(str(w) in errors[0] for w in words), result.output
    assert "Traceback" not in result.output and ".tmp" not in result.output


@pytest.fixture
def clip(tmp_path):
    """The bundled 31-joint CMU clip as a plain BVH file in tmp_path."""
    path = tmp_path / "clip.bvh"
    save_motion(load_motion(demo_clip_path()), path)
    return path


@pytest.fixture
def recording(tmp_path):
    """A short headset recording (CSV) synthesised from the bundled clip."""
    from humotion.canonical import to_canonical
    from humotion.sparse.recording import stream_from_motion, write_recording

    motion = to_canonical(load_motion(demo_clip_path())).resample(30.0)
    path = tmp_path / "session.csv"
    write_recording(stream_from_motion(motion, "HT", generator=torch.Generator().manual_seed(0)), path)
    return path


# -- item 1: a missing output folder is one line, before the work ---------------------------------

@pytest.mark.parametrize("command", [
    ("convert", "{clip}", "{out}"),
    ("convert", "{clip}", "{out}", "--canonical"),
    ("retarget", "{clip}", "--to", "canonical", "-o", "{out}"),
    ("body", "-o", "{out}", "--motion", "{clip}"),
    ("export", "sparse", "-o", "{out}"),
])
def test_a_missing_output_folder_is_one_line_naming_the_path(command, clip, tmp_path):
    out = tmp_path / "no" / "such" / "x.glb"
    result = run(*[a.format(clip=clip, out=out) for a in command])
    one_line_error(result, out, "does not exist")
    assert "wrote" not in result.output and "body (" not in result.output  # nothing was made first
    assert not (tmp_path / "no").exists()


def test_track_checks_its_outputs_before_tracking(recording, tmp_path):
    out = tmp_path / "missing" / "body.bvh"
    result = run("track", recording, "-o", out)
    one_line_error(result, out, "does not exist")
    assert "tracked" not in result.output
    result = run("track", recording, "-o", tmp_path / "body.bvh", "--gltf", tmp_path / "missing" / "body.glb")
    one_line_error(result, tmp_path / "missing" / "body.glb")
    assert "tracked" not in result.output
    result = run("track", recording, "-o", tmp_path / "body.txt")
    one_line_error(result, "body.txt", "cannot write '.txt' files")
    one_line_error(run("convert", demo_clip_path(), tmp_path / "body"), "body", "no suffix to say the format")


def test_the_atomic_writer_names_the_users_path_not_its_temporary_file(clip, tmp_path):
    motion = load_motion(clip)
    for name in ("x.bvh", "x.glb"):
        with pytest.raises(OutputPathError) as error:
            save_motion(motion, tmp_path / "no" / "dir" / name)
        assert str(error.value).startswith(f"{tmp_path / 'no' / 'dir' / name}: cannot write the file")
        assert ".tmp" not in str(error.value)
        assert isinstance(error.value, OSError)  # code catching failed writes still catches it


# -- item 2: an unwritable folder is one line naming the path -------------------------------------

@pytest.mark.parametrize("name", ["x.bvh", "x.glb"])
def test_an_output_under_a_file_is_one_line(clip, tmp_path, name):
    """Root-proof: no permission bits stop root, but a path through a regular file fails for anyone."""
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    one_line_error(run("convert", clip, blocker / name), blocker / name, "is not a folder")
    one_line_error(run("capture", demo_photo_path(), "-o", blocker / "out"), blocker / "out", "is a file")
    one_line_error(run("demo", "--no-view", "-o", blocker / "out"), blocker / "out", "is a file")
    assert blocker.read_text() == "not a folder"


@pytest.mark.parametrize("command, option, name", [("sparse", "--out", "run"), ("lift", "--out", "run"),
                                                   ("retarget", "--out", "run"), ("body", "--out", "run"),
                                                   ("prior", "-o", "prior.npz")])
def test_training_checks_its_output_before_loading_data(command, option, name, tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    one_line_error(run("train", command, option, blocker / name), blocker / name, "a_file")


@pytest.mark.skipif(as_root, reason="root writes into read-only folders; see test_an_output_under_a_file_is_one_line")
def test_a_read_only_folder_is_one_line(clip, tmp_path):
    folder = tmp_path / "read_only"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        for name in ("x.bvh", "x.glb"):
            one_line_error(run("convert", clip, folder / name), folder / name, "read-only")
        one_line_error(run("capture", demo_photo_path(), "-o", folder), folder, "read-only")
        one_line_error(run("capture", demo_photo_path(), "-o", folder / "new"), folder / "new", "read-only")
    finally:
        folder.chmod(0o755)


def test_a_folder_the_system_calls_read_only_is_one_line(clip, tmp_path, monkeypatch):
    """The read-only case as root too: os.access (what the check asks; it also sees a read-only
    file system, which stops root) says no for one folder."""
    folder = tmp_path / "read_only"
    folder.mkdir()
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda path, mode, **kw: path != folder and real_access(path, mode, **kw))
    one_line_error(run("convert", clip, folder / "x.glb"), folder / "x.glb", "read-only")
    one_line_error(run("capture", demo_photo_path(), "-o", folder / "new"), folder / "new", "read-only")
    assert list(folder.iterdir()) == []


# -- item 3: an output that is an input is refused without --force --------------------------------

def test_converting_a_file_onto_itself_is_refused_however_spelled(clip, tmp_path):
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "link.bvh").symlink_to(clip)
    before = clip.read_bytes()
    for target in (clip, tmp_path / "sub" / ".." / clip.name, tmp_path / "sub" / "link.bvh"):
        one_line_error(run("convert", clip, target, "--canonical"), target, "is the input file", "--force")
    assert clip.read_bytes() == before
    result = run("convert", clip, clip, "--canonical", "--force")
    assert result.exit_code == 0, result.output
    assert load_motion(clip).skeleton.num_joints == 22


def test_every_command_that_reads_a_file_refuses_to_write_over_it(clip, recording, tmp_path):
    rig = tmp_path / "rig.bvh"
    shutil.copy(clip, rig)
    glb = tmp_path / "walk.glb"
    save_motion(load_motion(clip), glb)
    link = tmp_path / "session.bvh"
    link.symlink_to(recording)  # a writable suffix that leads to the recording
    before = {p: p.read_bytes() for p in (clip, rig, glb, recording)}
    for args, path in [(("retarget", clip, "--to", "canonical", "-o", clip), clip),
                       (("retarget", clip, "--to", rig, "-o", rig), rig),
                       (("body", "-o", glb, "--motion", glb), glb),
                       (("track", recording, "-o", link), link)]:
        one_line_error(run(*args), path, "is the input file")
    assert all(p.read_bytes() == data for p, data in before.items())


def test_capture_refuses_to_write_its_overlay_over_its_input(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    shutil.copy(demo_photo_path(), out / "overlay.png")
    one_line_error(run("capture", out / "overlay.png", "-o", out), "overlay.png", "is the input file")


# -- issue 21 item 7: capture checks its input before making its folder ---------------------------

def test_capture_on_a_missing_or_undecodable_input_makes_no_folder(tmp_path):
    one_line_error(run("capture", tmp_path / "nowhere.mp4", "-o", tmp_path / "a"), "nowhere.mp4", "file not found")
    garbage = tmp_path / "garbage.mp4"
    garbage.write_bytes(bytes(range(256)) * 64)
    one_line_error(run("capture", garbage, "-o", tmp_path / "b"), "garbage.mp4", "cannot decode")
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


# -- item 12: OpenCV, FFmpeg and MediaPipe stay quiet unless --verbose ----------------------------

@pytest.fixture
def no_moov(tmp_path):
    """An mp4 cut short before its index (moov atom): FFmpeg and OpenCV both complain about it."""
    import numpy as np

    from humotion.io.video import VideoWriter

    whole = tmp_path / "whole.mp4"
    with VideoWriter(whole, 10) as writer:
        for k in range(10):
            writer.write(np.full((64, 64, 3), 20 * k, np.uint8))
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    return cut


def test_native_log_lines_are_hidden_unless_verbose(no_moov, tmp_path, capfd):
    from humotion.io.video import show_native_logs

    capfd.readouterr()
    one_line_error(run("capture", no_moov, "-o", tmp_path / "out"), "cut.mp4", "cannot decode")
    assert capfd.readouterr().err == ""
    try:
        one_line_error(run("capture", no_moov, "-o", tmp_path / "out", "--verbose"), "cut.mp4", "cannot decode")
    finally:
        show_native_logs(False)  # the default again, for the tests after
    shown = capfd.readouterr().err
    assert "moov atom not found" in shown and "WARN" in shown


def test_the_pose_detector_loads_and_detects_quietly(capfd):
    import cv2

    from humotion.capture.detection import MediaPipePoseDetector

    image = cv2.cvtColor(cv2.imread(str(demo_photo_path())), cv2.COLOR_BGR2RGB)
    capfd.readouterr()
    with MediaPipePoseDetector(max_people=1) as detector:
        assert len(detector.detect(image)) == 1
    assert capfd.readouterr().err == ""

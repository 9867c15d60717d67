"""The command line on real files: info, convert (AMC -> BVH keeps the skeleton), errors, demo."""

import json

import pytest
import torch
from click.testing import CliRunner

from humotion.cli import main
from humotion.io import load_motion


def run(*args):
    result = CliRunner().invoke(main, [str(a) for a in args])
    return result


def test_help_teaches():
    result = run("--help")
    assert result.exit_code == 0
    for word in ("info", "convert", "view", "demo", "data", "Examples:"):
        assert word in result.output


def test_info_json_on_amc_and_bvh(mocap):
    facts = json.loads(run("info", mocap / "cmu_fairmotion/01_01.amc", "--json").output)
    assert facts["joints"] == 31 and facts["fps"] == 120.0 and facts["canonical_layout"] == "cmu_asf"
    assert facts["frames"] == 2751 and facts["duration_s"] == pytest.approx(2751 / 120, abs=1e-3)
    facts = json.loads(run("info", mocap / "cmu_iclone_ccskeleton/001_01.bvh.gz", "--json").output)
    assert facts["joints"] == 100 and facts["fps"] == 60.0 and facts["frames"] == 1376
    text = run("info", mocap / "cmu_fairmotion/01_01.bvh").output
    assert "2752 at 120 fps" in text and "LeftUpLeg" in text


def test_convert_amc_to_bvh_keeps_skeleton_and_positions(mocap, tmp_path):
    source = mocap / "cmu_fairmotion/01_01.amc"
    out = tmp_path / "01_01.bvh"
    result = run("convert", source, out, "--asf", mocap / "cmu_fairmotion/01.asf")
    assert result.exit_code == 0, result.output
    original, written = load_motion(source), load_motion(out)
    assert written.skeleton.names == original.skeleton.names and written.fps == original.fps
    assert torch.allclose(written.world_positions(), original.world_positions(), atol=1e-5)
    assert torch.allclose(written.end_site_positions(), original.end_site_positions(), atol=1e-5)


def test_convert_to_canonical_at_30_fps(mocap, tmp_path):
    out = tmp_path / "body.bvh.gz"
    result = run("convert", mocap / "cmu_mocgui_s02/02_01.amc", out, "--canonical", "--fps", 30)
    assert result.exit_code == 0, result.output
    body = load_motion(out)
    assert body.skeleton.num_joints == 22 and body.fps == 30.0 and body.skeleton.names[0] == "pelvis"


def test_bad_file_gives_a_clear_message(tmp_path):
    broken = tmp_path / "broken.bvh"
    broken.write_text("HIERARCHY\nROOT Hips\n{\n  OFFSET 0 0\n")
    result = run("info", broken)
    assert result.exit_code != 0
    assert "broken.bvh, line 4" in result.output and "Traceback" not in result.output


def test_demo_runs_on_bundled_clip(tmp_path):
    result = run("demo", "--no-view", "-o", tmp_path)
    assert result.exit_code == 0, result.output
    body = load_motion(tmp_path / "canonical.bvh")
    source = load_motion(tmp_path / "source.bvh")
    assert body.skeleton.num_joints == 22 and source.skeleton.num_joints == 31
    assert body.num_frames == source.num_frames >= 150
    assert load_motion(tmp_path / "canonical.glb").num_frames == body.num_frames
    tracked = load_motion(tmp_path / "from_headset.bvh")  # the body rebuilt from a headset
    assert tracked.skeleton.names == body.skeleton.names and abs(tracked.duration - body.duration) < 0.1
    # the shipped model follows the clip: the tracked head stays near the true one
    head = body.skeleton.index("head")
    assert float((tracked.world_positions()[:, head] - body.world_positions()[:, head]).norm(dim=-1).mean()) < 0.15
    # the headset's motion on a learned body (76-joint rig): its head follows the tracked head
    rig = load_motion(tmp_path / "from_headset_body.glb")
    assert rig.skeleton.num_joints == 76 and rig.num_frames == tracked.num_frames
    rig_head = rig.world_positions()[:, rig.skeleton.index("head")]
    assert float((rig_head - tracked.world_positions()[:, head]).norm(dim=-1).mean()) < 0.12
    # the bundled photo's person in 3D: one frame, standing on the floor, head above the pelvis
    photo = load_motion(next((tmp_path / "photo").glob("person*.bvh")))
    joints = photo.world_positions()[0]
    assert photo.num_frames == 1 and joints[head, 1] > joints[0, 1] + 0.3
    assert (tmp_path / "photo" / "capture.json").is_file() and (tmp_path / "photo" / "overlay.png").is_file()  # a still image


def test_the_demo_and_quick_start_outputs_are_git_ignored():
    """`humotion demo` writes to its default folder and the README's quick start to out/, both
    inside the checkout: git must not list them as untracked files."""
    import re
    import shutil
    import subprocess
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    if shutil.which("git") is None or not (repo / ".git").exists():
        pytest.skip("not a git checkout")
    default = next(p.default for p in main.commands["demo"].params if p.name == "out_dir")
    readme = (repo / "README.md").read_text()
    quick_start = readme.split("## Five-minute tour", 1)[1].split("\n## ", 1)[0]
    written = re.findall(r"(?:-o |--gltf |\.amc |\.bvh |save_motion\(body, \")(out/[\w./]+)", quick_start)
    assert len(written) >= 6, written
    for path in [f"{default}/from_headset_body.glb", *written]:
        result = subprocess.run(["git", "check-ignore", "-q", path], cwd=repo)
        assert result.returncode == 0, f"{path} is not git-ignored"


def test_data_indexes_a_folder_and_reports_bad_files(mocap, tmp_path):
    folder = tmp_path / "mocap" / "cmu_mocgui_s02"
    folder.mkdir(parents=True)
    for name in ("02.asf", "02_01.amc", "02_02.amc"):
        (folder / name).write_bytes((mocap / "cmu_mocgui_s02" / name).read_bytes())
    (folder / "02_03.amc").write_text((mocap / "cmu_mocgui_s02" / "02_03.amc").read_text()[:5000])
    result = run("data", tmp_path / "mocap", "--cache-dir", tmp_path / "cache", "--json")
    assert result.exit_code == 0, result.output
    report = json.loads(result.output[result.output.index("{"):])
    assert sorted(c["path"].split("/")[-1] for c in report["clips"]) == ["02_01.amc", "02_02.amc"]
    assert {c["subject"] for c in report["clips"]} == {"cmu-02"}
    assert len(report["skipped"]) == 1 and "02_03.amc" in report["skipped"][0]["reason"]
    text = run("data", tmp_path / "mocap", "--cache-dir", tmp_path / "cache").output
    assert "cmu_mocgui_s02" in text and "train:" in text


def test_data_shows_progress_on_stderr_while_reading_files_the_first_time(mocap, tmp_path):
    """The first `humotion data` reads every file (tens of seconds on the shared data): a tqdm bar
    on stderr says how far it is; the next run reads the cache and shows none; --json keeps
    stdout pure JSON."""
    folder = tmp_path / "mocap" / "cmu_mocgui_s02"
    folder.mkdir(parents=True)
    for name in ("02.asf", "02_01.amc", "02_02.amc"):
        (folder / name).write_bytes((mocap / "cmu_mocgui_s02" / name).read_bytes())
    first = run("data", tmp_path / "mocap", "--cache-dir", tmp_path / "cache")
    assert first.exit_code == 0, first.output
    assert "reading motion files" in first.stderr and "2/2" in first.stderr
    assert "reading motion files" not in first.stdout and "cmu_mocgui_s02" in first.stdout
    again = run("data", tmp_path / "mocap", "--cache-dir", tmp_path / "cache")
    assert again.exit_code == 0 and "reading motion files" not in again.stderr
    fresh = run("data", tmp_path / "mocap", "--cache-dir", tmp_path / "cache2", "--json")
    assert fresh.exit_code == 0 and len(json.loads(fresh.stdout)["clips"]) == 2


def test_the_walk_for_motion_files_advances_a_bar_per_file(tmp_path):
    from humotion.data.collection import _scan

    class Counter:
        n = 0

        def update(self, k=1):
            self.n += k

    (tmp_path / "a" / "b").mkdir(parents=True)
    for name in ("a/x.bvh", "a/b/y.bvh", "a/notes.md"):
        (tmp_path / name).write_text("")
    bar = Counter()
    found = _scan(tmp_path, bar)
    assert bar.n == 3 and [f[0].name for f in found] == ["y.bvh", "x.bvh"]


def test_capture_command_on_the_bundled_photo_and_bad_input(tmp_path):
    from humotion.assets import demo_photo_path

    result = run("capture", demo_photo_path(), "-o", tmp_path / "out", "--height", "1.8", "--no-filter")
    assert result.exit_code == 0, result.output
    data = json.loads((tmp_path / "out" / "capture.json").read_text())
    assert data["height_m"] == 1.8 and len(data["people"]) == 1
    person = load_motion(next((tmp_path / "out").glob("person*.bvh")))
    assert abs(person.skeleton.height() - 1.8) < 0.01
    too_tall = run("capture", demo_photo_path(), "-o", tmp_path / "x", "--height", "7")
    assert too_tall.exit_code != 0 and "height_m must be a standing height in metres" in too_tall.output
    missing = run("capture", tmp_path / "nowhere.mp4", "-o", tmp_path / "y")
    assert missing.exit_code != 0 and "nowhere.mp4" in missing.output and "file not found" in missing.output
    garbled = run("capture", demo_photo_path(), "-o", tmp_path / "z", "--height", "tall")
    assert garbled.exit_code != 0 and "'tall' is not METRES or ID=METRES" in garbled.output



def test_capture_prints_the_warnings_capture_returns(tmp_path):
    """capture() returns its warnings; the command prints them (to stderr)."""
    import numpy as np
    from PIL import Image

    Image.fromarray(np.full((240, 320, 3), 128, np.uint8)).save(tmp_path / "empty_room.png")
    result = CliRunner().invoke(main, ["capture", str(tmp_path / "empty_room.png"), "-o", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    assert "warning: nobody was found" in result.stderr

def test_capture_heights_per_person_and_by_sex_and_age(tmp_path):
    from humotion.assets import demo_photo_path

    result = run("capture", demo_photo_path(), "-o", tmp_path / "kid", "--sex", "female", "--age", "7", "--no-refine")
    assert result.exit_code == 0, result.output
    data = json.loads((tmp_path / "kid" / "capture.json").read_text())
    assert data["height_m"] == pytest.approx(1.21) and data["heights_m"] == {"0": pytest.approx(1.21)}
    result = run("capture", demo_photo_path(), "-o", tmp_path / "two", "--height", "1.6", "--height", "0=1.9", "--no-refine")
    data = json.loads((tmp_path / "two" / "capture.json").read_text())
    assert data["height_m"] == 1.6 and data["heights_m"] == {"0": 1.9}
    assert abs(load_motion(tmp_path / "two" / "person0.bvh").skeleton.height() - 1.9) < 0.01
    toddler = run("capture", demo_photo_path(), "-o", tmp_path / "t", "--age", "1")
    assert toddler.exit_code != 0 and "age must be at least 2 years" in toddler.output

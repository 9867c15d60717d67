"""Batch capture (humotion.capture.batch): a folder of real clips with one corrupt file, captured on a
Ray cluster of two worker nodes started here, gives each video the files a plain capture() gives
it, and the corrupt one is reported and skipped; a batch killed midway resumes without redoing the
finished videos and ends with a complete summary. Clips: 8 frames cut from a shared real video."""

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from humotion.capture.batch import MARKER, find_videos, is_batch, output_names, run_batch, settings_of
from humotion.capture.pipeline import CaptureConfig, capture
from tests.data_root import DATA

VIDEO = DATA / "video" / "intel_one-by-one-person-detection_first40s.mp4"
STARTS = {"walk_a": 120, "walk_b": 250, "walk_c": 330}      # frames where one person is in view
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def clips(tmp_path_factory) -> Path:
    """A folder: three 8-frame clips of the real video (MPEG-4) and broken.mp4, one of them cut in half."""
    if not VIDEO.is_file():
        pytest.skip("shared video missing")
    folder = tmp_path_factory.mktemp("clips")
    for name, start in STARTS.items():
        source = cv2.VideoCapture(str(VIDEO))
        source.set(cv2.CAP_PROP_POS_FRAMES, start)
        writer = cv2.VideoWriter(str(folder / f"{name}.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (768, 432))
        for _ in range(8):
            writer.write(source.read()[1])
        writer.release()
        source.release()
    whole = (folder / "walk_a.mp4").read_bytes()
    (folder / "broken.mp4").write_bytes(whole[: len(whole) // 2])
    return folder


@pytest.fixture(scope="module")
def sequential(clips, tmp_path_factory) -> Path:
    """Each clip captured on its own by capture(), as `humotion capture CLIP -o OUT` does."""
    out = tmp_path_factory.mktemp("sequential")
    for name in STARTS:
        capture(clips / f"{name}.mp4", out / name, CaptureConfig(), progress=False)
    return out


def assert_same_capture(folder: Path, reference: Path):
    """The same files, and capture.json's people, frames, 2D keypoints and 3D joints within 1 mm."""
    made = {p.name for p in folder.iterdir()} - {MARKER}
    assert made == {p.name for p in reference.iterdir()}
    ours, theirs = (json.loads((f / "capture.json").read_text()) for f in (folder, reference))
    assert ours["people"].keys() == theirs["people"].keys() and ours["people"]
    for person, frames in theirs["people"].items():
        assert [f["frame"] for f in ours["people"][person]] == [f["frame"] for f in frames]
        for key in ("keypoints_2d", "joints_3d"):
            values = [[v for f in fs for point in f[key].values() for v in point] for fs in (ours["people"][person], frames)]
            np.testing.assert_allclose(*values, atol=1e-3)


def test_sources_name_the_videos(tmp_path):
    (tmp_path / "day1").mkdir()
    for name in ("day1/a.mp4", "day1/a.avi", "b.MOV", "notes.md", "out/overlay.mp4"):
        (tmp_path / name).parent.mkdir(exist_ok=True)
        (tmp_path / name).write_bytes(b"x")
    (tmp_path / "list.txt").write_text("# session 1\nday1/a.mp4\n\nmissing.mp4\n")
    folder = find_videos(str(tmp_path), exclude=tmp_path / "out")
    assert [p.relative_to(tmp_path).as_posix() for p in folder] == ["b.MOV", "day1/a.avi", "day1/a.mp4"]
    assert output_names(folder) == ["b", "day1/a_avi", "day1/a_mp4"]
    assert [p.name for p in find_videos(str(tmp_path / "**" / "*.mp4"))] == ["a.mp4", "overlay.mp4"]
    assert find_videos(str(tmp_path / "list.txt")) == [tmp_path / "day1/a.mp4", tmp_path / "missing.mp4"]
    assert all(map(is_batch, (str(tmp_path), str(tmp_path / "*.mp4"), str(tmp_path / "list.txt"))))
    assert not is_batch(str(tmp_path / "b.MOV"))
    with pytest.raises(ValueError, match="no videos found"):
        find_videos(str(tmp_path / "day1" / "*.mkv"))


def test_a_ray_cluster_captures_the_batch_as_sequential_runs(clips, sequential, tmp_path):
    cluster_utils = pytest.importorskip("ray.cluster_utils")
    cluster = cluster_utils.Cluster(initialize_head=True, head_node_args={"num_cpus": 0, "include_dashboard": False})
    try:
        for _ in range(2):      # two worker nodes, one CPU each
            cluster.add_node(num_cpus=1)
        cluster.wait_for_nodes()
        report = run_batch(find_videos(str(clips)), tmp_path, engine="ray", address=cluster.address)
    finally:
        cluster.shutdown()
    rows = {r["output"]: r for r in csv.DictReader((tmp_path / "summary.csv").open())}
    assert rows["broken"]["status"] == "failed" and "cannot decode" in rows["broken"]["error"]
    assert not (tmp_path / "broken" / MARKER).exists()
    for name in STARTS:
        assert rows[name]["status"] == "done" and rows[name]["people"] == "1" and rows[name]["frames"] == "8"
        assert_same_capture(tmp_path / name, sequential / name)
    assert len(report.workers) == 2 == len({r.worker for r in report.results})   # models loaded once per worker
    assert json.loads((tmp_path / "summary.json").read_text())["counts"] == {
        "done": 3, "failed": 1, "interrupted": 0, "pending": 0}


def test_a_killed_batch_resumes(clips, sequential, tmp_path):
    """The batch runs in a process pool of two; the whole process group is killed once a video is
    finished; the rerun does the rest and leaves the finished one untouched."""
    driver = (f"from humotion.capture.batch import find_videos, run_batch\n"
              f"run_batch(find_videos({str(clips)!r}), {str(tmp_path)!r}, engine='pool', workers=2)")
    process = subprocess.Popen([sys.executable, "-c", driver], cwd=REPO, start_new_session=True,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        while not list(tmp_path.glob(f"*/{MARKER}")) and process.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait()
    finished = {p.parent.name: p.stat().st_mtime_ns for p in tmp_path.glob(f"*/{MARKER}")}
    assert 1 <= len(finished) < 3, "the kill came too late to test resuming"
    before = json.loads((tmp_path / "summary.json").read_text())
    assert before["counts"]["pending"] >= 1          # the summary of the killed run says what is left

    report = run_batch(find_videos(str(clips)), tmp_path, engine="inline")
    rows = {r.output: r for r in report.results}
    assert {name for name, r in rows.items() if r.skipped} == set(finished)
    assert all((tmp_path / name / MARKER).stat().st_mtime_ns == mtime for name, mtime in finished.items())
    assert [rows[name].status for name in sorted(rows)] == ["failed", "done", "done", "done"]
    for name in STARTS:
        assert_same_capture(tmp_path / name, sequential / name)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["counts"] == {"done": 3, "failed": 1, "interrupted": 0, "pending": 0}
    assert {r["output"] for r in summary["results"]} == {"broken", *STARTS}


def test_other_settings_redo_a_finished_video(tmp_path):
    """A marker counts only for the settings it records: with others the video is captured again
    (here it is missing, so the attempt fails instead of being skipped)."""
    marker = tmp_path / "out" / "gone" / MARKER
    marker.parent.mkdir(parents=True)
    config = CaptureConfig()
    result = {"video": str(tmp_path / "gone.mp4"), "output": "gone", "status": "done", "people": 2}
    marker.write_text(json.dumps({"result": result, "settings": settings_of(config)}))
    [same] = run_batch([tmp_path / "gone.mp4"], tmp_path / "out", config, engine="inline").results
    assert same.status == "done" and same.skipped and same.people == 2
    [other] = run_batch([tmp_path / "gone.mp4"], tmp_path / "out", CaptureConfig(height_m=1.8), engine="inline").results
    assert other.status == "failed" and other.error == "file not found" and not other.skipped


def test_the_command_takes_a_folder(clips, tmp_path):
    """`humotion capture FOLDER`: the failure on one line, the summary named, exit code 1 for a
    failed video; the rerun skips the finished one."""
    from click.testing import CliRunner

    from humotion.cli import main

    folder = tmp_path / "videos"
    folder.mkdir()
    for name in ("walk_a.mp4", "broken.mp4"):
        (folder / name).write_bytes((clips / name).read_bytes())
    out = tmp_path / "out"
    first = CliRunner().invoke(main, ["capture", str(folder), "-o", str(out), "--workers", "1"])
    assert first.exit_code == 1, first.output
    assert f"failed: {folder / 'broken.mp4'}: cannot decode as a video" in first.output
    assert "1 of 2 videos done (0 by an earlier run), 1 failed" in first.output
    again = CliRunner().invoke(main, ["capture", str(folder / "walk_*.mp4"), "-o", str(out), "--workers", "1"])
    assert again.exit_code == 0 and "1 of 1 videos done (1 by an earlier run), 0 failed" in again.output
    live = CliRunner().invoke(main, ["capture", str(folder), "-o", str(out), "--live"])
    assert live.exit_code == 1 and "show one video; a batch (folder, glob, .txt list) takes" in live.output
    character = CliRunner().invoke(main, ["capture", str(folder), "-o", str(out), "--character", str(clips / "walk_a.mp4")])
    assert character.exit_code == 1 and "--character is not applied to a batch" in character.output


def test_an_address_where_nothing_answers_is_refused(tmp_path):
    pytest.importorskip("ray")
    with pytest.raises(ValueError, match="nothing answers at the Ray address 127.0.0.1:1"):
        run_batch([tmp_path / "a.mp4"], tmp_path / "out", engine="ray", address="127.0.0.1:1")

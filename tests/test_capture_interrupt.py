"""Ctrl-C or a crash in capture's 3D stage keeps what was finished: each person's files as they
were written, and a valid capture.json for them; the command's exit code says so (130 for
Ctrl-C). The stage is made to fail in-process (a monkeypatched refinement) on a real photo made
into a video where one person is seen twice (two segments)."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from humotion.capture import pipeline
from humotion.capture.lifting import Lifter, LiftingConfig
from humotion.capture.pipeline import CaptureConfig, CaptureResult, capture
from humotion.capture.refine import CaptureRefineConfig
from humotion.io.video import VideoWriter
from processes import interruptible

PHOTO = Path(__file__).resolve().parents[2] / "shared" / "data" / "images" / "yogait_cc0" / "tadasana_tada1.jpg"


@pytest.fixture(scope="module")
def two_stretches(tmp_path_factory) -> Path:
    """A video: the person on 5 frames, 10 empty grey frames, the person again on 5 frames."""
    if not PHOTO.is_file():
        pytest.skip("test photos missing")
    image = cv2.cvtColor(cv2.imread(str(PHOTO)), cv2.COLOR_BGR2RGB)
    image = cv2.resize(image, (240, round(image.shape[0] * 240 / image.shape[1])))
    grey = np.full_like(image, 128)
    path = tmp_path_factory.mktemp("video") / "twice.mp4"
    with VideoWriter(path, fps=30.0) as writer:
        for frame in [image] * 5 + [grey] * 10 + [image] * 5:       # gone 0.33 s: longer than BRIDGED_GAP
            writer.write(frame)
    return path


@pytest.fixture(scope="module")
def detector():
    from humotion.capture.detection import MediaPipePoseDetector

    with MediaPipePoseDetector(max_people=1) as found:
        yield found


@pytest.fixture(scope="module")
def lifter():
    torch.manual_seed(0)
    return Lifter(LiftingConfig(channels=16, levels=2)).eval()


def failing_second_time(error: BaseException):
    """A stand-in for pipeline.refined that works once, then raises error."""
    calls = []
    original = pipeline.refined

    def refined(*args, **kwargs):
        calls.append(1)
        if len(calls) > 1:
            raise error
        return original(*args, **kwargs)

    return refined


def test_ctrl_c_in_the_3d_stage_keeps_the_finished_person_and_says_so(tmp_path, two_stretches, detector, lifter,
                                                                       monkeypatch):
    monkeypatch.setattr(pipeline, "refined", failing_second_time(KeyboardInterrupt()))
    config = CaptureConfig(refine=CaptureRefineConfig(iterations=2, photo_iterations=2))
    result = capture(two_stretches, tmp_path, config, detector=detector, lifter=lifter, progress=False)
    assert result.interrupted and "Ctrl-C" in result.interrupted and len(result.people) == 1
    assert (tmp_path / "person0.bvh").is_file() and (tmp_path / "person0.glb").is_file()
    assert not list(tmp_path.glob("person0_*")) and not list(tmp_path.glob("*.partial"))
    data = json.loads((tmp_path / "capture.json").read_text())
    assert list(data["people"]) == ["0"] and len(data["people"]["0"]) == 5
    assert "Ctrl-C" in data["interrupted"] and any("1 of 2 segments" in w for w in data["warnings"])


def test_a_crash_in_the_3d_stage_is_raised_after_writing_what_was_finished(tmp_path, two_stretches, detector, lifter,
                                                                            monkeypatch):
    monkeypatch.setattr(pipeline, "refined", failing_second_time(RuntimeError("out of memory")))
    config = CaptureConfig(refine=CaptureRefineConfig(iterations=2, photo_iterations=2))
    with pytest.raises(RuntimeError, match="out of memory"):
        capture(two_stretches, tmp_path, config, detector=detector, lifter=lifter, progress=False)
    assert (tmp_path / "person0.bvh").is_file()
    data = json.loads((tmp_path / "capture.json").read_text())
    assert list(data["people"]) == ["0"] and "out of memory" in data["interrupted"]


def test_the_command_exits_with_130_after_ctrl_c(tmp_path, monkeypatch):
    from humotion.cli import main

    def interrupted_capture(source, out_dir, config, **kwargs):
        return CaptureResult([], [Path(out_dir) / "capture.json"], [], interrupted="interrupted (Ctrl-C)")

    monkeypatch.setattr(pipeline, "capture", interrupted_capture)
    photo = tmp_path / "photo.jpg"
    photo.write_bytes(PHOTO.read_bytes() if PHOTO.is_file() else pytest.skip("test photos missing"))
    outcome = CliRunner().invoke(main, ["capture", str(photo), "-o", str(tmp_path / "out")])
    assert outcome.exit_code == 130, outcome.output


def test_ctrl_c_while_reading_a_file_uses_the_frames_read_and_says_so(tmp_path, two_stretches, detector, lifter):
    class StoppedAtFrame4:
        def __init__(self):
            self.seen = 0

        def detect(self, image):
            self.seen += 1
            if self.seen == 4:
                raise KeyboardInterrupt
            return detector.detect(image)

    config = CaptureConfig(refine=CaptureRefineConfig(iterations=2, photo_iterations=2))
    result = capture(two_stretches, tmp_path, config, detector=StoppedAtFrame4(), lifter=lifter, progress=False)
    assert result.interrupted and "reading frames" in result.interrupted
    assert [p.segment.frames.tolist() for p in result.people] == [[0, 1, 2]]
    assert (tmp_path / "person0.bvh").is_file() and json.loads((tmp_path / "capture.json").read_text())["interrupted"]


def test_sigint_during_the_3d_stage_of_the_command_exits_130_with_a_valid_json(tmp_path):
    """The real thing: `humotion capture` in a subprocess on 3 s of a real clip (Intel IoT DevKit
    sample-videos, CC BY 4.0), SIGINT sent once the "3D per person" stage has started. --body full
    makes that stage take about 2 s rather than 1, so a loaded machine still signals inside it.
    The child takes SIGINT (interruptible) even when the test run was started in the background."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from humotion.io.video import open_frames

    video = PHOTO.parents[2] / "video" / "intel_one-by-one-person-detection_first40s.mp4"
    if not video.is_file():
        pytest.skip("shared videos missing")
    clip = tmp_path / "clip.mp4"
    with open_frames(video) as frames, VideoWriter(clip, fps=10.0) as writer:
        for index, _, image in frames:
            if index >= 130:
                break
            if index >= 100:
                writer.write(image)
    out = tmp_path / "out"
    command = [sys.executable, "-m", "humotion.cli", "capture", str(clip), "-o", str(out), "--body", "full", "--no-view"]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               env={**os.environ, "PYTHONUNBUFFERED": "1"}, preexec_fn=interruptible)
    seen, deadline = "", time.monotonic() + 240
    while "3D per person" not in seen and time.monotonic() < deadline and process.poll() is None:
        seen += process.stderr.read(1)
    assert "3D per person" in seen, seen[-2000:]
    process.send_signal(signal.SIGINT)
    stdout, stderr = process.communicate(timeout=120)
    assert process.returncode == 130, (process.returncode, stderr[-2000:])
    data = json.loads((out / "capture.json").read_text())
    assert data["interrupted"] and "Ctrl-C" in data["interrupted"]
    assert (out / "overlay.mp4").is_file() and not list(out.glob("*.partial"))
    for person in data["people"]:                              # whoever was finished has their files
        assert (out / f"person{person}.bvh").is_file()

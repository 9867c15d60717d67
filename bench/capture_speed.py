"""Video-capture speed on this CPU: milliseconds per frame of each stage, one person, 640x480.

    .venv/bin/python bench/capture_speed.py [--frames 90] [--weights PATH]

The video: a CC0 photo of a standing person (../shared/data/images/yogait_cc0) fitted into
640x480 and panned a few pixels per frame. Stages: detection (MediaPipe BlazePose, reported
separately: it is the 2D detector's cost), tracking + One-Euro filtering, lifting (the
network over the whole sequence), bone-length correction + joint angles + initial root, and
the refinement; then frames per second of everything after detection, against 30 fps. Also:
the overlay video (drawing + H.264 encoding), and live capture (humotion.capture.live: causal
lifting, bones, angles and root, frame by frame, as `humotion capture 0 --live` runs).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from humotion.capture.detection import MediaPipePoseDetector
from humotion.capture.lifting import load_lifter
from humotion.capture.live import LiveCapture
from humotion.capture.overlay import draw_people
from humotion.capture.people import PeopleTracker
from humotion.capture.pipeline import default_camera, initial_fit, lift_segment, refined, segments_of
from humotion.capture.prior import PosePrior
from humotion.capture.refine import CaptureRefineConfig
from humotion.capture.template import DEFAULT_HEIGHT
from humotion.io.video import VideoWriter

PHOTO = Path(__file__).resolve().parents[2] / "shared" / "data" / "images" / "yogait_cc0" / "tadasana_tada1.jpg"


def frames_640x480(count: int) -> list[np.ndarray]:
    """The photo letterboxed into 640x480, shifted 2 px right per frame."""
    photo = cv2.cvtColor(cv2.imread(str(PHOTO)), cv2.COLOR_BGR2RGB)
    scale = min(600 / photo.shape[1], 440 / photo.shape[0])
    small = cv2.resize(photo, (int(photo.shape[1] * scale), int(photo.shape[0] * scale)))
    canvas = np.full((480, 640, 3), 90, np.uint8)
    y, x = (480 - small.shape[0]) // 2, (640 - small.shape[1]) // 2
    canvas[y:y + small.shape[0], x:x + small.shape[1]] = small
    return [np.roll(canvas, 2 * (k % 10), axis=1) for k in range(count)]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=90)
    parser.add_argument("--weights", help="lifting weights (default: shipped)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    frames = frames_640x480(args.frames)
    lifter, prior = load_lifter(args.weights), PosePrior.load()
    camera = default_camera(640, 480)

    detect_ms, track_ms, overlay_ms, live_ms, seen = [], [], [], [], []
    tracker, live = PeopleTracker(), LiveCapture(camera)
    with MediaPipePoseDetector(max_people=1) as detector, tempfile.TemporaryDirectory() as folder, \
            VideoWriter(Path(folder) / "overlay.mp4", 30.0) as writer:
        detector.detect(frames[0])                                       # warm-up
        for index, frame in enumerate(frames):
            start = time.perf_counter()
            found = detector.detect(frame)
            middle = time.perf_counter()
            people = tracker.update(found, index / 30.0)
            tracked = time.perf_counter()
            writer.write(draw_people(frame, people))
            drawn = time.perf_counter()
            live.update(people)
            detect_ms.append((middle - start) * 1000)
            track_ms.append((tracked - middle) * 1000)
            overlay_ms.append((drawn - tracked) * 1000)
            live_ms.append((time.perf_counter() - drawn) * 1000)
            seen += [(index, index / 30.0, person.keypoints, person.confidence) for person in people]
    segment = max(segments_of(0, seen, min_frames=1), key=lambda s: len(s.frames))
    n = len(segment.frames)

    start = time.perf_counter()
    lift_segment(lifter, segment)
    lift_s = time.perf_counter() - start
    start = time.perf_counter()
    fit = initial_fit(segment, camera, lifter, DEFAULT_HEIGHT)
    angles_s = time.perf_counter() - start - lift_s               # initial_fit lifts too
    start = time.perf_counter()
    refined(fit, segment, camera, prior, CaptureRefineConfig())
    refine_s = time.perf_counter() - start

    stages = {"tracking + filter": statistics.median(track_ms), "lifting": 1000 * lift_s / n,
              "bones + angles + root": 1000 * angles_s / n, "refinement": 1000 * refine_s / n}
    print(f"one person, 640x480, {n} frames, one CPU thread")
    print(f"  {'detection (2D, MediaPipe)':28} {statistics.median(detect_ms):8.2f} ms/frame (median)")
    for name, ms in stages.items():
        print(f"  {name:28} {ms:8.2f} ms/frame")
    after = sum(stages.values())
    print(f"  everything after detection   {after:8.2f} ms/frame = {1000 / after:6.1f} fps (goal: 30 fps)")
    print(f"  end to end with detection    {after + statistics.median(detect_ms):8.2f} ms/frame = "
          f"{1000 / (after + statistics.median(detect_ms)):6.1f} fps")
    print(f"  overlay video (draw + H.264) {statistics.median(overlay_ms):8.2f} ms/frame (median)")
    print(f"  live 3D (causal, per frame)  {statistics.median(live_ms[1:]):8.2f} ms/frame (median; "
          f"p99 {np.percentile(live_ms[1:], 99):.2f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())

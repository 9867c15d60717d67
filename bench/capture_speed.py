"""Video-capture speed on this CPU: milliseconds per frame of each stage, one person, 640x480; and
the 2D stage with 1, 4 and 8 people at 640x480 and 1280x720.

    .venv/bin/python bench/capture_speed.py [--frames 90] [--weights PATH] [--detector movenet|mediapipe]
                                            [--people 1 4 8] [--sizes 640x480 1280x720] [--people-frames 60]

The video: a CC0 photo of a standing person (../shared/data/images/yogait_cc0) fitted into
640x480 and panned a few pixels per frame. Stages: detection (MediaPipe BlazePose, reported
separately: it is the 2D detector's cost), tracking + One-Euro filtering, lifting (the
network over the whole sequence), bone-length correction + joint angles + initial root (and
their second run, straightened to the floor's vertical), and the refinement as capture runs it
(with the camera's pose: two passes holding the feet; beside it, the same run's figure for the
previous release's refinement, PREVIOUS, the compiled energy at the previous release's 75 steps a
pass, and the refinement's cost on a 1 s stretch of the clip, where its fixed cost per segment
weighs more); then frames per second of everything after
detection, against 30 fps. Also:
the overlay video (drawing + H.264 encoding), and live capture (humotion.capture.live: causal
lifting, bones, angles and root, frame by frame, as `humotion capture 0 --live` runs).

The 2D stage runs as `humotion capture` runs it (humotion.capture.follow.PeopleFinder): with the
default MoveNet detector, following each known person on a crop (Lightning, on every other frame,
optical flow in between: follow.DETECT_EVERY) plus one scan region (MultiPose) every third frame,
then tracking; MoveNet following everyone with the model on every frame (detect_every=1: the
baseline) and the old MediaPipe detector (whole frame each time) are timed side by side on the
same frames, in turn, ten frames each (BLOCK). Several people (--people): the photo repeated in a grid, each copy
panned a few pixels per frame; the stages after the 2D one run per person, so they cost the
one-person figure times the number of people. Times are wall-clock medians, but the 2D stage's
are means: its scan runs on every third frame only at 30 fps (follow.SCAN_INTERVAL), which a median hides. CPU seconds of the
2D stage are printed too, since other work on a shared machine inflates wall-clock times.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import torch

from humotion.capture.detection import MediaPipePoseDetector
from humotion.capture.follow import DETECTORS, PeopleFinder, make_detector
from humotion.capture.lifting import load_lifter
from humotion.capture.live import LiveCapture
from humotion.capture.overlay import draw_people
from humotion.capture.people import PeopleTracker
from humotion.capture.pipeline import (CaptureConfig, camera_pose, default_camera, initial_fit, lift_segment, refined,
                                       segments_of, straightened)
from humotion.capture.prior import PosePrior
from humotion.capture.refine import CaptureRefineConfig
from humotion.capture.template import DEFAULT_HEIGHT
from humotion.io.video import VideoWriter

PHOTO = Path(__file__).resolve().parents[2] / "shared" / "data" / "images" / "yogait_cc0" / "tadasana_tada1.jpg"


PREVIOUS = CaptureRefineConfig(compiled=False, iterations=75)
"""The previous release's refinement: the same terms, 75 L-BFGS steps a pass, the energy written
in torch and differentiated by autograd (now in float64, as the compiled energy)."""


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
    parser.add_argument("--detector", choices=DETECTORS, default="movenet", help="the 2D detector in the one-person loop")
    parser.add_argument("--people", type=int, nargs="*", default=[1, 4, 8], help="people counts for the 2D stage")
    parser.add_argument("--sizes", nargs="*", default=["640x480", "1280x720"])
    parser.add_argument("--people-frames", type=int, default=60)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    frames = frames_640x480(args.frames)
    lifter, prior = load_lifter(args.weights), PosePrior.load()
    camera = default_camera(640, 480)

    detect_ms, track_ms, overlay_ms, live_ms, seen = [], [], [], [], []
    tracker, live = PeopleTracker(), LiveCapture(camera)
    with make_detector(args.detector, 1) as detector, tempfile.TemporaryDirectory() as folder, \
            VideoWriter(Path(folder) / "overlay.mp4", 30.0) as writer:
        finder = PeopleFinder(detector, tracker)
        for index, frame in enumerate(frames):
            start = time.perf_counter()
            track_before = finder.timings["track"]
            people = finder(frame, index / 30.0)
            tracked = time.perf_counter()
            middle = tracked - (finder.timings["track"] - track_before)     # detection | tracking
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
    lift_segment(lifter, segment, camera)
    lift_s = time.perf_counter() - start
    start = time.perf_counter()
    fit = initial_fit(segment, camera, lifter, DEFAULT_HEIGHT)
    angles_s = time.perf_counter() - start - lift_s               # initial_fit lifts too
    pose = camera_pose([fit], [segment], 30.0, CaptureConfig(), [], camera=camera)
    floor = None if pose.source == "level" else pose
    start = time.perf_counter()
    fit = straightened(fit, segment, camera, pose)
    angles_s += time.perf_counter() - start
    refine_s = {"now": [], "before": [], "75 steps": []}
    for _ in range(2):                      # in turn, the faster of two: the first call warms torch up
        for name, config in (("before", PREVIOUS), ("75 steps", CaptureRefineConfig(iterations=75)),
                             ("now", CaptureRefineConfig())):
            start = time.perf_counter()
            refined(fit, segment, camera, prior, config, floor, 30.0)
            refine_s[name].append(time.perf_counter() - start)
    short = replace(segment, frames=segment.frames[:30], times=segment.times[:30], keypoints=segment.keypoints[:30],
                    confidence=segment.confidence[:30])
    short_fit = replace(fit, rotations=fit.rotations[:30], root=fit.root[:30], network=fit.network[:30],
                        lifted=fit.lifted[:30])
    for _ in range(2):
        start = time.perf_counter()
        refined(short_fit, short, camera, prior, CaptureRefineConfig(), floor, 30.0)
        refine_s.setdefault("1 s", []).append(time.perf_counter() - start)
    refine_s = {name: min(seconds) for name, seconds in refine_s.items()}

    stages = {"tracking + filter": statistics.median(track_ms), "lifting": 1000 * lift_s / n,
              "bones + angles + root": 1000 * angles_s / n, "refinement": 1000 * refine_s["now"] / n}
    print(f"one person, 640x480, {n} frames, one CPU thread")
    print(f"  {'detection (2D, ' + args.detector + ')':28} {statistics.fmean(detect_ms):8.2f} ms/frame (mean)")
    for name, ms in stages.items():
        print(f"  {name:28} {ms:8.2f} ms/frame")
    print(f"  (refinement in the same run: the previous release's, 75 steps a pass, its energy in torch with autograd: "
          f"{1000 * refine_s['before'] / n:.2f} ms/frame; compiled at 75 steps: {1000 * refine_s['75 steps'] / n:.2f}; "
          f"on the clip's first 1 s alone: {1000 * refine_s['1 s'] / 30:.2f} ms/frame;\n   "
          f"camera from {pose.source!r})")
    after = sum(stages.values())
    print(f"  everything after detection   {after:8.2f} ms/frame = {1000 / after:6.1f} fps (goal: 30 fps)")
    print(f"  end to end with detection    {after + statistics.fmean(detect_ms):8.2f} ms/frame = "
          f"{1000 / (after + statistics.fmean(detect_ms)):6.1f} fps")
    print(f"  overlay video (draw + H.264) {statistics.median(overlay_ms):8.2f} ms/frame (median)")
    print(f"  live 3D (causal, per frame)  {statistics.median(live_ms[1:]):8.2f} ms/frame (median; "
          f"p99 {np.percentile(live_ms[1:], 99):.2f})")
    if args.people:
        several_people(args.people, [tuple(int(v) for v in size.split("x")) for size in args.sizes],
                       args.people_frames, after)
    return 0


def people_frames(count: int, people: int, width: int, height: int) -> list[np.ndarray]:
    """The photo repeated `people` times in a grid on a width x height canvas (up to 4 per row, each
    copy as large as its cell allows), each copy panned 2 px per frame."""
    photo = cv2.cvtColor(cv2.imread(str(PHOTO)), cv2.COLOR_BGR2RGB)
    columns = min(people, 4)
    rows = -(-people // columns)
    cell_w, cell_h = width // columns, height // rows
    scale = min(0.9 * cell_w / photo.shape[1], 0.9 * cell_h / photo.shape[0])
    small = cv2.resize(photo, (int(photo.shape[1] * scale), int(photo.shape[0] * scale)), interpolation=cv2.INTER_AREA)
    frames = []
    for k in range(count):
        canvas = np.full((height, width, 3), 90, np.uint8)
        shift = 2 * (k % 10)
        for i in range(people):
            r, c = divmod(i, columns)
            y = r * cell_h + (cell_h - small.shape[0]) // 2
            x = c * cell_w + (cell_w - small.shape[1]) // 2 + shift - 10
            canvas[y:y + small.shape[0], max(x, 0):x + small.shape[1]] = small[:, max(-x, 0):]
        frames.append(canvas)
    return frames


BLOCK = 10
"""Frames each 2D stage runs in a row before the next takes its turn: alternating frame by frame,
each stage found its models pushed out of the CPU caches by the others' (a third slower), which a
real run, one stage on every frame, never sees."""


def several_people(counts: list[int], sizes: list[tuple[int, int]], count: int, after_one: float) -> None:
    """ms per frame of the 2D stage with several people; see the module docstring. Three 2D stages
    run in turn, BLOCK frames each, so that other work on the machine weighs on them alike: MoveNet as
    `humotion capture` runs it (its graphs' padding folded into their convolutions,
    humotion.capture.movenet.folded_model; optical flow between its runs), MoveNet with the
    model on every frame (the baseline), and MediaPipe."""
    print(f"\n2D stage with several people ({count} frames each, one CPU thread; mean ms/frame; "
          f"'after' = {after_one:.2f} ms x people)")
    print("  size       people | movenet: follow   scan  track  2D total  found  CPU s | model every frame: 2D total "
          "| mediapipe: 2D total  found | end to end fps (movenet / model every frame / mediapipe)")
    with make_detector("movenet", 10) as movenet, MediaPipePoseDetector(max_people=10) as mediapipe:
        for width, height in sizes:
            for people in counts:
                frames = people_frames(count, people, width, height)
                finders = {"movenet": PeopleFinder(movenet, PeopleTracker()),
                           "every_frame": PeopleFinder(movenet, PeopleTracker(), detect_every=1),
                           "mediapipe": PeopleFinder(mediapipe, PeopleTracker())}
                totals = {name: [] for name in finders}
                found = {name: [] for name in finders}
                parts = {k: [] for k in finders["movenet"].timings}
                cpu = dict.fromkeys(finders, 0.0)
                for block in range(0, count, BLOCK):         # each finder its own run of frames, in turn
                    for name, finder in finders.items():
                        for index in range(block, min(block + BLOCK, count)):
                            before = dict(finder.timings)
                            start, start_cpu = time.perf_counter(), time.process_time()
                            tracked = finder(frames[index], index / 30.0)
                            totals[name].append(1000 * (time.perf_counter() - start))
                            cpu[name] += time.process_time() - start_cpu
                            found[name].append(len(tracked))
                            if name == "movenet":
                                for k in parts:
                                    parts[k].append(1000 * (finder.timings[k] - before[k]))
                steady = slice(count // 3, None)  # after the first full scan has found everyone
                total = {name: statistics.fmean(v[steady]) for name, v in totals.items()}
                part = {k: statistics.fmean(v[steady]) for k, v in parts.items()}
                seen = {name: statistics.median(v[steady]) for name, v in found.items()}
                after = after_one * people
                fps = " / ".join(f"{1000 / (total[name] + after):.1f}" for name in finders)
                print(f"  {width}x{height:<5d} {people:6d} | {part['follow']:14.2f} {part['scan']:6.2f} "
                      f"{part['track']:6.2f} {total['movenet']:9.2f} {seen['movenet']:6.0f} {cpu['movenet']:6.1f} "
                      f"| {total['every_frame']:27.2f} | {total['mediapipe']:19.2f} {seen['mediapipe']:6.0f} | {fps}")
                if seen["every_frame"] != seen["movenet"]:
                    print(f"    (the model on every frame found {seen['every_frame']:.0f} people)")

if __name__ == "__main__":
    sys.exit(main())

"""Batch capture throughput on this machine: videos per hour and frames per second with 1, 2 and 4
workers, the scaling against one worker, and the time spent starting workers and loading models.

    .venv/bin/python bench/capture_batch.py [--videos 12] [--frames 20] [--workers 1 2 4] [--engines pool ray]
        | tee docs/bench/capture_batch.txt

The batch: --videos clips of --frames frames each, cut (MPEG-4, 768x432, 10 fps) at spread-out
starts from the shared real video of one person at a time walking in a room
(../shared/data/video/intel_one-by-one-person-detection_first40s.mp4), captured with the default
settings (MoveNet, refinement) by humotion.capture.batch.run_batch into a fresh folder per run.
Baseline: the same batch in this process, one video after the other, models already loaded
(engine "inline"). Then each engine ("pool": a local process pool; "ray": a local Ray instance)
with each worker count. Per run: wall-clock seconds, videos per hour, frames per second, the
speed-up over the engine's one worker, each video's capture time (median, models loaded), and the start-up: seconds from the batch's start until each
worker had started, imported humotion and loaded its models (mean over workers; the model loading
alone in brackets), and that start-up summed over the workers per video of the batch. The load
average is printed before each run: the machine is shared, so wall-clock times include others' work.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path

import cv2

from humotion.capture.batch import Worker, run_batch
from humotion.capture.pipeline import CaptureConfig

VIDEO = Path(__file__).resolve().parents[2] / "shared" / "data" / "video" / "intel_one-by-one-person-detection_first40s.mp4"


def cut_clips(folder: Path, count: int, frames: int) -> list[Path]:
    """count clips of frames frames from VIDEO, their starts spread over frames 100-370 (someone in view)."""
    paths = []
    for k in range(count):
        start = 100 + k * (270 // max(count - 1, 1))
        source = cv2.VideoCapture(str(VIDEO))
        source.set(cv2.CAP_PROP_POS_FRAMES, start)
        path = folder / f"clip{k:02d}_{start}.mp4"
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (768, 432))
        for _ in range(frames):
            ok, image = source.read()
            if not ok:
                break
            writer.write(image)
        writer.release()
        source.release()
        paths.append(path)
    return paths


def load() -> str:
    return "load average %.1f %.1f %.1f" % os.getloadavg()


def run(videos, out: Path, engine: str, workers: int, baseline: float | None) -> float:
    """One batch; prints its line; returns its frames per second."""
    before = load()
    report = run_batch(videos, out, CaptureConfig(), workers=workers, engine=engine)
    done = [r for r in report.results if r.status == "done"]
    frames = sum(r.frames for r in done)
    fps = frames / report.seconds
    ready = report.ready_seconds()
    startup = ""
    if engine != "inline" and ready:
        loads = [w.load_seconds for w in report.workers.values()]
        startup = (f"start-up {statistics.mean(ready.values()):5.1f} s per worker ({statistics.mean(loads):.1f} loading "
                   f"models), {sum(ready.values()) / len(videos):4.1f} s per video")
    per_video = statistics.median(r.seconds for r in done)
    scaling = f"x{fps / baseline:4.2f}" if baseline else "  -  "
    print(f"{engine:6s} {workers} worker(s): {len(done)}/{len(videos)} videos, {frames} frames in {report.seconds:6.1f} s: "
          f"{len(done) / report.seconds * 3600:6.0f} videos/h, {fps:5.2f} frames/s, {scaling}, "
          f"capture {per_video:4.1f} s per video (median); {startup}  [{before}]",
          flush=True)
    return fps


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--videos", type=int, default=12)
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument("--engines", nargs="+", default=["pool", "ray"], choices=["pool", "ray"])
    args = parser.parse_args()
    cores = len(os.sched_getaffinity(0))
    print(f"machine: {platform.processor() or platform.machine()}, {cores} cores, shared with other jobs; {load()}")
    with tempfile.TemporaryDirectory() as tmp:
        videos = cut_clips(Path(tmp), args.videos, args.frames)
        print(f"batch: {len(videos)} clips x {args.frames} frames (768x432, 10 fps) of {VIDEO.name}")
        start = time.perf_counter()
        Worker(CaptureConfig())
        print(f"one worker's models load in this (warm) process in {time.perf_counter() - start:.2f} s")
        run(videos, Path(tmp) / "inline", "inline", 1, None)
        for engine in args.engines:
            baseline = None
            for workers in args.workers:
                fps = run(videos, Path(tmp) / f"{engine}{workers}", engine, workers, baseline)
                baseline = baseline or fps
    print(f"done; {load()}")


if __name__ == "__main__":
    main()

"""Batch capture: many videos, each into its own folder, resumable, with one summary (docs/batch.md).

    videos = find_videos("videos/")              # a folder, a glob ("videos/**/*.mp4") or a list file (.txt)
    report = run_batch(videos, "out/", CaptureConfig(), workers=2)

Each video is captured by humotion.capture.pipeline.capture into out/<name>/, name being its path
relative to the videos' common folder without the suffix (videos/day1/a.mp4 -> out/day1/a/). A
video that fails (unreadable, corrupt, an error in the pipeline) is reported in its result and the
batch goes on. A finished video gets a marker, out/<name>/done.json, written last and atomically
(a temporary file renamed) with its result and the settings it was made with; a rerun skips the
videos whose marker names the same settings, so an interrupted batch resumes, and a video
interrupted midway (no marker) is done again. out/summary.csv and out/summary.json list every
video's result; they are rewritten (atomically) after each video, so a killed batch leaves one.

Engines (run_batch's engine): "inline" captures in this process, one video after the other;
"pool" in a local process pool (concurrent.futures, spawned processes); "ray" on Ray actors, on
this machine or on a cluster (address; `pip install humotion[cluster]`). Each worker loads the
detector, the lifter and the pose prior once (Worker), then captures video after video. Workers
write the outputs themselves to the paths the driver gives: on a cluster, out_dir and the videos
must be on storage every node sees at the same path (docs/batch.md).

Nothing is printed: results go to the on_result callback, notes to the module's logger.
"""

from __future__ import annotations

import csv
import glob
import importlib.util
import io
import json
import logging
import os
import socket
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field
from multiprocessing import get_context
from pathlib import Path
from typing import Callable, Iterable, Iterator

from humotion.capture.pipeline import CaptureConfig
from humotion.io.paths import write_atomic

log = logging.getLogger(__name__)

VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv", ".flv", ".ts", ".gif")
LIST_SUFFIX = ".txt"
MARKER = "done.json"
SUMMARY_FIELDS = ("video", "output", "status", "people", "frames", "seconds", "warnings", "error", "worker", "skipped")
ENGINES = ("inline", "pool", "ray")


@dataclass
class VideoResult:
    """One video's row of the summary.

    video: its path; output: its folder, relative to the batch's output folder. status: "done",
    "failed" (error says why), "interrupted" (stopped midway, to be redone) or "pending" (not
    reached). people: distinct person ids found; frames: frames read; seconds: wall-clock seconds
    its capture took (models already loaded). warnings: the pipeline's. worker: "host:pid" of the
    process that made it. skipped: finished by an earlier run and not redone (its figures are
    that run's)."""

    video: str
    output: str
    status: str = "pending"
    people: int = 0
    frames: int = 0
    seconds: float = 0.0
    warnings: list[str] = field(default_factory=list)
    error: str = ""
    worker: str = ""
    skipped: bool = False


@dataclass
class WorkerInfo:
    """A worker's start: load_seconds spent loading the models; ready_at: time.time() when it was
    ready (after starting, importing and loading)."""

    name: str
    load_seconds: float
    ready_at: float


@dataclass
class BatchReport:
    """What run_batch did: every video's result (in input order), the workers that ran (name ->
    WorkerInfo; ready_seconds gives each one's start-up from the batch's start), the wall-clock
    seconds, the summary files, and whether the batch was interrupted (Ctrl-C)."""

    results: list[VideoResult]
    workers: dict[str, WorkerInfo]
    started_at: float
    seconds: float
    summary_csv: Path
    summary_json: Path
    interrupted: bool = False

    def ready_seconds(self) -> dict[str, float]:
        """{worker: seconds from the batch's start until it had started and loaded the models}."""
        return {name: info.ready_at - self.started_at for name, info in self.workers.items()}

    def count(self, status: str) -> int:
        return sum(r.status == status for r in self.results)


# --- which videos, and where each one goes ------------------------------------------------------

def is_batch(source: str) -> bool:
    """Whether a capture source names several videos: a folder, a glob pattern (* ? [) that is not
    an existing file, or a list file (.txt)."""
    path = Path(source)
    return path.is_dir() or path.suffix.lower() == LIST_SUFFIX or (
        not path.exists() and any(c in source for c in "*?["))


def find_videos(source: str, exclude: str | Path | None = None) -> list[Path]:
    """The videos a batch source names, as absolute paths, sorted, without repeats:
    - a folder: the files with a VIDEO_SUFFIXES suffix in it and its subfolders;
    - a glob pattern ("**" reaches into subfolders): the files it matches;
    - a list file (.txt): one path a line, relative to the list's folder; blank lines and lines
      starting with # are skipped; missing files are kept (they fail, and are reported, when run).
    Files under exclude (the output folder) are left out. ValueError when none is found."""
    path = Path(source)
    if path.is_dir():
        found = [p for p in path.rglob("*") if p.suffix.lower() in VIDEO_SUFFIXES and p.is_file()]
    elif path.suffix.lower() == LIST_SUFFIX:
        if not path.is_file():
            raise ValueError(f"{source}: list of videos not found")
        lines = [line.strip() for line in path.read_text().splitlines()]
        found = [path.parent / line for line in lines if line and not line.startswith("#")]
    else:
        found = [Path(p) for p in glob.glob(source, recursive=True) if Path(p).is_file()]
    videos = sorted({p.absolute() for p in found})
    if exclude is not None:
        out = Path(exclude).absolute()
        videos = [v for v in videos if out not in v.parents]
    if not videos:
        raise ValueError(f"{source}: no videos found (a folder is searched for {', '.join(VIDEO_SUFFIXES)})")
    return videos


def output_names(videos: list[Path]) -> list[str]:
    """Each video's output folder, relative to the batch's output folder: its path relative to the
    videos' common folder, without the suffix ("day1/a"); where two videos would share one (a.mp4
    and a.avi), both keep their suffix ("a_mp4", "a_avi")."""
    videos = [Path(v).absolute() for v in videos]
    common = Path(os.path.commonpath([v.parent for v in videos]))
    names = [v.relative_to(common).with_suffix("").as_posix() for v in videos]
    clash = {n for n in names if names.count(n) > 1}
    return [f"{n}_{v.suffix.lstrip('.')}" if n in clash else n for n, v in zip(names, videos)]


def settings_of(config: CaptureConfig, weights: str | Path | None = None) -> dict:
    """The settings a marker records (the capture config and the lifter's weights), as JSON values."""
    return json.loads(json.dumps({"config": asdict(config), "weights": None if weights is None else str(weights)},
                                 sort_keys=True, default=str))


# --- one worker --------------------------------------------------------------------------------

class Worker:
    """Loads the models once (detector, lifter, pose prior), then captures video after video.

    threads: torch and OpenCV threads for this worker (None: leave them). Made in this process
    (inline), in each process of a pool, or as a Ray actor (ray.remote(Worker)); those get one
    thread each: the workers are the parallelism, and a capture's tensors are small."""

    def __init__(self, config: CaptureConfig, weights: str | Path | None = None, threads: int | None = None):
        start = time.perf_counter()
        import torch

        from humotion.capture.follow import make_detector
        from humotion.capture.lifting import load_lifter
        from humotion.capture.prior import PosePrior

        if threads is not None:
            import cv2

            torch.set_num_threads(threads)
            cv2.setNumThreads(threads)
        self.config = config
        self.lifter, self.prior = load_lifter(weights), PosePrior.load()
        self.detector = make_detector(config.detector, config.max_people)
        self.info = WorkerInfo(f"{socket.gethostname()}:{os.getpid()}", time.perf_counter() - start, time.time())

    def run(self, video: str, out_dir: str, name: str, settings: dict) -> tuple[VideoResult, WorkerInfo]:
        """Capture video into out_dir/name; on success the marker is written last. Any error of
        the capture is caught into the result (status "failed"); Ctrl-C gives "interrupted"."""
        from humotion.capture.pipeline import capture

        folder = Path(out_dir) / name
        result = VideoResult(str(video), name, worker=self.info.name)
        start = time.perf_counter()
        try:
            made = capture(video, folder, self.config, detector=self.detector, lifter=self.lifter, prior=self.prior,
                           progress=False)
        except Exception as error:      # reported in the summary; the batch goes on
            result.status, result.error = "failed", _one_line(error, str(video))
            result.seconds = round(time.perf_counter() - start, 3)
            return result, self.info
        result.seconds = round(time.perf_counter() - start, 3)
        result.people = len({p.segment.person for p in made.people})
        result.frames = _frames_read(folder)
        result.warnings = list(made.warnings)
        if made.interrupted:
            result.status = "interrupted"
        else:
            result.status = "done"
            _write_json(folder / MARKER, {"result": asdict(result), "settings": settings})
        return result, self.info


def _one_line(error: Exception, video: str | None = None) -> str:
    """The error on one line: a file error about the video itself gives its problem alone (the row
    names the video), any other error its type and message."""
    from humotion.io.errors import MotionFileError

    if isinstance(error, MotionFileError) and error.path == video and error.line is None:
        return " ".join(error.problem.split())
    return f"{type(error).__name__}: {' '.join(str(error).split())}"


def _frames_read(folder: Path) -> int:
    """Frames the capture read: those of its overlay video (1 for a still image's overlay.png)."""
    from humotion.io.video import open_frames

    if (folder / "overlay.png").is_file():
        return 1
    try:
        with open_frames(folder / "overlay.mp4") as frames:
            return frames.frame_count
    except Exception:       # no overlay (nothing read): no frames to count
        return 0


_worker: Worker | None = None      # the pool process's worker (made by _start_pool_worker)


def _start_pool_worker(config: CaptureConfig, weights, threads: int) -> None:
    global _worker
    _worker = Worker(config, weights, threads)


def _run_in_pool(job: tuple) -> tuple[VideoResult, WorkerInfo]:
    return _worker.run(*job)


# --- engines: each yields (result, worker info or None) as videos finish ----------------------------

def _inline(jobs: list[tuple], config, weights, workers, address) -> Iterator[tuple]:
    worker = Worker(config, weights)
    for job in jobs:
        yield worker.run(*job)


def _pool(jobs: list[tuple], config, weights, workers, address) -> Iterator[tuple]:
    pool = ProcessPoolExecutor(workers, mp_context=get_context("spawn"), initializer=_start_pool_worker,
                               initargs=(config, weights, 1))
    try:
        futures = {pool.submit(_run_in_pool, job): job for job in jobs}
        for future in as_completed(futures):
            try:
                yield future.result()
            except Exception as error:       # the process died or could not start: only this video fails
                yield _failed(futures[future], f"the worker process failed: {_one_line(error)}"), None
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _ray(jobs: list[tuple], config, weights, workers, address) -> Iterator[tuple]:
    try:
        import ray
    except ImportError:
        raise ValueError("Ray is not installed: pip install 'humotion[cluster]' (or run without --ray-address)") from None
    started = not ray.is_initialized()
    if started:
        _check_reachable(address)
        try:
            ray.init(address=address, num_cpus=None if address else workers, include_dashboard=False,
                     log_to_driver=False, logging_level=logging.ERROR)
        except ConnectionError as error:
            raise ValueError(f"cannot connect to the Ray cluster at {address} ({_one_line(error)}); where it was "
                             "started with token authentication, set RAY_AUTH_MODE=token here (docs/batch.md)") from None
    try:
        cpus = max(int(ray.cluster_resources().get("CPU", 0)), 1)
        if workers is None:
            workers = cpus       # one worker per CPU of the cluster
        elif workers > cpus:     # an actor needs a CPU: more would wait forever
            log.warning("%d workers asked for, the Ray cluster has %d CPUs: %d workers", workers, cpus, cpus)
            workers = cpus
        actor = ray.remote(num_cpus=1)(Worker)
        idle = [actor.remote(config, weights, 1) for _ in range(min(workers, len(jobs)))]
        queue, running = list(jobs), {}
        while queue or running:
            while idle and queue:
                worker, job = idle.pop(), queue.pop(0)
                running[worker.run.remote(*job)] = (worker, job)
            if not running:     # every worker was lost
                for job in queue:
                    yield _failed(job, "no Ray worker left (each one failed)"), None
                return
            [ref], _ = ray.wait(list(running), num_returns=1)
            worker, job = running.pop(ref)
            try:
                yield ray.get(ref)
                idle.append(worker)
            except ray.exceptions.RayActorError as error:     # the worker (or its node) is gone: not reused
                yield _failed(job, f"the Ray worker failed: {_one_line(error)}"), None
            except ray.exceptions.RayError as error:
                yield _failed(job, f"Ray: {_one_line(error)}"), None
                idle.append(worker)
    finally:
        if started:
            ray.shutdown()


def _check_reachable(address: str | None, timeout: float = 10.0) -> None:
    """ValueError when nothing answers at a Ray address "HOST:PORT" (ray.init would retry for many
    minutes); None (a local instance) and "auto" are not checked."""
    if not address or address == "auto" or "://" in address:
        return
    host, _, port = address.rpartition(":")
    try:
        socket.create_connection((host, int(port)), timeout=timeout).close()
    except (OSError, ValueError) as error:
        raise ValueError(f"nothing answers at the Ray address {address} ({_one_line(error)}): is `ray start "
                         "--head` running there, and the port open?") from None


_ENGINE_RUNS = {"inline": _inline, "pool": _pool, "ray": _ray}


def _failed(job: tuple, error: str) -> VideoResult:
    video, _, name, _ = job
    return VideoResult(str(video), name, "failed", error=error)


def _cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def choose_engine(workers: int, address: str | None = None) -> str:
    """"ray" with a cluster address; else "inline" for one worker; else "ray" when Ray is
    installed, "pool" when not."""
    if address:
        return "ray"
    if workers <= 1:
        return "inline"
    return "ray" if importlib.util.find_spec("ray") is not None else "pool"


# --- the batch ---------------------------------------------------------------------------------

def run_batch(videos: Iterable[str | Path], out_dir: str | Path, config: CaptureConfig = CaptureConfig(),
              weights: str | Path | None = None, workers: int | None = None, engine: str | None = None,
              address: str | None = None, on_result: Callable[[VideoResult], None] | None = None) -> BatchReport:
    """Capture every video into out_dir/<name>/ (output_names), skipping those finished by an
    earlier run with the same settings; write out_dir/summary.csv and summary.json.

    workers: processes capturing at once (None: this machine's cores, or the cluster's CPUs with
    address). engine: one of ENGINES (None: choose_engine). address: a Ray cluster's address
    ("HOST:6379", or "auto" on a node of it). on_result(result) is called once per video, the
    skipped ones first, the others as they finish (for a progress bar). Ctrl-C stops the batch:
    the summary is written with the videos not reached as "pending", and report.interrupted set.
    ValueError for an unknown engine or when Ray is needed and missing."""
    videos = [Path(v).absolute() for v in videos]
    out = Path(out_dir).absolute()
    out.mkdir(parents=True, exist_ok=True)
    settings = settings_of(config, weights)
    results = [VideoResult(str(v), name) for v, name in zip(videos, output_names(videos))]
    jobs, index = [], {}
    for i, result in enumerate(results):
        earlier = _finished(out / result.output, settings)
        if earlier is not None:
            results[i] = earlier
        else:
            jobs.append((result.video, str(out), result.output, settings))
            index[result.output] = i
    engine = engine or choose_engine(workers or _cores(), address)
    if engine not in ENGINES:
        raise ValueError(f"unknown engine {engine!r}: choose one of {', '.join(ENGINES)}")
    report = BatchReport(results, {}, time.time(), 0.0, out / "summary.csv", out / "summary.json")
    log.info("%d videos: %d finished earlier, %d to capture (%s, %s workers)", len(results),
             len(results) - len(jobs), len(jobs), engine, workers or "all")
    for result in results:
        if result.skipped and on_result:
            on_result(result)
    try:
        if jobs:
            if engine != "ray":
                workers = min(workers or _cores(), len(jobs))
            for result, info in _ENGINE_RUNS[engine](jobs, config, weights, workers, address):
                results[index[result.output]] = result
                if info is not None:
                    report.workers.setdefault(info.name, info)
                if result.status == "failed":
                    log.info("%s failed: %s", result.video, result.error)
                _write_summary(report)
                if on_result:
                    on_result(result)
                if result.status == "interrupted":      # Ctrl-C reached the worker's capture
                    raise KeyboardInterrupt
    except KeyboardInterrupt:
        report.interrupted = True
    finally:
        report.seconds = time.time() - report.started_at
        _write_summary(report)
    return report


def _finished(folder: Path, settings: dict) -> VideoResult | None:
    """The result in folder's marker when it was made with these settings (skipped=True), else None."""
    try:
        marker = json.loads((folder / MARKER).read_text())
        result = VideoResult(**marker["result"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if marker.get("settings") != settings:
        log.info("%s: made with other settings, captured again", folder)
        return None
    result.skipped = True
    return result


def _write_summary(report: BatchReport) -> None:
    """summary.json ({"videos", "counts" by status, "seconds", "results": rows}) and summary.csv
    (SUMMARY_FIELDS, warnings joined by " | "), each atomically."""
    rows = [asdict(r) for r in report.results]
    counts = {s: report.count(s) for s in ("done", "failed", "interrupted", "pending")}
    _write_json(report.summary_json, {"videos": len(rows), "counts": counts, "skipped": sum(r["skipped"] for r in rows),
                                      "seconds": round(report.seconds, 3), "interrupted": report.interrupted,
                                      "results": rows})
    text = io.StringIO()
    writer = csv.DictWriter(text, SUMMARY_FIELDS)
    writer.writeheader()
    writer.writerows({**r, "warnings": " | ".join(r["warnings"])} for r in rows)
    write_atomic(report.summary_csv, text.getvalue().encode())


def _write_json(path: Path, value) -> None:
    write_atomic(path, json.dumps(value, indent=1).encode())

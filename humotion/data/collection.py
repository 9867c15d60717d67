"""Mocap collections: index every motion file under a folder, cache parsed arrays, split by subject.

    collection = MotionCollection.load("../shared/data/mocap")     # first load parses, later loads read the cache
    print(collection.summary())                                    # per source: clips, minutes, subjects, skipped
    splits = collection.split((0.8, 0.1, 0.1), seed=0)             # {'train': [subject ids], 'val': [...], 'test': [...]}
    train = collection.windows(length=40, fps=30.0, split="train", signature=...)  # torch Dataset

A *source* is a top-level folder of the tree (or the root itself when it holds a SOURCE.md).
A *subject* id names the person, the same across sources (see :func:`subject_id`); splits are
made by subject, never by clip, so one person's takes never sit on both sides of an evaluation.
The parsed-array cache lives in humotion.data.cache, the split rules in humotion.data.split.

Paths and symlinks, one rule: the root is resolved once (symlinks followed), and every path the
collection gives (``.root``, clip and skipped paths) is that resolved root joined with the file's
path under it. Links to folders inside the tree are followed (a source kept on another drive),
each real folder read once. Relate clip paths to ``collection.root``, not to the path given.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import time
from collections import defaultdict
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path, PurePath
from typing import Callable, Iterable, Iterator, Sequence

import torch
from tqdm.auto import tqdm

from humotion.data.cache import CACHE_VERSION, cache_key, default_cache_dir, read_cache, read_cache_meta, write_cache
from humotion.data.split import EVALUATION_ONLY, SPLIT_NAMES, TOGETHER, split_subjects
from humotion.io import READABLE, load_motion
from humotion.io.amass import companion_files as amass_companions
from humotion.io.errors import base_suffix
from humotion.motion import Motion
from humotion.skeleton import Skeleton

__all__ = ["MotionCollection", "Clip", "Skipped", "subject_id", "skeleton_signature", "UNSUPPORTED",
           "WHOLE_SOURCE_SUBJECTS",
           # re-exported from humotion.data.cache and humotion.data.split
           "CACHE_VERSION", "cache_key", "default_cache_dir", "split_subjects", "TOGETHER", "EVALUATION_ONLY",
           "SPLIT_NAMES"]

log = logging.getLogger("humotion.data")

UNSUPPORTED = {".fbx": "unsupported format"}
"""Motion formats found in the wild that humotion does not read: listed as skipped, not errors."""

WHOLE_SOURCE_SUBJECTS = {"cmu_expmap_li2018": "cmu-expmap-unknown"}
"""Sources whose clips cannot all be tied to a person: the whole source is one subject (one
split group). cmu_expmap_li2018 does not say which CMU trials its 96 clips are."""


# -- subjects ------------------------------------------------------------------------------

def subject_id(source: str, relpath: str | PurePath) -> str:
    """The person a clip shows, from its source folder and path inside it.

    'cmu-NN' for CMU takes named <subject>_<trial>... (001_01.bvh, 01_01.amc, 60_01_scaled.bvh,
    07_01-walk.amc -> 'cmu-01', 'cmu-01', 'cmu-60', 'cmu-07') in sources named cmu*; 'hdm05-bd'
    for HDM05 files HDM_bd_...; WHOLE_SOURCE_SUBJECTS for sources without per-clip subjects;
    '<source>-<folder>' for AMASS files (.npz), whose first folder in a dataset is the subject
    (BMLmovi/Subject_1_F_MoSh/... -> 'BMLmovi-Subject_1_F_MoSh'; AMASS's CMU takes: 'cmu-NN');
    otherwise '<source>-unknown' (the whole source one group, the safe default).
    """
    name = PurePath(relpath).name
    if source in WHOLE_SOURCE_SUBJECTS:
        return WHOLE_SOURCE_SUBJECTS[source]
    match = re.match(r"HDM_([A-Za-z]+)_", name)
    if match:
        return f"hdm05-{match.group(1).lower()}"
    match = re.match(r"(\d+)_\d+", name)
    if match and source.lower().startswith("cmu"):
        return f"cmu-{int(match.group(1)):02d}"
    parts = PurePath(relpath).parts
    if name.lower().endswith(".npz") and len(parts) > 1:      # AMASS: <dataset>/<subject>/<take>_poses.npz
        return f"{source}-{parts[0]}"
    return f"{source}-unknown"


def skeleton_signature(skeleton: Skeleton) -> str:
    """'<J>j-<hash>': equal for skeletons with the same joint names and tree (offsets may differ),
    i.e. for motions whose rotation arrays can be stacked."""
    text = "|".join(f"{n}:{p}" for n, p in zip(skeleton.names, skeleton.parents))
    return f"{skeleton.num_joints}j-{hashlib.sha1(text.encode()).hexdigest()[:8]}"


# -- clips ---------------------------------------------------------------------------------

@dataclass(frozen=True)
class Clip:
    """One motion file of a collection (metadata only; :meth:`load` gives the Motion).

    path: absolute file path. source: top-level folder. subject: person id (see subject_id).
    frames, fps: as read (fps is the file's, or 120 Hz for formats without one).
    num_joints, signature: the skeleton (see skeleton_signature).
    """

    path: Path
    source: str
    subject: str
    frames: int
    fps: float
    num_joints: int
    signature: str
    cache_file: Path | None = field(default=None, repr=False)
    _motion: Motion | None = field(default=None, repr=False, compare=False)

    @property
    def duration(self) -> float:
        """Seconds."""
        return self.frames / self.fps

    @property
    def name(self) -> str:
        """File name without .gz and format suffix: '01_01', 'HDM_bd_squat1Reps_001_120'."""
        stem = self.path.name[:-3] if self.path.name.lower().endswith(".gz") else self.path.name
        return stem.rsplit(".", 1)[0]

    def load(self) -> Motion:
        """The Motion, from memory, the cache (rebuilt when missing or corrupt) or the file."""
        if self._motion is not None:
            return self._motion
        if self.cache_file is not None:
            motion = read_cache(self.cache_file)
            if motion is not None:
                return motion
        return _parse(self.path, self.cache_file)


def _worker_init() -> None:
    torch.set_num_threads(1)  # one process per CPU already


def _parse_result(path: Path, cache_file: Path | None, keep: bool) -> tuple[dict | None, Motion | None, str | None]:
    """(metadata, the Motion when keep, None) for a readable file; (None, None, reason) otherwise."""
    try:
        motion = _parse(path, cache_file)
    except Exception as error:  # MotionFileError names the file; anything else is a reader bug
        reason = str(error) if str(path) in str(error) else f"{path}: {type(error).__name__}: {error}"
        return None, None, reason
    meta = dict(frames=motion.num_frames, fps=motion.fps, skeleton=motion.skeleton)
    return meta, (motion if keep else None), None


def _parse(path: Path, cache_file: Path | None) -> Motion:
    """Read a motion file (raises MotionFileError) and store it in the cache when one is given."""
    motion = load_motion(path)
    if not motion.name:
        stem = path.name[:-3] if path.name.lower().endswith(".gz") else path.name
        motion.name = stem.rsplit(".", 1)[0]
    if cache_file is not None:
        write_cache(cache_file, motion)
    return motion


@dataclass(frozen=True)
class Skipped:
    """A file that is not in the collection and why (unsupported format, or the reader's error)."""

    path: Path
    source: str
    reason: str


# -- scanning ------------------------------------------------------------------------------

def _is_motion_file(path: Path) -> bool:
    return base_suffix(path) in READABLE and path.name not in {"README.txt", "LICENSE.txt", "shape.npz"}


def _files(folder: Path, bar: tqdm | None = None) -> list[Path]:
    """Every file under folder, sorted, following links to folders (each real folder once, so a
    link back up the tree ends); broken links are left out. bar: a progress bar advanced per file."""
    found, seen = [], set()
    for top, folders, names in os.walk(folder, followlinks=True):
        folders.sort()
        real = os.path.realpath(top)
        if real in seen:
            folders.clear()
            continue
        seen.add(real)
        found += [p for p in (Path(top, name) for name in names) if p.is_file()]
        if bar is not None:
            bar.update(len(names))
    return sorted(found)


def _scan(root: Path, bar: tqdm | None = None) -> list[tuple[Path, str, Path]]:
    """(file, source, source folder) for every motion file (readable or UNSUPPORTED) under root,
    sorted. The source is the top-level folder, or root itself for files directly in it or when
    root holds a SOURCE.md (one source given on its own). bar: advanced per file looked at."""
    single = (root / "SOURCE.md").exists()
    found = []
    for path in _files(root, bar):
        if not (_is_motion_file(path) or base_suffix(path) in UNSUPPORTED):
            continue
        rel = path.relative_to(root)
        if single or len(rel.parts) == 1:
            found.append((path, root.name, root))
        else:
            found.append((path, rel.parts[0], root / rel.parts[0]))
    return found


def _companions(source_dir: Path) -> list[Path]:
    """Skeleton files a reader may use for a clip in this source: every .asf and .json in it."""
    return [p for p in _files(source_dir) if p.suffix.lower() in (".asf", ".json")]


# -- the collection ------------------------------------------------------------------------

class MotionCollection:
    """Clips indexed from a folder tree, with the files that were skipped and why.

    clips: Clip list (sorted by path). skipped: Skipped list. Iterating gives the clips.
    """

    def __init__(self, clips: Sequence[Clip], skipped: Sequence[Skipped] = (), root: Path | None = None):
        self.clips, self.skipped, self.root = list(clips), list(skipped), root

    # -- loading ---------------------------------------------------------------------------
    @classmethod
    def load(cls, root: str | Path, *, cache_dir: str | Path | None = None, cache: bool = True,
             sources: Iterable[str] | None = None, exclude: Iterable[str] = (),
             subject_fn: Callable[[str, PurePath], str] = subject_id,
             workers: int | None = None, progress: bool = True) -> "MotionCollection":
        """Index every motion file under root (BVH, AMC with its ASF, exp-map .txt, each maybe .gz);
        root is resolved and links to folders under it are followed (module docstring).

        cache_dir: where parsed arrays are kept (default: default_cache_dir()); cache=False keeps
            the motions in memory instead. sources / exclude: top-level folder names to keep / drop.
        subject_fn(source, path relative to the source folder) -> subject id (default subject_id).
        workers: processes parsing files not yet cached (default: one per CPU, at most 8; 1 = serial).
        progress: tqdm bars on stderr while the tree is walked (if that takes over a second) and
            while files not yet cached are read.
        Unsupported (FBX) and unreadable files are listed in .skipped (unreadable ones also
        logged with the reader's message); one bad file never stops the load.
        """
        root = Path(root).expanduser().resolve()
        if not root.is_dir():
            raise FileNotFoundError(f"no such folder: {root}")
        keep, drop = (set(sources) if sources is not None else None), set(exclude)
        # The walk can take seconds on a cold disk: a bar, shown only if it lasts over a second.
        with tqdm(desc="looking for motion files", unit="file", delay=1.0, disable=not progress) as bar:
            found = _scan(root, bar)
        files = [f for f in found if (keep is None or f[1] in keep) and f[1] not in drop]
        cache_root = (Path(cache_dir) if cache_dir is not None else default_cache_dir()) / "motions"
        start = time.perf_counter()
        cache_files, results, todo = _from_cache(files, cache_root if cache else None)
        workers = min(os.cpu_count() or 1, 8) if workers is None else max(1, workers)
        results.update(_parse_all(todo, keep=not cache, workers=workers, progress=progress))
        clips, skipped = _clips(files, results, cache_files, subject_fn)
        collection = cls(clips, skipped, root)
        log.info("indexed %d clips (%.1f min, %d files read, %d from cache) and skipped %d files under %s in %.1f s",
                 len(clips), collection.minutes, len(todo), len(results) - len(todo), len(skipped), root,
                 time.perf_counter() - start)
        return collection

    # -- access ----------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.clips)

    def __iter__(self) -> Iterator[Clip]:
        return iter(self.clips)

    def __getitem__(self, index: int) -> Clip:
        return self.clips[index]

    @property
    def minutes(self) -> float:
        return sum(c.duration for c in self.clips) / 60

    def sources(self) -> list[str]:
        return sorted({c.source for c in self.clips})

    def subjects(self, source: str | None = None) -> list[str]:
        """Subject ids (of one source when given), sorted."""
        return sorted({c.subject for c in self.clips if source is None or c.source == source})

    def signatures(self) -> dict[str, int]:
        """Skeleton signature -> number of clips."""
        counts: dict[str, int] = defaultdict(int)
        for c in self.clips:
            counts[c.signature] += 1
        return dict(sorted(counts.items()))

    def filter(self, *, sources: Iterable[str] | None = None, exclude: Iterable[str] = (),
               subjects: Iterable[str] | None = None, signature: str | None = None) -> "MotionCollection":
        """The clips of the given sources / subjects / skeleton signature, without excluded sources."""
        keep_src = set(sources) if sources is not None else None
        keep_sub = set(subjects) if subjects is not None else None
        drop = set(exclude)
        clips = [c for c in self.clips
                 if (keep_src is None or c.source in keep_src) and c.source not in drop
                 and (keep_sub is None or c.subject in keep_sub) and (signature is None or c.signature == signature)]
        return MotionCollection(clips, self.skipped, self.root)

    # -- splits ----------------------------------------------------------------------------
    def subject_minutes(self) -> dict[str, float]:
        """Subject id -> minutes of motion."""
        minutes: dict[str, float] = defaultdict(float)
        for c in self.clips:
            minutes[c.subject] += c.duration / 60
        return dict(minutes)

    def split(self, fractions: Sequence[float] = (0.8, 0.1, 0.1), seed: int = 0, *,
              names: Sequence[str] = SPLIT_NAMES, pin: dict[str, str] | None = None,
              together: Iterable[Sequence[str]] = TOGETHER,
              evaluation_only: Iterable[str] = EVALUATION_ONLY) -> dict[str, list[str]]:
        """Subjects into splits: {'train': [...], 'val': [...], 'test': [...]}, deterministic.

        The subjects of `evaluation_only` sources go to the last split (test) unless pinned, on
        top of the others, which are balanced by minutes (see :func:`split_subjects`).
        """
        minutes = self.subject_minutes()
        held_out = {c.subject for c in self.clips if c.source in set(evaluation_only)} - set(pin or {})
        splits = split_subjects({s: m for s, m in minutes.items() if s not in held_out}, fractions, seed,
                                names=names, pin=pin, together=together)
        splits[names[-1]] = sorted(splits[names[-1]] + list(held_out))
        return splits

    def windows(self, length: int, fps: float, split: str | Iterable[str] | None = None, *,
                splits: dict[str, list[str]] | None = None, stride: int | None = None,
                transform: Callable[[Motion], Motion] | None = None, signature: str | None = None,
                augment: Callable[[Motion], Motion] | None = None, as_motion: bool = False, progress: bool = False):
        """A torch Dataset of fixed-length windows (see humotion.data.windows.MotionWindows).

        split: a split name (subjects from `splits`, default self.split()), or subject ids, or None for all.
        signature: keep only clips on this skeleton; otherwise every clip (after transform) must
            share one skeleton, else ValueError.
        """
        from humotion.data.windows import MotionWindows

        clips = self
        if isinstance(split, str):
            splits = splits if splits is not None else self.split()
            if split not in splits:
                raise KeyError(f"no split {split!r}; splits: {', '.join(splits)}")
            clips = self.filter(subjects=splits[split])
        elif split is not None:
            clips = self.filter(subjects=split)
        if signature is not None:
            clips = clips.filter(signature=signature)
        if transform is None and len(clips.signatures()) > 1:
            found = ", ".join(f"{sig} ({n} clips)" for sig, n in clips.signatures().items())
            raise ValueError(f"windows would mix skeletons that cannot be stacked: {found}. Pass signature= "
                             "to keep one, or a transform that maps every clip onto one skeleton.")
        return MotionWindows(clips.clips, length, fps, stride=stride, transform=transform, augment=augment,
                             as_motion=as_motion, progress=progress)

    # -- report ----------------------------------------------------------------------------
    def summary(self) -> str:
        """A text table per source (clips, minutes, subjects, skeletons, skipped files) and the
        list of skipped files with their reasons."""
        rows = [("source", "clips", "minutes", "subjects", "joints", "skipped", "subject ids")]
        for source in sorted({c.source for c in self.clips} | {s.source for s in self.skipped}):
            clips = [c for c in self.clips if c.source == source]
            subjects = sorted({c.subject for c in clips})
            joints = "/".join(str(j) for j in sorted({c.num_joints for c in clips})) or "-"
            rows.append((source, str(len(clips)), f"{sum(c.duration for c in clips) / 60:.2f}",
                         str(len(subjects)), joints, str(sum(s.source == source for s in self.skipped)),
                         _abbreviate(subjects)))
        rows.append(("total", str(len(self)), f"{self.minutes:.2f}", str(len(self.subjects())), "-",
                     str(len(self.skipped)), ""))
        widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
        lines = ["  ".join(v.ljust(w) if i in (0, 6) else v.rjust(w) for i, (v, w) in enumerate(zip(r, widths))).rstrip()
                 for r in rows]
        lines.insert(1, "-" * len(lines[0]))
        lines.insert(len(lines) - 1, "-" * len(lines[0]))
        if self.skipped:
            lines.append("")
            lines.append("skipped files:")
            lines += [f"  {s.path}: {s.reason}" if str(s.path) not in s.reason else f"  {s.reason}" for s in self.skipped]
        return "\n".join(lines)

    def __repr__(self) -> str:
        return (f"MotionCollection({len(self)} clips, {self.minutes:.1f} min, {len(self.subjects())} subjects, "
                f"{len(self.sources())} sources, {len(self.skipped)} skipped)")


def _abbreviate(items: list[str], limit: int = 6) -> str:
    return ", ".join(items) if len(items) <= limit else ", ".join(items[:limit]) + f", ... (+{len(items) - limit})"


# -- loading steps ---------------------------------------------------------------------------

def _from_cache(files: list[tuple[Path, str, Path]], cache_root: Path | None):
    """Step 1 of MotionCollection.load: the metadata of every readable file whose cache entry is
    valid. Returns (path -> cache file or None, path -> (meta, None, None), [(path, cache file)]
    still to parse). cache_root None: no cache, every file is parsed."""
    companions: dict[str, list[Path]] = {}
    cache_files: dict[Path, Path | None] = {}
    results: dict[Path, tuple] = {}  # path -> (meta, motion or None, error or None)
    todo: list[tuple[Path, Path | None]] = []
    for path, source, source_dir in files:
        if base_suffix(path) in UNSUPPORTED:
            continue
        if source not in companions:
            companions[source] = _companions(source_dir)
        readers = companions[source] + amass_companions(path)     # + the SMPL-H model an AMASS file is read with
        cache_files[path] = cache_root / f"{cache_key(path, readers)}.npz" if cache_root is not None else None
        meta = read_cache_meta(cache_files[path]) if cache_root is not None else None
        if meta is None:
            todo.append((path, cache_files[path]))
        else:
            results[path] = (meta, None, None)
    return cache_files, results, todo


def _parse_all(todo: list[tuple[Path, Path | None]], *, keep: bool, workers: int, progress: bool) -> dict[Path, tuple]:
    """Step 2: parse the files not in the cache (in worker processes when there are several).
    Returns path -> _parse_result(...); keep: keep the Motions (no cache to reload them from)."""
    results: dict[Path, tuple] = {}
    bar = tqdm(total=len(todo), desc="reading motion files", unit="file", disable=not progress or not todo)
    if workers > 1 and len(todo) > 2:
        with ProcessPoolExecutor(workers, initializer=_worker_init) as pool:
            futures = {pool.submit(_parse_result, path, cf, keep): path for path, cf in todo}
            for future in as_completed(futures):
                results[futures[future]] = future.result()
                bar.update()
    else:
        for path, cf in todo:
            results[path] = _parse_result(path, cf, keep)
            bar.update()
    bar.close()
    return results


def _clips(files: list[tuple[Path, str, Path]], results: dict[Path, tuple], cache_files: dict[Path, Path | None],
           subject_fn: Callable[[str, PurePath], str]) -> tuple[list[Clip], list[Skipped]]:
    """Step 3: the clips and the skipped files, in path order."""
    clips, skipped = [], []
    for path, source, source_dir in files:
        if base_suffix(path) in UNSUPPORTED:
            skipped.append(Skipped(path, source, UNSUPPORTED[base_suffix(path)]))
            continue
        meta, motion, error = results[path]
        if error is not None:
            log.warning("skipped %s", error)
            skipped.append(Skipped(path, source, error))
            continue
        skeleton = meta["skeleton"]
        clips.append(Clip(path, source, subject_fn(source, path.relative_to(source_dir)), meta["frames"],
                          meta["fps"], skeleton.num_joints, skeleton_signature(skeleton), cache_files[path], motion))
    return clips, skipped

"""Mocap collections: index every motion file under a folder, cache parsed arrays, split by subject.

    collection = MotionCollection.load("../shared/data/mocap")     # first load parses, later loads read the cache
    print(collection.summary())                                    # per source: clips, minutes, subjects, skipped
    splits = collection.split((0.8, 0.1, 0.1), seed=0)             # {'train': [subject ids], 'val': [...], 'test': [...]}
    train = collection.windows(length=40, fps=30.0, split="train", signature=...)  # torch Dataset

A *source* is a top-level folder of the tree (or the root itself when it holds a SOURCE.md).
A *subject* id names the person, the same across sources (see :func:`subject_id`); splits are
made by subject, never by clip, so one person's takes never sit on both sides of an evaluation.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import time
from collections import defaultdict
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field, fields
from pathlib import Path, PurePath
from typing import Callable, Iterable, Iterator, Sequence

import numpy as np
import torch
from tqdm.auto import tqdm

from humotion.io import READABLE, load_motion
from humotion.io.errors import base_suffix
from humotion.motion import Motion
from humotion.skeleton import Skeleton

log = logging.getLogger("humotion.data")

CACHE_VERSION = 1
"""Bump when the cached arrays would differ for the same file (a reader fix, a new field)."""

UNSUPPORTED = {".fbx": "unsupported format"}
"""Motion formats found in the wild that humotion does not read: listed as skipped, not errors."""

WHOLE_SOURCE_SUBJECTS = {"cmu_expmap_li2018": "cmu-expmap-unknown"}
"""Sources whose clips cannot all be tied to a person: the whole source is one subject (one
split group). cmu_expmap_li2018 does not say which CMU trials its 96 clips are."""

TOGETHER = (
    ("cmu-60", "cmu-61"),
    ("cmu-expmap-unknown", "cmu-02", "cmu-07", "cmu-10", "cmu-11", "cmu-16"),
)
"""Subjects kept in the same split by default.

- CMU 60 and 61 are the two partners of the same salsa recordings: distinct people, but their
  motion is coupled frame for frame, so not independent data.
- cmu_expmap_li2018 holds copies of takes found elsewhere in ../shared/data/mocap. Matching
  per-joint rotation-angle curves (hips, knees, shoulders, elbows; 30 Hz, 1 s windows, mean
  difference 0.004-0.015 rad against >= 0.03 rad for any other pair) identified 14 of its 96
  clips: test/soccer/soccer_1 = 11_01; train/soccer/soccer_4, soccer_5 = 10_05, 10_06;
  train/walking_extra/walking_18 = 10_04; walking_27..33 = 16_15, 16_16, 16_21, 16_22, 16_31,
  16_32, 16_47; train/running/running_2 = 16_36; train/walking/walking_1 = 02_01;
  train/walking/walking_4 = 07_01 (also confirming its rows are 120 Hz). The source therefore
  shares a split with subjects 02, 07, 10, 11 and 16. Its other 82 clips matched nothing held
  here but may still be takes of CMU subjects that other copies of the database hold: exclude
  the source when that matters for a reported number.
"""

EVALUATION_ONLY = ("hdm05_jointlearning",)
"""Sources that may evaluate but not train shipped weights (HDM05: CC BY-SA 3.0, share-alike):
MotionCollection.split puts their subjects in the test split by default."""

SPLIT_NAMES = ("train", "val", "test")


# -- subjects ------------------------------------------------------------------------------

def subject_id(source: str, relpath: str | PurePath) -> str:
    """The person a clip shows, from its source folder and path inside it.

    'cmu-NN' for CMU takes named <subject>_<trial>... (001_01.bvh, 01_01.amc, 60_01_scaled.bvh,
    07_01-walk.amc -> 'cmu-01', 'cmu-01', 'cmu-60', 'cmu-07') in sources named cmu*; 'hdm05-bd'
    for HDM05 files HDM_bd_...; WHOLE_SOURCE_SUBJECTS for sources without per-clip subjects;
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
            motion = _read_cache(self.cache_file)
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
        _write_cache(cache_file, motion)
    return motion


@dataclass(frozen=True)
class Skipped:
    """A file that is not in the collection and why (unsupported format, or the reader's error)."""

    path: Path
    source: str
    reason: str


# -- cache ---------------------------------------------------------------------------------

def default_cache_dir() -> Path:
    """$HUMOTION_CACHE, else ~/.cache/humotion."""
    return Path(os.environ.get("HUMOTION_CACHE") or Path.home() / ".cache" / "humotion")


def _reader_fingerprint(suffix: str) -> str:
    """Hash of the reader module's source, so a changed reader never serves stale arrays."""
    module = {".bvh": "bvh.py", ".amc": "asf_amc.py", ".txt": "expmap.py"}.get(suffix, "")
    path = Path(__file__).parent.parent / "io" / module
    try:
        return hashlib.sha1(path.read_bytes()).hexdigest()[:12] if module else ""
    except OSError:
        return ""


def _stat_key(path: Path) -> str:
    st = path.stat()
    return f"{path.resolve()}|{st.st_size}|{st.st_mtime_ns}"


def cache_key(path: Path, companions: Sequence[Path] = ()) -> str:
    """Hash of (absolute path, size, mtime_ns, CACHE_VERSION, reader source) of the file and of its
    companion skeleton files (ASF, skeleton.json), so editing any of them rebuilds the entry."""
    parts = [str(CACHE_VERSION), _reader_fingerprint(base_suffix(path)), _stat_key(path)]
    parts += [_stat_key(c) for c in companions]
    return hashlib.sha1("\n".join(parts).encode()).hexdigest()


def _write_cache(file: Path, motion: Motion) -> None:
    """Save a Motion as .npz: a JSON 'meta' entry (version, fps, frames, name, skeleton) and the
    arrays (float32). Written to a temporary name and renamed, so no reader sees half a file."""
    s = motion.skeleton
    meta = dict(version=CACHE_VERSION, fps=motion.fps, frames=motion.num_frames, name=motion.name,
                skeleton=dict(names=s.names, parents=s.parents, offsets=s.offsets.tolist(),
                              end_site_parents=s.end_site_parents, end_site_offsets=s.end_site_offsets.tolist(),
                              end_site_names=s.end_site_names))
    arrays = dict(meta=np.str_(json.dumps(meta)), rotations=motion.rotations.numpy(),
                  root_positions=motion.root_positions.numpy())
    if motion.joint_offsets is not None:
        arrays["joint_offsets"] = motion.joint_offsets.numpy()
    try:
        file.parent.mkdir(parents=True, exist_ok=True)
        tmp = file.with_name(f"{file.stem}.{os.getpid()}.tmp.npz")
        np.savez(tmp, **arrays)
        os.replace(tmp, file)
    except OSError as error:
        log.warning("cannot write cache entry %s (%s); continuing without it", file, error)


def _read_meta(data) -> dict:
    meta = json.loads(str(data["meta"]))
    if meta["version"] != CACHE_VERSION:
        raise ValueError(f"cache version {meta['version']}, expected {CACHE_VERSION}")
    meta["skeleton"] = Skeleton(**meta["skeleton"])
    return meta


def _read_cache_meta(file: Path) -> dict | None:
    """{frames, fps, name, skeleton} of a cache entry without reading its arrays; None when the
    entry is missing, damaged or from another CACHE_VERSION (it is then rebuilt)."""
    try:
        with np.load(file, allow_pickle=False) as data:
            return _read_meta(data)
    except FileNotFoundError:
        return None
    except Exception as error:  # any damage (truncated zip, missing key, bad values) -> rebuild
        log.info("ignoring unreadable cache entry %s (%s)", file, error)
        return None


def _read_cache(file: Path) -> Motion | None:
    """The cached Motion, or None when the entry is missing or damaged."""
    try:
        with np.load(file, allow_pickle=False) as data:
            meta = _read_meta(data)
            rotations, root = data["rotations"], data["root_positions"]
            offsets = data["joint_offsets"] if "joint_offsets" in data else None
        frames, joints = meta["frames"], meta["skeleton"].num_joints
        if rotations.shape != (frames, joints, 4) or root.shape != (frames, 3) or rotations.dtype != np.float32:
            raise ValueError(f"arrays {rotations.shape} {root.shape} do not match the entry's metadata")
        return _validated_motion(meta["skeleton"], rotations, root, meta["fps"], offsets, meta["name"])
    except FileNotFoundError:
        return None
    except Exception as error:
        log.info("ignoring unreadable cache entry %s (%s)", file, error)
        return None


def _validated_motion(skeleton, rotations, root_positions, fps, joint_offsets, name) -> Motion:
    """A Motion from arrays that Motion validated before they were cached (zip CRCs catch later
    damage), built without repeating the checks: torch's finiteness scan of every array costs
    more than reading the file."""
    motion = Motion.__new__(Motion)
    values = dict(skeleton=skeleton, rotations=torch.from_numpy(rotations), root_positions=torch.from_numpy(root_positions),
                  fps=float(fps), joint_offsets=None if joint_offsets is None else torch.from_numpy(joint_offsets), name=name)
    for f in fields(Motion):
        setattr(motion, f.name, values[f.name] if f.name in values else f.default)
    return motion


# -- scanning ------------------------------------------------------------------------------

def _is_motion_file(path: Path) -> bool:
    return base_suffix(path) in READABLE and path.name not in {"README.txt", "LICENSE.txt"}


def _scan(root: Path) -> list[tuple[Path, str, Path]]:
    """(file, source, source folder) for every motion file (readable or UNSUPPORTED) under root,
    sorted. The source is the top-level folder, or root itself for files directly in it or when
    root holds a SOURCE.md (one source given on its own)."""
    single = (root / "SOURCE.md").exists()
    found = []
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
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
    return sorted(p for p in source_dir.rglob("*") if p.is_file() and p.suffix.lower() in (".asf", ".json"))


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
        """Index every motion file under root (BVH, AMC with its ASF, exp-map .txt, each maybe .gz).

        cache_dir: where parsed arrays are kept (default: default_cache_dir()); cache=False keeps
            the motions in memory instead. sources / exclude: top-level folder names to keep / drop.
        subject_fn(source, path relative to the source folder) -> subject id (default subject_id).
        workers: processes parsing files not yet cached (default: one per CPU, at most 8; 1 = serial).
        Unsupported (FBX) and unreadable files are listed in .skipped (unreadable ones also
        logged with the reader's message); one bad file never stops the load.
        """
        root = Path(root).expanduser().resolve()
        if not root.is_dir():
            raise FileNotFoundError(f"no such folder: {root}")
        keep, drop = (set(sources) if sources is not None else None), set(exclude)
        files = [f for f in _scan(root) if (keep is None or f[1] in keep) and f[1] not in drop]
        cache_root = (Path(cache_dir) if cache_dir is not None else default_cache_dir()) / "motions"
        companions: dict[str, list[Path]] = {}
        start = time.perf_counter()
        # 1. metadata from the cache where it is valid
        results: dict[Path, tuple] = {}  # path -> (meta, motion or None, error or None)
        todo: list[tuple[Path, Path | None]] = []
        cache_files: dict[Path, Path | None] = {}
        for path, source, source_dir in files:
            if base_suffix(path) in UNSUPPORTED:
                continue
            if source not in companions:
                companions[source] = _companions(source_dir)
            cache_files[path] = cache_root / f"{cache_key(path, companions[source])}.npz" if cache else None
            meta = _read_cache_meta(cache_files[path]) if cache else None
            if meta is None:
                todo.append((path, cache_files[path]))
            else:
                results[path] = (meta, None, None)
        # 2. parse the rest (in worker processes when there are several files)
        workers = min(os.cpu_count() or 1, 8) if workers is None else max(1, workers)
        bar = tqdm(total=len(todo), desc="reading motion files", unit="file", disable=not progress or not todo)
        if workers > 1 and len(todo) > 2:
            with ProcessPoolExecutor(workers, initializer=_worker_init) as pool:
                futures = {pool.submit(_parse_result, path, cf, not cache): path for path, cf in todo}
                for future in as_completed(futures):
                    results[futures[future]] = future.result()
                    bar.update()
        else:
            for path, cf in todo:
                results[path] = _parse_result(path, cf, not cache)
                bar.update()
        bar.close()
        # 3. clips in path order
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


# -- splitting -----------------------------------------------------------------------------

def _stable_rank(seed: int, attempt: int, key: str) -> str:
    return hashlib.sha256(f"{seed}:{attempt}:{key}".encode()).hexdigest()


def split_subjects(minutes: dict[str, float], fractions: Sequence[float] = (0.8, 0.1, 0.1), seed: int = 0, *,
                   names: Sequence[str] = SPLIT_NAMES, pin: dict[str, str] | None = None,
                   together: Iterable[Sequence[str]] = TOGETHER, attempts: int = 4) -> dict[str, list[str]]:
    """Assign every subject to one split, balancing minutes of motion; deterministic in (minutes, seed).

    minutes: subject id -> minutes. fractions: share of the minutes per split (same order as names).
    pin: subject id -> split name, placed there first. together: groups of subject ids kept in one
        split (ids not in `minutes` are ignored).
    Groups (a subject, or a `together` group) are visited in the order of sha256(seed, attempt,
    group) and each is put where it brings the splits' minutes closest to their targets (least
    sum of squared relative deviations); of `attempts` such orders the best-balanced one wins.
    Returns split name -> sorted subject ids; every subject in exactly one split.
    """
    if len(fractions) != len(names):
        raise ValueError(f"{len(fractions)} fractions for {len(names)} split names {tuple(names)}")
    if any(f < 0 for f in fractions) or sum(fractions) <= 0:
        raise ValueError(f"fractions must be non-negative with a positive sum, got {tuple(fractions)}")
    pin = dict(pin or {})
    for subject, name in pin.items():
        if name not in names:
            raise ValueError(f"subject {subject!r} pinned to unknown split {name!r}; splits: {', '.join(names)}")
    # Union the `together` groups (transitively) over the subjects present.
    group_of = {s: s for s in minutes}
    for group in together:
        present = sorted(s for s in group if s in minutes)
        for s in present[1:]:
            old, new = group_of[s], group_of[present[0]]
            group_of = {k: (new if v == old else v) for k, v in group_of.items()}
    groups: dict[str, list[str]] = defaultdict(list)
    for s, g in group_of.items():
        groups[g].append(s)

    total = sum(minutes.values())
    targets = [total * f / sum(fractions) for f in fractions]
    open_splits = [i for i, t in enumerate(targets) if t > 0]

    def cost(filled: list[float]) -> float:
        return sum(((filled[i] - targets[i]) / targets[i]) ** 2 for i in open_splits)

    pinned_groups, free = [], []
    for key in sorted(groups):
        members = sorted(groups[key])
        pinned = {pin[s] for s in members if s in pin}
        if len(pinned) > 1:
            raise ValueError(f"subjects {members} must share a split but are pinned to {sorted(pinned)}")
        if pinned:
            pinned_groups.append((members, list(names).index(pinned.pop())))
        else:
            free.append(members)

    best = None
    for attempt in range(max(1, attempts)):
        assignment = list(pinned_groups)
        filled = [0.0] * len(names)
        for members, index in assignment:
            filled[index] += sum(minutes[s] for s in members)
        for members in sorted(free, key=lambda m: _stable_rank(seed, attempt, ",".join(m))):
            amount = sum(minutes[s] for s in members)

            def after(i: int) -> list[float]:
                return [f + amount if j == i else f for j, f in enumerate(filled)]

            index = min(open_splits, key=lambda i: (cost(after(i)), i))
            assignment.append((members, index))
            filled = after(index)
        if best is None or cost(filled) < best[0]:
            best = (cost(filled), assignment)
    result: dict[str, list[str]] = {n: [] for n in names}
    for members, index in best[1]:
        result[names[index]] += members
    return {n: sorted(v) for n, v in result.items()}

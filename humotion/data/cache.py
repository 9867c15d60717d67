"""The parsed-motion cache of MotionCollection: one .npz file per motion file, named by cache_key.

    key = cache_key(path, companions)            # changes when the file, its ASF, the reader or CACHE_VERSION does
    write_cache(cache_dir / f"{key}.npz", motion)
    motion = read_cache(cache_dir / f"{key}.npz")    # None when missing or damaged: parse the file again

An entry holds a JSON 'meta' string (version, fps, frames, name, skeleton) and the float32 arrays;
read_cache_meta reads the metadata alone, which is what indexing a collection needs.

    write_motions(file, motions)                 # several Motions in one .npz (training's windows cache)
    motions = read_motions(file)                 # None when missing or damaged

Entries are data only (JSON and numeric arrays, read with allow_pickle=False): a file planted in
the cache folder can give wrong numbers, never run code.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from dataclasses import fields
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from humotion.atomic import atomic_file
from humotion.io.errors import base_suffix
from humotion.motion import Motion
from humotion.skeleton import Skeleton

log = logging.getLogger("humotion.data")

CACHE_VERSION = 1
"""Bump when the cached arrays would differ for the same file (a reader fix, a new field)."""

READER_MODULES = {".bvh": ("bvh.py",), ".amc": ("asf_amc.py", "asf.py", "amc.py"), ".txt": ("expmap.py",),
                  ".npz": ("amass.py",)}
"""Motion suffix -> the humotion/io modules whose source makes up its reader (see cache_key)."""


def default_cache_dir() -> Path:
    """$HUMOTION_CACHE, else ~/.cache/humotion."""
    return Path(os.environ.get("HUMOTION_CACHE") or Path.home() / ".cache" / "humotion")


def _reader_fingerprint(suffix: str) -> str:
    """Hash of the reader modules' source, so a changed reader never serves stale arrays.

    The modules' bytes are hashed one after the other ('' for an unknown suffix or an unreadable
    module), so a reader in a single module hashes as that module's file alone.
    """
    modules = READER_MODULES.get(suffix, ())
    folder = Path(__file__).parent.parent / "io"
    digest = hashlib.sha1()
    try:
        for module in modules:
            digest.update((folder / module).read_bytes())
    except OSError:
        return ""
    return digest.hexdigest()[:12] if modules else ""


def _stat_key(path: Path) -> str:
    st = path.stat()
    return f"{path.resolve()}|{st.st_size}|{st.st_mtime_ns}"


def cache_key(path: Path, companions: Sequence[Path] = ()) -> str:
    """Hash of (absolute path, size, mtime_ns, CACHE_VERSION, reader source) of the file and of its
    companion skeleton files (ASF, skeleton.json), so editing any of them rebuilds the entry."""
    parts = [str(CACHE_VERSION), _reader_fingerprint(base_suffix(path)), _stat_key(path)]
    parts += [_stat_key(c) for c in companions]
    return hashlib.sha1("\n".join(parts).encode()).hexdigest()


def _skeleton_fields(s: Skeleton) -> dict:
    """A Skeleton as JSON-ready keyword arguments of Skeleton(...)."""
    return dict(names=s.names, parents=s.parents, offsets=s.offsets.tolist(), end_site_parents=s.end_site_parents,
                end_site_offsets=s.end_site_offsets.tolist(), end_site_names=s.end_site_names)


def write_cache(file: Path, motion: Motion) -> None:
    """Save a Motion as .npz: a JSON 'meta' entry (version, fps, frames, name, skeleton) and the
    arrays (float32)."""
    meta = dict(version=CACHE_VERSION, fps=motion.fps, frames=motion.num_frames, name=motion.name,
                skeleton=_skeleton_fields(motion.skeleton))
    arrays = dict(meta=np.str_(json.dumps(meta)), rotations=motion.rotations.numpy(),
                  root_positions=motion.root_positions.numpy())
    if motion.joint_offsets is not None:
        arrays["joint_offsets"] = motion.joint_offsets.numpy()
    _save(file, arrays)


def write_motions(file: Path, motions: Sequence[Motion]) -> None:
    """Save Motions in one .npz: a JSON 'meta' entry (version, the distinct skeletons, and per
    motion its frames, fps, name, skeleton index and whether it has joint_offsets) and each
    array of all motions flattened and concatenated (float32): rotations (sum T*J, 4),
    root_positions (sum T, 3), joint_offsets (sum T*J over the motions that have them, 3)."""
    skeletons: dict[str, int] = {}
    entries = [dict(frames=m.num_frames, fps=m.fps, name=m.name, joint_offsets=m.joint_offsets is not None,
                    skeleton=skeletons.setdefault(json.dumps(_skeleton_fields(m.skeleton)), len(skeletons)))
               for m in motions]
    meta = dict(version=CACHE_VERSION, skeletons=[json.loads(k) for k in skeletons], motions=entries)

    def joined(arrays: list, width: int) -> np.ndarray:
        return np.concatenate([a.reshape(-1, width) for a in arrays]) if arrays else np.zeros((0, width), np.float32)

    _save(file, dict(meta=np.str_(json.dumps(meta)), rotations=joined([m.rotations.numpy() for m in motions], 4),
                     root_positions=joined([m.root_positions.numpy() for m in motions], 3),
                     joint_offsets=joined([m.joint_offsets.numpy() for m in motions if m.joint_offsets is not None], 3)))


def _save(file: Path, arrays: dict) -> None:
    """Write arrays as .npz atomically (:func:`humotion.atomic.atomic_file`), so no reader sees half
    a file; when the entry cannot be written (e.g. a folder stands at its name) a warning is logged
    and nothing is left behind."""
    try:
        file.parent.mkdir(parents=True, exist_ok=True)
        with atomic_file(file) as out:
            np.savez(out, **arrays)
    except OSError as error:
        log.warning("cannot write cache entry %s (%s); continuing without it", file, error)


def _read_meta(data) -> dict:
    meta = json.loads(str(data["meta"]))
    if meta["version"] != CACHE_VERSION:
        raise ValueError(f"cache version {meta['version']}, expected {CACHE_VERSION}")
    meta["skeleton"] = Skeleton(**meta["skeleton"])
    return meta


def read_cache_meta(file: Path) -> dict | None:
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


def read_cache(file: Path) -> Motion | None:
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


def read_motions(file: Path) -> list[Motion] | None:
    """The Motions of a write_motions file, or None when it is missing, damaged or from another
    CACHE_VERSION."""
    try:
        with np.load(file, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            arrays = {k: data[k] for k in ("rotations", "root_positions", "joint_offsets")}
        if meta["version"] != CACHE_VERSION:
            raise ValueError(f"cache version {meta['version']}, expected {CACHE_VERSION}")
        skeletons = [Skeleton(**s) for s in meta["skeletons"]]
        entries = meta["motions"]
        rows = [e["frames"] * skeletons[e["skeleton"]].num_joints for e in entries]
        layout = {"rotations": (rows, 4), "root_positions": ([e["frames"] for e in entries], 3),
                  "joint_offsets": ([n for n, e in zip(rows, entries) if e["joint_offsets"]], 3)}
        parts = {}
        for key, (counts, width) in layout.items():
            if arrays[key].shape != (sum(counts), width) or arrays[key].dtype != np.float32:
                raise ValueError(f"{key} is {arrays[key].dtype} {arrays[key].shape}, the metadata says float32 "
                                 f"{(sum(counts), width)}")
            parts[key] = iter(np.split(arrays[key], np.cumsum(counts)[:-1]))
        motions = []
        for e in entries:
            skeleton = skeletons[e["skeleton"]]
            shape = (e["frames"], skeleton.num_joints)
            offsets = next(parts["joint_offsets"]).reshape(*shape, 3) if e["joint_offsets"] else None
            motions.append(_validated_motion(skeleton, next(parts["rotations"]).reshape(*shape, 4),
                                             next(parts["root_positions"]), e["fps"], offsets, e["name"]))
        return motions
    except FileNotFoundError:
        return None
    except Exception as error:  # any damage (truncated zip, missing key, bad values) -> rebuild
        log.info("ignoring unreadable cache file %s (%s)", file, error)
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

"""The parsed-motion cache of MotionCollection: one .npz file per motion file, named by cache_key.

    key = cache_key(path, companions)            # changes when the file, its ASF, the reader or CACHE_VERSION does
    write_cache(cache_dir / f"{key}.npz", motion)
    motion = read_cache(cache_dir / f"{key}.npz")    # None when missing or damaged: parse the file again

An entry holds a JSON 'meta' string (version, fps, frames, name, skeleton) and the float32 arrays;
read_cache_meta reads the metadata alone, which is what indexing a collection needs.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
from dataclasses import fields
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from humotion.io.errors import base_suffix
from humotion.motion import Motion
from humotion.skeleton import Skeleton

log = logging.getLogger("humotion.data")

CACHE_VERSION = 1
"""Bump when the cached arrays would differ for the same file (a reader fix, a new field)."""

READER_MODULES = {".bvh": ("bvh.py",), ".amc": ("asf_amc.py", "asf.py", "amc.py"), ".txt": ("expmap.py",)}
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


def write_cache(file: Path, motion: Motion) -> None:
    """Save a Motion as .npz: a JSON 'meta' entry (version, fps, frames, name, skeleton) and the
    arrays (float32). Written to a temporary name and renamed, so no reader sees half a file; when
    the entry cannot be written (e.g. a folder stands at its name) the temporary file is removed."""
    s = motion.skeleton
    meta = dict(version=CACHE_VERSION, fps=motion.fps, frames=motion.num_frames, name=motion.name,
                skeleton=dict(names=s.names, parents=s.parents, offsets=s.offsets.tolist(),
                              end_site_parents=s.end_site_parents, end_site_offsets=s.end_site_offsets.tolist(),
                              end_site_names=s.end_site_names))
    arrays = dict(meta=np.str_(json.dumps(meta)), rotations=motion.rotations.numpy(),
                  root_positions=motion.root_positions.numpy())
    if motion.joint_offsets is not None:
        arrays["joint_offsets"] = motion.joint_offsets.numpy()
    tmp = file.with_name(f"{file.stem}.{os.getpid()}.tmp.npz")
    try:
        file.parent.mkdir(parents=True, exist_ok=True)
        np.savez(tmp, **arrays)
        os.replace(tmp, file)
    except OSError as error:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
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

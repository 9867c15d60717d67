"""Output paths checked before any work is done, so that a run fails at once, not after it.

The rule: an output FILE goes into a folder that exists (it is not made: a mistyped folder is
reported, not created); an output FOLDER is made, with its parents, when missing. Either way the
place must be writable. The checks raise OutputPathError naming the path as given. The writers
write through write_atomic, so an output file holds its old bytes or all the new ones.

    check_output_file("out/walk.bvh")          # out/ exists, is a folder, can be written
    check_output_folder("runs/capture_3")      # exists and writable, or can be made
    same_file("a.bvh", "./x/../a.bvh")         # True: one file, however spelled or linked
    write_atomic("out/walk.bvh.gz", chunks)    # bytes or chunks of bytes; gzipped for .gz
"""

from __future__ import annotations

import gzip
import os
from collections.abc import Iterable
from pathlib import Path

from humotion.atomic import atomic_file
from humotion.io.errors import OutputPathError


def check_output_file(path: str | Path) -> Path:
    """path as a Path when a file can be written there: not a folder, its folder exists, is a
    folder and is writable. OutputPathError naming path otherwise."""
    path = Path(path)
    if path.is_dir():
        raise OutputPathError(path, "is a folder; give a file name")
    folder = path.parent
    if not folder.is_dir():
        problem = f"{folder} is not a folder" if folder.exists() else f"the folder {folder} does not exist (create it first)"
        raise OutputPathError(path, f"cannot write here: {problem}")
    _check_writable(path, folder)
    return path


def check_output_folder(path: str | Path) -> Path:
    """path as a Path when it is a writable folder, or can be made as one (its nearest existing
    ancestor is a writable folder). OutputPathError naming path otherwise. Makes nothing."""
    path = Path(path)
    if path.exists():
        if not path.is_dir():
            raise OutputPathError(path, "is a file, not a folder")
        _check_writable(path, path)
        return path
    ancestor = next(p for p in path.absolute().parents if p.exists())
    if not ancestor.is_dir():
        raise OutputPathError(path, f"cannot make the folder: {ancestor} is a file")
    _check_writable(path, ancestor)
    return path


def _check_writable(path: Path, folder: Path) -> None:
    # os.access: the permission bits, ACLs and a read-only file system (EROFS, also for root).
    if not os.access(folder, os.W_OK | os.X_OK):
        where = "the folder" if folder == path else "the current folder" if folder == Path(".") else f"its folder {folder}"
        raise OutputPathError(path, f"cannot write here: {where} is read-only for this user")


def same_file(a: str | Path, b: str | Path) -> bool:
    """True when a and b are one existing file, however spelled: ../, a symbolic or a hard link."""
    try:
        return os.path.samefile(a, b)
    except OSError:  # either is missing: nothing to overwrite
        return False


def write_atomic(path: str | Path, data: bytes | Iterable[bytes]) -> None:
    """data (bytes, or chunks of bytes written as they come; gzip-compressed for a .gz name) into
    path through :func:`humotion.atomic.atomic_file`: path holds its old bytes or all the new
    ones, never a part. OutputPathError naming path, not the temporary file, when it cannot be
    written."""
    path = Path(path)
    chunks = [data] if isinstance(data, bytes) else data
    try:
        with atomic_file(path) as file:
            if path.name.lower().endswith(".gz"):
                with gzip.GzipFile(filename="", mode="wb", fileobj=file, compresslevel=6, mtime=0) as packed:
                    packed.writelines(chunks)
            else:
                file.writelines(chunks)
    except OSError as error:
        raise OutputPathError(path, f"cannot write the file ({error.strerror or error})") from None

"""The one error type every motion-file reader raises, the one for outputs that cannot be written,
and transparent gzip reading."""

from __future__ import annotations

import gzip
from pathlib import Path


class MotionFileError(ValueError):
    """A motion file could not be read: names the file, the line (when known) and the problem."""

    def __init__(self, path: str | Path, problem: str, line: int | None = None):
        self.path, self.problem, self.line = str(path), problem, line
        where = f"{self.path}, line {line}" if line is not None else self.path
        super().__init__(f"{where}: {problem}")


class OutputPathError(OSError):
    """An output file or folder cannot be written: names the path the user gave (never a temporary
    file's) and the problem. An OSError, so code that handles failed writes handles these too."""

    def __init__(self, path: str | Path, problem: str):
        self.path, self.problem = str(path), problem
        super().__init__(f"{self.path}: {problem}")


def read_bytes(path: str | Path) -> bytes:
    """The bytes of a file, gunzipped when it is gzip-compressed (by content, not by name).

    Raises MotionFileError for a missing, unreadable, empty or truncated-gzip file.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as error:
        raise MotionFileError(path, f"cannot read file ({error.strerror or error})") from None
    if raw[:2] == b"\x1f\x8b":
        try:
            raw = gzip.decompress(raw)
        except (OSError, EOFError, gzip.BadGzipFile) as error:
            raise MotionFileError(path, f"corrupt or truncated gzip data ({error})") from None
    if not raw.strip():
        raise MotionFileError(path, "file is empty")
    return raw


def read_text(path: str | Path) -> str:
    """The text of a file (UTF-8, else Latin-1), gunzipped when it is gzip-compressed.

    Raises MotionFileError for a missing, empty, truncated-gzip or binary file.
    """
    raw = read_bytes(path)
    if b"\x00" in raw:
        raise MotionFileError(path, "file is binary, not a text motion file")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        return raw.decode("latin-1")


def base_suffix(path: str | Path) -> str:
    """The format suffix of a path, lower case, ignoring a trailing .gz: 'x.amc.gz' -> '.amc'."""
    name = Path(path).name.lower()
    if name.endswith(".gz"):
        name = name[:-3]
    return Path(name).suffix


def file_stem(path: str | Path, suffix: str) -> str:
    """The file's name without a trailing .gz, then without suffix (either in any case):
    file_stem('runs/Walk.BVH.gz', '.bvh') -> 'Walk'. A Motion read from a file is named this."""
    name = Path(path).name
    if name.lower().endswith(".gz"):
        name = name[:-3]
    if name.lower().endswith(suffix):
        name = name[: -len(suffix)]
    return name

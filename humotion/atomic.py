"""Files written whole or not at all: the one temporary-file-then-rename writer every writer uses.

    with atomic_file("runs/sparse/checkpoint-200.pt") as file:
        torch.save(state, file)                      # or np.savez(file, ...), file.write(bytes)

:func:`humotion.io.paths.write_atomic` builds on it for bytes (gzipped for a .gz name) and names
the user's path in its errors.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO


@contextlib.contextmanager
def atomic_file(path: str | Path) -> Iterator[BinaryIO]:
    """A binary file open for writing path's new contents: a temporary file beside path
    (.NAME.XXXXXXXX.tmp), renamed onto path when the block ends without an error, with path's
    permission bits (0o644 for a new file). So path holds its old bytes or all the new ones, never
    a part. On an error or Ctrl-C the temporary file is removed, path is left as it was and the
    error goes on."""
    path = Path(path)
    mode = path.stat().st_mode & 0o777 if path.exists() else 0o644
    handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(handle)
    try:
        with open(temporary, "wb") as file:    # by name: writers such as onnx.save read file.name
            yield file
        os.chmod(temporary, mode)
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise

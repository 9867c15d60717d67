"""Where the tests find the real data: $HUMOTION_DATA, else ../shared/data beside the repository.

Point HUMOTION_DATA at another spelling of that folder (a symlink, a mounted drive) to run the data
tests through it. The library resolves a collection's root (symlinks followed), so the tests
compare paths resolved on both sides.
"""

import os
from pathlib import Path

DATA = Path(os.environ.get("HUMOTION_DATA") or Path(__file__).resolve().parents[1].parent / "shared" / "data")
MOCAP = DATA / "mocap"

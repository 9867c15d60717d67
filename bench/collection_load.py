"""Time to index and load every motion of a mocap folder tree: first load (parsing every file,
filling a fresh cache) and second load (from that cache), with the collection's summary.

    .venv/bin/python bench/collection_load.py [ROOT]      # default ../shared/data/mocap
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

from humotion.data import MotionCollection

ROOT = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "mocap"


def load_everything(root: Path, cache_dir: str) -> tuple[MotionCollection, float]:
    """Index the tree and load every clip's arrays; (collection, seconds)."""
    start = time.perf_counter()
    collection = MotionCollection.load(root, cache_dir=cache_dir, progress=False)
    frames = sum(clip.load().num_frames for clip in collection.clips)
    seconds = time.perf_counter() - start
    assert frames == sum(c.frames for c in collection.clips)
    return collection, seconds


def main(argv=None) -> int:
    root = Path(argv[0] if argv else ROOT)
    with tempfile.TemporaryDirectory() as cache:
        collection, first = load_everything(root, cache)
        _, second = load_everything(root, cache)
    print(collection.summary())
    print(f"first load (parse every file, fill the cache): {first:6.1f} s")
    print(f"second load (from the cache):                  {second:6.1f} s   ({first / second:.0f}x faster)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

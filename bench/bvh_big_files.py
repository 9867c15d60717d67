"""Peak memory and speed of reading a big BVH file: `humotion info`'s outline (read_bvh_outline)
and a full read (read_bvh), each in a fresh process, on a file generated in a temporary folder.

    .venv/bin/python bench/bvh_big_files.py [--mb 100] [--zeros] [--gzip] [--source FILE]

The file is FILE's (default CMU 01_01) hierarchy with its motion rows repeated up to --mb
megabytes; --zeros writes rows of "0" instead (2 bytes a value: the most values per megabyte),
--gzip compresses it (.bvh.gz). Each line printed: the job, its peak resident memory (and
that over the bare imports, and as a multiple of the file's size), its wall and CPU seconds,
and megabytes of file (uncompressed) per second of each. The goal for 100 MB: under 768 MB
peak and at least 20 MB/s.
"""

from __future__ import annotations

import argparse
import gzip
import json
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

SOURCE = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "mocap" / "cmu_fairmotion" / "01_01.bvh"

# Run in a fresh interpreter: imports, then the job, then its own peak RSS and times (JSON).
JOB = """
import json, os, resource, sys, time
from humotion.io.bvh import read_bvh, read_bvh_outline
job, path = sys.argv[1], sys.argv[2]
before = resource.getrusage(resource.RUSAGE_SELF)
start = time.perf_counter()
if job == "read":
    frames = read_bvh(path).num_frames
elif job == "info":
    frames = read_bvh_outline(path).num_frames
else:
    frames = 0
wall = time.perf_counter() - start
after = resource.getrusage(resource.RUSAGE_SELF)
print(json.dumps({"frames": frames, "wall_s": wall, "peak_mb": after.ru_maxrss / 1024,
                  "cpu_s": after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime}))
"""


def make_file(folder: Path, source: Path, megabytes: float, zeros: bool, compress: bool) -> tuple[Path, int]:
    """A BVH of about `megabytes` (uncompressed) in folder; (its path, its uncompressed bytes)."""
    text = source.read_text()
    head, motion = re.split(r"(?m)^MOTION\s*$", text, maxsplit=1)
    lines = motion.strip().split("\n")  # Frames:, Frame Time:, rows
    rows = [line for line in lines[2:] if line.strip()]
    if zeros:
        rows = [" ".join(["0"] * len(rows[0].split()))]
    block = ("\n".join(rows) + "\n").encode()
    repeats = max(1, round(megabytes * 1e6 / len(block)))
    header = f"{head}MOTION\nFrames: {len(rows) * repeats}\n{lines[1].strip()}\n".encode()
    path = folder / ("big.bvh.gz" if compress else "big.bvh")
    with (gzip.open(path, "wb", compresslevel=1) if compress else open(path, "wb")) as file:
        file.write(header)
        for _ in range(repeats):
            file.write(block)
    return path, len(header) + repeats * len(block)


def run(job: str, path: Path) -> dict:
    result = subprocess.run([sys.executable, "-c", JOB, job, str(path)], capture_output=True, text=True, check=True,
                            env=dict(os.environ, OMP_NUM_THREADS="1"))
    return json.loads(result.stdout.strip().split("\n")[-1])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--mb", type=float, default=100.0, help="Uncompressed size of the file, megabytes.")
    parser.add_argument("--zeros", action="store_true", help="Rows of zeros instead of the source's rows.")
    parser.add_argument("--gzip", action="store_true", help="Write and read a .bvh.gz.")
    parser.add_argument("--source", type=Path, default=SOURCE, help="BVH whose hierarchy and rows are repeated.")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as folder:
        path, size = make_file(Path(folder), args.source, args.mb, args.zeros, args.gzip)
        mb = size / 1e6
        print(f"{path.name}: {mb:.1f} MB{' uncompressed' if args.gzip else ''}, rows of "
              f"{'zeros' if args.zeros else args.source.name}")
        imports = run("imports", path)["peak_mb"]
        print(f"  imports only    peak {imports:6.0f} MB")
        for job in ("info", "read"):
            r = run(job, path)
            print(f"  {job:<4} {r['frames']:>9} frames  peak {r['peak_mb']:6.0f} MB (+{r['peak_mb'] - imports:.0f} over "
                  f"the imports, {r['peak_mb'] / mb:.1f}x the file)  {r['wall_s']:6.2f} s wall = {mb / r['wall_s']:6.1f} MB/s, "
                  f"{r['cpu_s']:6.2f} s CPU = {mb / r['cpu_s']:6.1f} MB/s")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

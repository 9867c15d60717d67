"""A newcomer's first minutes: the install's time and size, and the demo's time to its viewer.

    .venv/bin/python bench/first_run.py [--venv DIR] [--fresh] [--runs 2]

--fresh: make DIR (default: a temporary folder) a new virtual environment and install humotion
into it with scripts/setup.sh's command (pip install -c constraints.txt -e ".[dev,docs]"), timed;
pip's own cache is used as it is (a machine that never downloaded the wheels takes longer).
Without it, DIR (default .venv) is measured as it is.
Prints: the environment's size on disk (du) and its ten largest packages; then, --runs times,
the seconds from starting `humotion demo` (into a temporary folder) to its printing the viewer's
address, the first run being the environment's first (caches cold) when --fresh; and the load
average beside each figure (the machine's other work slows every step).
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def load() -> str:
    return Path("/proc/loadavg").read_text().split()[0] if Path("/proc/loadavg").exists() else "?"


def megabytes(path: Path) -> float:
    return int(subprocess.run(["du", "-sk", str(path)], capture_output=True, text=True, check=True).stdout.split()[0]) / 1024


def install(venv: Path) -> float:
    start = time.monotonic()
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    subprocess.run([str(venv / "bin/python"), "-m", "pip", "install", "--quiet", "--disable-pip-version-check",
                    "-c", "constraints.txt", "-e", ".[dev,docs]"], cwd=ROOT, check=True)
    return time.monotonic() - start


def demo_seconds(venv: Path, port: int) -> float:
    """Seconds from starting `humotion demo` to the viewer's address on its output."""
    with tempfile.TemporaryDirectory() as out:
        start = time.monotonic()
        process = subprocess.Popen([str(venv / "bin/humotion"), "demo", "-o", out, "--port", str(port)],
                                   stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                   env={**os.environ, "BROWSER": "true"})
        try:
            for line in process.stdout:
                if "humotion viewer: open" in line:
                    return time.monotonic() - start
            raise RuntimeError(f"the demo ended (exit code {process.wait()}) without starting its viewer")
        finally:
            process.terminate()
            process.wait(timeout=30)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--venv", type=Path)
    parser.add_argument("--fresh", action="store_true")
    parser.add_argument("--runs", type=int, default=2)
    parser.add_argument("--port", type=int, default=8151)
    args = parser.parse_args()
    temporary = None
    venv = args.venv
    if args.fresh and venv is None:
        temporary = tempfile.mkdtemp(prefix="humotion-venv-")
        venv = Path(temporary) / "venv"
    venv = venv or ROOT / ".venv"
    try:
        print(f"CPU cores {os.cpu_count()}, Python {sys.version.split()[0]}, {sys.platform}")
        if args.fresh:
            before = load()
            seconds = install(venv)
            print(f"install (scripts/setup.sh's pip command, into a new venv): {seconds:.0f} s "
                  f"(load average {before} at the start, {load()} at the end)")
        packages = sorted(((megabytes(p), p.name) for p in next((venv / "lib").glob("python3*")).joinpath(
            "site-packages").iterdir() if p.is_dir()), reverse=True)
        print(f"environment {venv.name}: {megabytes(venv):.0f} MB on disk; largest packages (MB): "
              + ", ".join(f"{name} {mb:.0f}" for mb, name in packages[:10]))
        print(f"humotion/assets (in the checkout; an editable install leaves them there): {megabytes(ROOT / 'humotion/assets'):.0f} MB")
        for run in range(args.runs):
            seconds = demo_seconds(venv, args.port)
            first = " (the environment's first)" if args.fresh and run == 0 else ""
            print(f"demo run {run + 1}{first}: {seconds:.1f} s to the viewer's address (load average {load()})")
    finally:
        if temporary:
            shutil.rmtree(temporary, ignore_errors=True)


if __name__ == "__main__":
    main()

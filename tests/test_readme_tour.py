"""The README's five-minute tour, run as written, so that the README cannot drift from the program.

The tour's bash block is parsed line by line and run in a temporary folder holding links to the
repository's `.venv` and `humotion/` (so its relative paths mean what they mean in a clone). Each
`.venv/bin/humotion ...` line runs in this process through click (one import of torch for all;
the same entry point as the script), then the README's Python snippet. Checked on every line:
each file it names outside `out/` ships (is in the repository); each `out/` path it names
exists afterwards and is not empty, an input among them having been written by a line above;
the command succeeds. Lines marked "(slow" (video capture) or "Ctrl-C" (the viewer, which serves
until stopped) run in the slow test, as subprocesses.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from click.testing import CliRunner
from processes import interruptible

ROOT = Path(__file__).resolve().parents[1]
HUMOTION = ".venv/bin/humotion"


def readme_block(title: str, language: str) -> str:
    """The first fenced block of `language` under the README's section `title`."""
    text = (ROOT / "README.md").read_text()
    section = text.split(f"## {title}\n", 1)[1].split("\n## ", 1)[0]
    return section.split(f"```{language}\n", 1)[1].split("```", 1)[0]


def tour() -> list[tuple[list[str], str]]:
    """The tour's lines as (arguments, comment)."""
    lines = []
    for line in readme_block("Five-minute tour", "bash").splitlines():
        command, _, comment = line.partition("#")
        if command.strip():
            lines.append((shlex.split(command), comment.strip()))
    return lines


def interactive(comment: str) -> bool:
    return "(slow" in comment or "Ctrl-C" in comment


@pytest.fixture
def clone(tmp_path, monkeypatch):
    """A temporary folder that looks like a clone to the tour: .venv and humotion linked."""
    (tmp_path / ".venv").symlink_to(Path(sys.prefix))
    (tmp_path / "humotion").symlink_to(ROOT / "humotion")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("BROWSER", "true")   # no browser tab from any viewer
    return tmp_path


def check_paths_before(args: list[str]) -> None:
    """Every file the line names outside out/ ships; every out/ input was written above."""
    for arg in args:
        if arg.startswith("humotion/"):
            assert Path(arg).is_file(), f"{arg} does not ship"
            assert (ROOT / arg).resolve().is_relative_to(ROOT / "humotion"), arg


def check_outputs_after(args: list[str], line: str) -> None:
    for arg in args:
        if arg.startswith("out/"):
            path = Path(arg)
            assert path.exists(), f"{line!r} did not write {arg}"
            assert path.is_dir() and any(path.iterdir()) or path.stat().st_size > 0, f"{arg} is empty"


def test_tour_parses_into_commands_that_exist():
    from humotion.cli import main

    lines = tour()
    assert lines[0][0] == ["mkdir", "-p", "out"]
    names = set(main.commands)
    for args, _ in lines[1:]:
        assert args[0] == HUMOTION and args[1] in names, args
    assert any(interactive(c) for _, c in lines) and not all(interactive(c) for _, c in lines[1:])


def test_quick_tour_lines_and_python_snippet(clone):
    from humotion.cli import main

    runner = CliRunner()
    for args, comment in tour():
        if interactive(comment):
            continue
        line = " ".join(args)
        if args[0] == "mkdir":
            subprocess.run(args, check=True)
            continue
        check_paths_before(args)
        result = runner.invoke(main, args[1:], catch_exceptions=False)
        assert result.exit_code == 0, f"{line}: {result.output}"
        check_outputs_after(args, line)
        if "--json" in args:
            facts = json.loads(result.stdout)
            assert facts["frames"] == 240 and facts["joints"] == 31, facts
        if args[1] == "track" and "-o" in args:
            assert "tracked 300 headset frames" in result.output   # 10 s at 30 fps
    snippet = readme_block("Five-minute tour", "python")
    printed = subprocess.run([sys.executable, "-c", snippet], capture_output=True, text=True, timeout=300)
    assert printed.returncode == 0, printed.stderr
    expected = re.search(r"print\(motion\)\s+# (.*)", snippet).group(1)
    assert printed.stdout.strip() == expected
    assert Path("out/punch_body.bvh").stat().st_size > 0


@pytest.mark.slow
def test_slow_tour_lines(clone):
    """Video capture, then the viewer: it prints its address and stops cleanly on Ctrl-C."""
    lines = tour()
    Path("out").mkdir()
    for args, comment in lines:   # the inputs of the slow lines, written by the quick ones above
        if args[0] != "mkdir" and not interactive(comment) and args[1] != "capture":
            subprocess.run(args, check=True, capture_output=True, timeout=600)
    for args, comment in lines:
        if not interactive(comment):
            continue
        check_paths_before(args)
        line = " ".join(args)
        if "Ctrl-C" not in comment:
            done = subprocess.run(args, capture_output=True, text=True, timeout=900)
            assert done.returncode == 0, f"{line}: {done.stderr[-2000:]}"
            check_outputs_after(args, line)
            continue
        server = subprocess.Popen([*args, "--port", "0"] if args[1] == "view" else args, stdout=subprocess.PIPE,
                                  stderr=subprocess.STDOUT, text=True, start_new_session=True,
                                  preexec_fn=interruptible)
        try:
            deadline = time.monotonic() + 180
            address = None
            while address is None and time.monotonic() < deadline:
                output = server.stdout.readline()
                if not output:
                    break
                address = re.search(r"http://127\.0\.0\.1:\d+", output)
            assert address, f"{line}: no viewer address printed"
            time.sleep(2)   # serving
        finally:
            os.killpg(server.pid, signal.SIGINT)
            rest = server.communicate(timeout=30)[0]
        assert server.returncode in (0, 130), f"{line}: Ctrl-C gave exit code {server.returncode}: {rest[-2000:]}"
    assert (Path("out/hikers") / "capture.json").is_file()

"""The documentation: the site (mkdocs.yml) builds in strict mode, so a broken link, anchor,
include or docstring reference fails CI, and it holds what it promises (the API reference from
the docstrings, the model cards and the bench output included, not copied); the README's links
resolve."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")


def relative_links(markdown: str) -> list[str]:
    """The link and image targets of a markdown text that are paths in the repository."""
    return [t for t in LINK.findall(markdown) if not re.match(r"[a-z]+:", t) and not t.startswith("#")]


def test_readme_links_resolve():
    readme = (ROOT / "README.md").read_text()
    links = relative_links(readme)
    assert "docs/index.md" in [t.split("#")[0] for t in links]
    missing = [t for t in links if not (ROOT / t.split("#")[0]).exists()]
    assert not missing, f"README links to missing files: {missing}"


def test_relative_links_are_found():
    assert relative_links("[a](docs/x.md#y) ![b](i.png) [c](https://e.org) [d](#top)") == ["docs/x.md#y", "i.png"]


def test_site_builds_strictly(tmp_path):
    pytest.importorskip("mkdocs", reason="the docs extra is not installed (pip install -e .[docs])")
    pytest.importorskip("mkdocstrings_handlers.python", reason="mkdocstrings-python is not installed")
    site = tmp_path / "site"
    run = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)],
                         cwd=ROOT, capture_output=True, text=True, timeout=600,
                         env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    assert run.returncode == 0, run.stderr[-3000:]

    def page(name: str) -> str:
        return (site / name / "index.html").read_text()

    assert 'id="humotion.sparse.tracker.SparseTracker.update"' in page("api/sparse")   # from the docstrings
    card = (ROOT / "humotion/assets/body/MODEL_CARD.md").read_text().splitlines()[0].lstrip("# ")
    assert card.split(":")[0] in page("models/body")
    assert (site / "models/body/images/pose_set_low_now.png").is_file()
    speed = (ROOT / "docs/bench/sparse_speed.txt").read_text().splitlines()[0]
    assert speed.split(",")[0] in page("benchmarks")
    assert "timestamp" in page("formats")   # the recording format, from humotion.sparse.recording's docstring

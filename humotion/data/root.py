"""Where humotion finds the mocap, images, videos and characters it trains and evaluates on."""

from __future__ import annotations

import os
from pathlib import Path


def default_data_dir() -> Path:
    """$HUMOTION_DATA, else ../shared/data beside the repository (the folder holding mocap/,
    images/, video/ and characters/). Read on each call."""
    return Path(os.environ.get("HUMOTION_DATA") or Path(__file__).resolve().parents[2].parent / "shared" / "data")

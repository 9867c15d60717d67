"""Make the demo clip bundled in humotion/assets from the CMU data in ../shared/data.

    .venv/bin/python scripts/make_demo_clip.py

Takes CMU 02_05 (punch, strike), keeps 8 s, resamples to 30 fps, writes gzip-compressed BVH in metres.
"""

from pathlib import Path

from humotion.assets import demo_clip_path
from humotion.io import load_motion
from humotion.io.bvh import write_bvh

SOURCE = Path(__file__).resolve().parents[1].parent / "shared/data/mocap/cmu_mocgui_s02/02_05.amc"

motion = load_motion(SOURCE)
clip = motion[: int(8 * motion.fps)].resample(30.0)
clip.name = "cmu_02_05_punch"
write_bvh(clip, demo_clip_path())
print(f"wrote {demo_clip_path()}: {clip}")

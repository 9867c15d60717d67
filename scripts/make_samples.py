"""Make the sample inputs shipped in humotion/assets/samples from the shared data in ../shared/data.

    .venv/bin/python scripts/make_samples.py

headset_cmu_03_03.csv: what a VR headset with hand tracking would record over the first 10 s of
CMU take 03_03 (subject 03, walk on uneven terrain), computed by forward kinematics: the eyes' and
wrists' poses of the canonical body at 30 fps, the hands visible only inside the headset cameras'
view (humotion.sparse.recording.stream_from_motion, scenario HT, seed 0), OpenXR axes, values to
5 decimals. Not a real headset recording.
hikers_3s.mp4: the first 3 s of the OpenMPF hikers clip (CC BY 2.0, Peter Stevens), cut at a key
frame by stream copy (no re-encode).
debug_robot.vrm: a byte copy of the shared MIT-licensed VRM character (its licence text is kept
beside it by hand: LICENSE-debug_robot-MIT.txt).
"""

import csv
import shutil
from pathlib import Path

import av
import torch

from humotion.assets import ASSETS
from humotion.canonical import to_canonical
from humotion.io import load_motion
from humotion.sparse.recording import stream_from_motion, write_recording

SAMPLES = ASSETS / "samples"
SHARED = Path(__file__).resolve().parents[1].parent / "shared/data"


def headset_csv(path: Path, seconds: float = 10.0) -> None:
    motion = load_motion(SHARED / "mocap/cmu_cyun9601/amc/03/03_03.amc.gz")
    body = to_canonical(motion[: int(seconds * motion.fps)]).resample(30.0)
    write_recording(stream_from_motion(body, "HT", generator=torch.Generator().manual_seed(0)), path)
    rows = list(csv.reader(path.read_text().splitlines()))
    short = [rows[0]] + [[c if c in ("", "0", "1") else f"{float(c):.5f}" for c in row] for row in rows[1:]]
    with path.open("w", newline="") as handle:
        csv.writer(handle).writerows(short)
    print(f"wrote {path}: {len(short) - 1} frames, {path.stat().st_size / 1e3:.0f} kB")


def video_cut(source: Path, path: Path, seconds: float = 3.0) -> None:
    with av.open(str(source)) as reader, av.open(str(path), "w") as writer:
        stream = reader.streams.video[0]
        out = writer.add_stream_from_template(stream)
        frames = 0
        for packet in reader.demux(stream):
            if packet.pts is None or packet.pts * stream.time_base >= seconds:
                continue
            packet.stream = out
            writer.mux(packet)
            frames += 1
    print(f"wrote {path}: {frames} frames, {path.stat().st_size / 1e3:.0f} kB")


SAMPLES.mkdir(exist_ok=True)
headset_csv(SAMPLES / "headset_cmu_03_03.csv")
video_cut(SHARED / "video/openmpf_video_02_hikers.mp4", SAMPLES / "hikers_3s.mp4")
shutil.copyfile(SHARED / "characters/debug_robot.vrm", SAMPLES / "debug_robot.vrm")

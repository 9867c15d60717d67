"""Small files that ship with humotion so its demo runs with no data download.

cmu_02_05_punch.bvh.gz: 8 s of CMU subject 02, trial 05 (punch, strike), 30 fps, on the CMU 31-joint
skeleton, metres. "The data used in this project was obtained from mocap.cs.cmu.edu. The
database was created with funding from NSF EIA-0196217." (CMU's terms: free for all uses; the
data itself may not be resold.) Made by scripts/make_demo_clip.py.
capture/warrior_pose_cc0.jpg: a person in a warrior pose, 540x360, scaled down from test_war0.jpg of
IBM/yogait's test images (released under CC0 by IBM's CODAIT team); the demo's video-capture input.
capture/, retarget/ and sparse/: shipped models, each with its MODEL_CARD.md.
samples/: the README tour's inputs, a headset recording computed from CMU mocap and 3 s of
video (samples/SOURCE.md: what each is, its licence and credit; made by scripts/make_samples.py).
"""

from pathlib import Path

ASSETS = Path(__file__).resolve().parent


def demo_clip_path() -> Path:
    """Path of the bundled demo motion (a short CMU clip, BVH)."""
    return ASSETS / "cmu_02_05_punch.bvh.gz"


def demo_photo_path() -> Path:
    """Path of the bundled demo photo: a person in a warrior pose, 540x360 (CC0, from IBM/yogait's
    test images by the CODAIT team)."""
    return ASSETS / "capture" / "warrior_pose_cc0.jpg"

"""The canonical body: template, and mappings from every rig in ../shared/data."""

import math

import numpy as np
import pytest

from humotion import canonical
from humotion.canonical import canonical_skeleton, detect_layout, mapping_error, to_canonical
from humotion import rotations as rot
from humotion.io import load_motion
from humotion.motion import Motion

BODY = ["pelvis", "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle",
        "spine1", "spine2", "spine3", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
        "left_wrist", "right_wrist"]


def test_template_is_a_t_pose_of_the_asked_height():
    skeleton = canonical_skeleton(1.80)
    assert skeleton.num_joints == 22 and len(skeleton.end_site_names) == 5
    assert skeleton.height() == pytest.approx(1.80, abs=1e-6)
    rest = dict(zip(skeleton.names, skeleton.rest_positions()))
    arm = rest["left_wrist"] - rest["left_shoulder"]
    assert arm[0] > 0.4 and abs(arm[1]) < 1e-9  # left arm horizontal, towards +X
    assert rest["left_ankle"][1] < rest["left_knee"][1] < rest["left_hip"][1]
    assert list(skeleton.mirror_indices()[[1, 2]]) == [2, 1]


CASES = [
    ("cmu_fairmotion/01_01.amc", "cmu_asf", {}),
    ("cmu_expmap_li2018/data/test/walking/walking_1.txt.gz", "cmu_asf", {}),
    ("cmu_fairmotion/01_01.bvh", "cmu_bvh", {"units": "cmu"}),
    ("cmu_iclone_ccskeleton/002_01.bvh.gz", "cc_base", {}),
    ("cmu_salsa_beemsoft/60_01_scaled.bvh.gz", "daz", {}),
]


@pytest.mark.parametrize("path, layout, options", CASES, ids=[c[1] + ":" + c[0].split("/")[-1] for c in CASES])
def test_rigs_map_onto_the_canonical_body(mocap, path, layout, options):
    motion = load_motion(mocap / path, **options)[:600]
    assert detect_layout(motion.skeleton) == layout
    body = to_canonical(motion)
    assert body.skeleton.names == canonical.JOINTS and body.num_frames == motion.num_frames
    # Joint positions follow the source's: within 1 cm for the legs, arms and spine; the head and
    # neck move by the rotation of source joints the canonical body does not have (upper neck).
    errors = mapping_error(motion)
    assert max(errors[j] for j in BODY) < 0.01, errors
    assert max(errors.values()) < 0.06, errors
    # The rest pose is a T-pose facing +Z whatever the source's zero pose looks like.
    rest = dict(zip(body.skeleton.names, body.skeleton.rest_positions()))
    for side, sign in (("left", 1), ("right", -1)):
        arm = rest[f"{side}_wrist"] - rest[f"{side}_shoulder"]
        assert sign * arm[0] > 0.9 * np.linalg.norm(arm)
        leg = rest[f"{side}_ankle"] - rest[f"{side}_hip"]
        assert -leg[1] > 0.9 * np.linalg.norm(leg)
    # The salsa release was rescaled to a 1.2 m figure by its author; the others are 1.5-1.8 m.
    assert 1.1 < body.skeleton.height() < 2.0


def test_unknown_rig_is_refused_by_name():
    skeleton = canonical_skeleton()
    from humotion.skeleton import Skeleton

    odd = Skeleton(["a", "b"], [-1, 0], np.zeros((2, 3)))
    with pytest.raises(ValueError, match="match none of the known rigs"):
        detect_layout(odd)
    assert detect_layout(skeleton) == "canonical"


def test_canonical_motion_survives_a_bvh_round_trip(mocap, tmp_path):
    """Written as BVH, the canonical body's end sites come back named after their parents
    ("head_end"); it still maps onto the canonical body, to the same joint and end-site positions."""
    from humotion.io.bvh import read_bvh, write_bvh

    body = to_canonical(load_motion(mocap / CASES[0][0]))[:120]
    write_bvh(body, tmp_path / "body.bvh")
    back = read_bvh(tmp_path / "body.bvh", units="m")
    assert detect_layout(back.skeleton) == "canonical_bvh"
    again = to_canonical(back)
    assert np.allclose(again.world_positions(), body.world_positions(), atol=1e-4)
    assert np.allclose(again.end_site_positions(), body.end_site_positions(), atol=1e-4)


def test_same_take_on_two_rigs_gives_the_same_canonical_rotations(mocap):
    """CMU 01_01 as ASF/AMC and as the cgspeed BVH (other joint names, thorax dropped, frame 0 an
    added T-pose): on the canonical body the joint rotations must agree, not just the positions."""
    from humotion.sparse.metrics import mpjre

    amc = to_canonical(load_motion(mocap / "cmu_fairmotion/01_01.amc")[:600])
    bvh = to_canonical(load_motion(mocap / "cmu_fairmotion/01_01.bvh", units="cmu")[1:601])
    legs_and_arms = [canonical.JOINTS.index(j) for j in BODY if not j.startswith("spine")]
    error = mpjre(amc.rotations_as("matrix")[:, legs_and_arms], bvh.rotations_as("matrix")[:, legs_and_arms])
    assert error < 2.0, error
    # and a rest pose maps to small rotations: no joint flipped by half a turn
    rest = to_canonical(Motion.rest(load_motion(mocap / "cmu_fairmotion/01_01.amc").skeleton))
    angles = rot.convert(rest.rotations[0], "quat", "rotvec").norm(dim=-1)
    assert float(angles.max()) < math.radians(30)


def test_game_rig_agrees_with_cmu_on_the_same_take(mocap):
    """CMU 02_01 on the original skeleton and retargeted onto the 100-joint game rig, whose zero
    pose points the legs up: limb rotations on the canonical body agree."""
    from humotion.sparse.metrics import mpjre

    cmu = to_canonical(load_motion(mocap / "cmu_mocgui_s02/02_01.amc")).resample(30)
    game = to_canonical(load_motion(mocap / "cmu_iclone_ccskeleton/002_01.bvh.gz")).resample(30)
    frames = min(len(cmu), len(game))
    limbs = [canonical.JOINTS.index(j) for j in ("left_hip", "right_hip", "left_knee", "right_knee",
                                                 "left_elbow", "right_elbow")]
    error = mpjre(cmu.rotations_as("matrix")[:frames, limbs], game.rotations_as("matrix")[:frames, limbs])
    assert error < 5.0, error

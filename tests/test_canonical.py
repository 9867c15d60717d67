"""The canonical body: template, and mappings from every rig in ../shared/data."""

import math

import numpy as np
import pytest
import torch

from humotion import canonical
from humotion.canonical import MAPPINGS, canonical_skeleton, detect_layout, mapping_error, to_canonical
from humotion import rotations as rot
from humotion.io import load_motion
from humotion.motion import Motion
from humotion.retarget import MissingKeyJoints
from humotion.skeleton import Skeleton

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


HDM05 = "hdm05_jointlearning/amc/hopBothLegs1hops/HDM_bk_hopBothLegs1hops_021_120.amc.gz"


@pytest.mark.parametrize("path, options", [(p, o) for p, _, o in CASES] + [(HDM05, {})],
                         ids=[c[0].split("/")[-1] for c in CASES] + ["hdm05"])
def test_real_rigs_convert_exactly_as_with_their_hand_made_tables(mocap, path, options):
    """The key-joint finder gives the tables the conversion used before, end sites included, so
    the real CMU, iClone, salsa and HDM05 files convert bit for bit as they did."""
    motion = load_motion(mocap / path, **options)[:200]
    layout = detect_layout(motion.skeleton)
    assert canonical.key_points(motion.skeleton) == {k: MAPPINGS[layout][k] for k in canonical.JOINTS + canonical.END_SITES}
    found, table = to_canonical(motion), to_canonical(motion, layout=layout)
    assert torch.equal(found.rotations, table.rotations) and torch.equal(found.root_positions, table.root_positions)
    assert torch.equal(found.skeleton.offsets, table.skeleton.offsets)
    assert torch.equal(found.skeleton.end_site_offsets, table.skeleton.end_site_offsets)


# CMU's cgspeed BVH names (01_01.bvh), renamed joint by joint as other tools name the same bones.
# 3ds Max biped names, spaces as underscores as BVH needs them.
_MAX = {"Hips": "Bip01_Pelvis", "LowerBack": "Bip01_Spine", "Spine": "Bip01_Spine1", "Spine1": "Bip01_Spine2",
        "Neck": "Bip01_Neck", "Neck1": "Bip01_Neck1", "Head": "Bip01_Head"}
_MAX_SIDED = {"HipJoint": "HipJoint", "UpLeg": "Thigh", "Leg": "Calf", "Foot": "Foot", "ToeBase": "Toe0",
              "Shoulder": "Clavicle", "Arm": "UpperArm", "ForeArm": "Forearm", "Hand": "Hand",
              "FingerBase": "Finger2", "Fingers": "Finger21", "Thumb": "Finger0"}   # 3ds Max: Finger0 is the thumb
_MIXAMO = {"LowerBack": "Spine", "Spine": "Spine1", "Spine1": "Spine2", "Neck1": "Neck2", "LHipJoint": "LeftHipJoint",
           "RHipJoint": "RightHipJoint", "LeftFingerBase": "LeftHandMiddle1", "LFingers": "LeftHandMiddle2",
           "LThumb": "LeftHandThumb1", "RightFingerBase": "RightHandMiddle1", "RFingers": "RightHandMiddle2",
           "RThumb": "RightHandThumb1"}


def _max_name(name: str) -> str:
    if name in _MAX:
        return _MAX[name]
    side = "L" if name.startswith("L") else "R"
    base = name.removeprefix("Left").removeprefix("Right")
    return f"Bip01_{side}_{_MAX_SIDED[base if base != name else name[1:]]}"


RENAMINGS = {
    "3ds Max biped": _max_name,
    "Mixamo": lambda name: "mixamorig:" + _MIXAMO.get(name, name),
    "anonymous": None,   # j0, j1, ...: only the tree's shape says which joint is which
}


def renamed(motion: Motion, how: str) -> Motion:
    """The motion with its joints (and end sites) renamed, everything else untouched."""
    sk = motion.skeleton
    names = [f"j{j}" for j in range(sk.num_joints)] if RENAMINGS[how] is None else [RENAMINGS[how](n) for n in sk.names]
    skeleton = Skeleton(names, sk.parents, sk.offsets, sk.end_site_parents, sk.end_site_offsets,
                        [f"{names[p]}_end{e}" for e, p in enumerate(sk.end_site_parents)])
    return Motion(skeleton, motion.rotations, motion.root_positions, motion.fps, name=motion.name)


@pytest.mark.parametrize("how", list(RENAMINGS))
def test_renamed_cmu_bvh_maps_as_the_original(mocap, how, tmp_path):
    """CMU 01_01 (cgspeed BVH) with 3ds-Max-biped, Mixamo or no meaningful joint names, written to
    BVH and read back: no hand-made table knows these rigs, yet the canonical body is the one
    from the original names (the key-joint finder; before, 'match none of the known rigs')."""
    from humotion.io.bvh import read_bvh, write_bvh

    original = load_motion(mocap / "cmu_fairmotion/01_01.bvh", units="cmu")[1:241]
    write_bvh(renamed(original, how).resample(60.0), tmp_path / "take.bvh")
    other = read_bvh(tmp_path / "take.bvh", units="m")
    with pytest.raises(ValueError, match="match none of the known rigs"):
        detect_layout(other.skeleton)
    expected, got = to_canonical(original.resample(60.0)), to_canonical(other)
    assert got.skeleton.names == canonical.JOINTS
    assert torch.allclose(got.skeleton.offsets, expected.skeleton.offsets, atol=1e-5)
    assert torch.allclose(got.skeleton.end_site_offsets, expected.skeleton.end_site_offsets, atol=1e-5)
    assert torch.allclose(got.world_positions(), expected.world_positions(), atol=1e-4)
    assert torch.allclose(got.end_site_positions(), expected.end_site_positions(), atol=1e-4)


def test_a_rig_the_finder_misreads_takes_the_retargeters_override_file(mocap, tmp_path):
    """Overrides as for `humotion retarget --overrides`: the anonymous rig's head put on its
    upper neck is obeyed, and a joint that cannot be found is named with the override hint."""
    from humotion.retarget import load_overrides

    motion = renamed(load_motion(mocap / "cmu_fairmotion/01_01.bvh", units="cmu")[1:31], "anonymous")
    upper_neck = f"j{load_motion(mocap / 'cmu_fairmotion/01_01.bvh', units='cmu').skeleton.index('Neck1')}"
    path = tmp_path / "rig.json"
    path.write_text('{"joints": {"head": "%s"}}' % upper_neck)
    body = to_canonical(motion, overrides=load_overrides(path))
    neck_head = body.world_positions()[:, canonical.JOINTS.index("head")]
    assert torch.allclose(neck_head, motion.world_positions()[:, motion.skeleton.index(upper_neck)], atol=1e-5)
    stub = Skeleton(["a", "b", "c"], [-1, 0, 1], [[0, 1, 0], [0, 0.5, 0], [0, 0.5, 0]])
    with pytest.raises(MissingKeyJoints, match="override file"):
        to_canonical(Motion.rest(stub))

"""Retargeting on the 38-joint exp-map skeleton of Li et al.'s CMU set (cmu_expmap_li2018): key
joints, body parts, correspondence and rest poses, and a known answer: the file
train/walking_extra/walking_27 holds CMU take 16_15, which is also held as ASF/AMC (how the
pairs were found: bench/retarget_eval.py)."""

from functools import partial

import pytest

from humotion.canonical import JOINTS
from humotion.io import load_motion
from humotion.io.asf_amc import read_asf
from humotion.retarget import Rig, copy_rotations, retarget
from humotion.retarget.rig import correspondence, rest_difference
from humotion.skeleton import Skeleton

SIDES = ("left", "right")
# Key point -> exp-map joint: each joint sits at the start of the ASF bone it is named after.
SIDED_KEYS = {"hip": "femur", "knee": "tibia", "ankle": "foot", "foot": "toes", "toe": "toes_end",
              "collar": "clavicle", "shoulder": "humerus", "elbow": "radius", "wrist": "wrist", "hand": "fingers"}
KEY_JOINTS = {"pelvis": "root", "spine1": "lowerback", "spine2": "upperback", "spine3": "thorax",
              "neck": "lowerneck", "head": "head", "head_top": "head_end",
              **{f"{side}_{key}": side[0] + bone for side in SIDES for key, bone in SIDED_KEYS.items()}}
SIDED_PARTS = {"leg": ("hipjoint", "femur", "tibia", "foot", "toes", "toes_end"),
               "arm": ("clavicle", "humerus", "radius", "wrist", "hand", "fingers", "fingers_end", "thumb", "thumb_end")}
PART_JOINTS = {"torso": {"root", "lowerback", "upperback", "thorax"},
               "head": {"lowerneck", "upperneck", "head", "head_end"},
               **{f"{side}_{limb}": {side[0] + bone for bone in bones} for side in SIDES for limb, bones in SIDED_PARTS.items()}}


@pytest.fixture(scope="module")
def expmap(mocap):
    """CMU 16_15 (a 3.9 s walk) from the exp-map set, on subject 02's bones, 120 Hz."""
    return load_motion(mocap / "cmu_expmap_li2018/data/train/walking_extra/walking_27.txt.gz")


@pytest.fixture(scope="module")
def amc(mocap):
    """The same take on subject 16's own 31-joint ASF skeleton."""
    return load_motion(mocap / "cmu_sxaxmz/amc/16/16_15__walk.amc.gz")


def test_key_joints_and_body_parts(expmap):
    rig = Rig.of(expmap.skeleton)
    assert expmap.skeleton.num_joints == 38
    assert rig.key_joints == KEY_JOINTS
    parts = {}
    for name in expmap.skeleton.names:
        parts.setdefault(rig.part_of(name), set()).add(name)
    assert parts == PART_JOINTS


def test_key_joints_from_the_tree_alone(expmap):
    """Without its names (as read_expmap names an unknown tree: joint0, joint1, ...) the tree's
    shape finds the same joints, the hands' end points too (the joint most along the forearm)."""
    sk = expmap.skeleton
    anonymous = Skeleton([f"joint{j}" for j in range(sk.num_joints)], sk.parents, sk.offsets)
    names = dict(zip(anonymous.names, sk.names))
    found = {key: names.get(joint) for key, joint in Rig.of(anonymous).key_joints.items()}
    assert found == KEY_JOINTS


def test_correspondence_and_rest_poses_against_the_asf_skeleton(mocap, expmap, amc):
    rig, asf = Rig.of(expmap.skeleton), Rig.of(amc.skeleton)
    # Every ASF joint pairs with its namesake; the exp-map's "_end" joints are ASF end sites.
    assert correspondence(rig, asf) == {n: n for n in amc.skeleton.names}
    # The exp-map bones are subject 02's: same rest directions as its ASF skeleton, so the rest
    # alignment sees no difference there; against subject 16's the shoulders differ most.
    own = Rig.of(read_asf(mocap / "cmu_mocgui_s02/02.asf").skeleton)
    assert max(rest_difference(rig, own).values()) < 0.01
    other = rest_difference(rig, asf)
    assert max(other, key=other.get) == "left_shoulder" and 5 < other["left_shoulder"] < 12
    # The conversion drops subject 02's thorax bone (2.07 ASF units: neck and collars start where
    # it starts): the same hip height, 0.117 m less standing height.
    assert rig.hip_height() == pytest.approx(own.hip_height(), abs=1e-6)
    assert own.standing_height() - rig.standing_height() == pytest.approx(0.117, abs=0.002)


def test_first_row_is_the_conversions_t_pose(expmap, amc):
    assert expmap.num_frames == amc.num_frames + 1
    world = expmap[:1].world_positions()[0]
    sk = expmap.skeleton

    def direction(a, b):
        d = world[sk.index(b)] - world[sk.index(a)]
        return d / d.norm()

    for side in "lr":
        assert float(direction(f"{side}femur", f"{side}tibia")[1]) < -0.99      # legs straight down
        assert abs(float(direction(f"{side}humerus", f"{side}radius")[0])) > 0.98  # arms sideways


def test_classical_onto_the_asf_skeleton_matches_the_amc(expmap, amc):
    """Known answer: row k + 1 of the exp-map file is AMC frame k; on subject 16's skeleton the
    classical retargeter is within 1.2 cm of the capture on average (measured 0.84 cm; arms
    up to 2.6 cm, from the two subjects' different rest directions at the shoulders) and 4 cm at
    worst. Copying rotations reproduces it: the conversion copied the AMC's rotations."""
    rig = Rig.of(amc.skeleton)
    truth = rig.points(*amc.world(), JOINTS)
    for name, method, mean, worst in (("copy", copy_rotations, 0.001, 0.005),
                                      ("classical", partial(retarget, feet=False, floor=rig.floor_of(amc)), 0.012, 0.04)):
        points = rig.points(*method(expmap[1:], rig).world(), JOINTS)
        relative = ((points - points[:, :1]) - (truth - truth[:, :1])).norm(dim=-1)
        assert float(relative.mean()) < mean and float(relative.max()) < worst, name
        # The root scales with hip height (1.004 m here, 1.001 m on subject 16): the pelvis stays within 1 cm
        # (the result stood on the capture's floor).
        assert float((points[:, 0] - truth[:, 0]).norm(dim=-1).max()) < 0.01

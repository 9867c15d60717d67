"""Understanding a rig for retargeting: key joints, body parts, membership matrix, overrides,
rest-pose alignment, on the real rigs of ../shared/data and on known answers."""

import json

import numpy as np
import pytest

from humotion.canonical import JOINTS, MAPPINGS, canonical_skeleton, detect_layout
from humotion.io import load_motion
from humotion.io.asf_amc import read_asf
from humotion.retarget import PARTS, MissingKeyJoints, Rig, correspondence, find_key_joints, load_overrides, rest_difference
from humotion.skeleton import Skeleton

RIGS = {
    "cmu_asf": ("cmu_fairmotion/01_01.amc", {}),
    "expmap": ("cmu_expmap_li2018/data/test/walking/walking_1.txt.gz", {}),
    "cmu_bvh": ("cmu_fairmotion/01_01.bvh", {"units": "cmu"}),
    "game_100": ("cmu_iclone_ccskeleton/001_01.bvh.gz", {}),
    "game_101": ("cmu_iclone_ccskeleton/002_01.bvh.gz", {}),
    "daz": ("cmu_salsa_beemsoft/60_01_scaled.bvh.gz", {}),
}


def skeleton_of(mocap, rig: str) -> Skeleton:
    path, options = RIGS[rig]
    return load_motion(mocap / path, **options)[:2].skeleton


def renamed(skeleton: Skeleton) -> Skeleton:
    """The same tree with joint names that say nothing."""
    return Skeleton([f"j{i}" for i in range(skeleton.num_joints)], skeleton.parents, skeleton.offsets,
                    skeleton.end_site_parents, skeleton.end_site_offsets)


def without(skeleton: Skeleton, name: str) -> Skeleton:
    """The skeleton with one joint removed, its children hung on its parent (positions kept)."""
    j = skeleton.index(name)
    keep = [i for i in range(skeleton.num_joints) if i != j]
    parent_of = [skeleton.parents[j] if p == j else p for p in skeleton.parents]
    offsets = skeleton.offsets.double().numpy()
    offsets[[c for c in range(skeleton.num_joints) if skeleton.parents[c] == j]] += offsets[j]
    new_index = {old: new for new, old in enumerate(keep)}
    ends = [(new_index[p], o) for p, o in zip(skeleton.end_site_parents, skeleton.end_site_offsets.double().numpy()) if p != j]
    return Skeleton([skeleton.names[i] for i in keep], [-1 if parent_of[i] < 0 else new_index[parent_of[i]] for i in keep],
                    offsets[keep], [p for p, _ in ends], np.array([o for _, o in ends]))


@pytest.mark.parametrize("rig", ["cmu_asf", "expmap", "cmu_bvh", "game_100", "game_101", "daz"])
def test_key_joints_found_by_name_agree_with_the_hand_made_mappings(mocap, rig):
    skeleton = skeleton_of(mocap, rig)
    table = MAPPINGS[detect_layout(skeleton)]
    found = find_key_joints(skeleton)
    assert {k: found[k] for k in JOINTS} == {k: table[k] for k in JOINTS}


@pytest.mark.parametrize("rig", ["cmu_asf", "cmu_bvh", "expmap"])
def test_key_joints_found_from_the_tree_alone(mocap, rig):
    skeleton = skeleton_of(mocap, rig)
    by_name, by_shape = find_key_joints(skeleton), find_key_joints(renamed(skeleton))
    for key in JOINTS:
        assert by_shape[key] == f"j{skeleton.index(by_name[key])}", key


def test_parts_of_named_joints(mocap):
    cmu = Rig.of(skeleton_of(mocap, "cmu_asf"))
    expected = {"lhumerus": "left_arm", "lclavicle": "left_arm", "rthumb": "right_arm", "lhipjoint": "left_leg",
                "rtoes": "right_leg", "root": "torso", "thorax": "torso", "lowerneck": "head", "head": "head"}
    assert {j: cmu.part_of(j) for j in expected} == expected
    game = Rig.of(skeleton_of(mocap, "game_101"))
    expected = {"CC_Base_L_Upperarm": "left_arm", "CC_Base_L_Pinky3": "left_arm", "CC_Base_R_ForearmTwist02": "right_arm",
                "CC_Base_L_ThighTwist01": "left_leg", "CC_Base_R_BigToe1": "right_leg", "CC_Base_Pelvis": "torso",
                "RL_BoneRoot": "torso", "CC_Base_L_Breast": "torso", "CC_Base_JawRoot": "head", "CC_Base_NeckTwist01": "head"}
    assert {j: game.part_of(j) for j in expected} == expected
    body = Rig.of(canonical_skeleton())
    expected = {"left_collar": "left_arm", "right_wrist": "right_arm", "left_hip": "left_leg", "right_foot": "right_leg",
                "pelvis": "torso", "spine3": "torso", "neck": "head"}
    assert {j: body.part_of(j) for j in expected} == expected


def test_membership_matrix_has_one_part_per_joint_and_the_root_column(mocap):
    game = Rig.of(skeleton_of(mocap, "game_100"))
    p = game.membership
    assert p.shape == (6, 101)
    assert (p[:, -1] == 1).all() and (p[:, :-1].sum(0) == 1).all()
    counts = dict(zip(PARTS, p[:, :-1].sum(1)))
    assert counts["left_arm"] == counts["right_arm"] == 24 and counts["left_leg"] == counts["right_leg"] == 15
    assert Rig.of(canonical_skeleton()).membership.shape == (6, 23)


def test_correspondence_between_cmu_and_the_game_rig(mocap):
    pairs = correspondence(Rig.of(skeleton_of(mocap, "cmu_asf")), Rig.of(skeleton_of(mocap, "game_100")))
    assert pairs["lhumerus"] == "CC_Base_L_Upperarm" and pairs["rradius"] == "CC_Base_R_Forearm"
    assert pairs["lfemur"] == "CC_Base_L_Thigh" and pairs["rtoes"] == "CC_Base_R_ToeBase"
    assert pairs["root"] == "CC_Base_Hip" and pairs["lowerneck"] == "CC_Base_NeckTwist01"
    assert "lhipjoint" not in pairs and "upperneck" not in pairs


def test_rest_pose_difference_t_pose_against_a_pose_and_legs_up():
    t_pose = canonical_skeleton()
    a_pose = _a_pose(t_pose, 45.0)
    diff = rest_difference(Rig.of(t_pose), Rig.of(a_pose))
    assert diff["left_elbow"] == pytest.approx(45.0, abs=0.5) and diff["right_wrist"] == pytest.approx(45.0, abs=0.5)
    assert max(diff[k] for k in ("left_knee", "spine2", "head")) < 0.5


def _a_pose(skeleton: Skeleton, degrees: float) -> Skeleton:
    """The canonical T-pose with both arms lowered by `degrees` at the shoulders."""
    offsets, ends = skeleton.offsets.double().numpy(), skeleton.end_site_offsets.double().numpy()
    for side, sign in (("left", -1.0), ("right", 1.0)):
        a = np.radians(degrees) * sign
        turn = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        for joint in (f"{side}_elbow", f"{side}_wrist"):
            offsets[skeleton.index(joint)] = turn @ offsets[skeleton.index(joint)]
        e = skeleton.end_site_names.index(f"{side}_hand")
        ends[e] = turn @ ends[e]
    return Skeleton(skeleton.names, skeleton.parents, offsets, skeleton.end_site_parents, ends, skeleton.end_site_names)


def test_a_rig_without_a_knee_is_refused_naming_the_knee(mocap):
    skeleton = without(read_asf(mocap / "cmu_fairmotion/01.asf").skeleton, "ltibia")
    with pytest.raises(MissingKeyJoints, match="left_knee") as error:
        Rig.of(skeleton, label="no_knee.asf")
    assert "no_knee.asf" in str(error.value) and "override file" in str(error.value)
    assert "right_knee" not in error.value.missing


def test_a_rig_without_an_arm_is_refused_naming_the_wrist(mocap):
    """The tree's shape offers no hand for the missing arm (the remaining hand's two fingertips
    are no pair of arms): refused instead of retargeting both arms' motion onto one."""
    skeleton = read_asf(mocap / "cmu_fairmotion/01.asf").skeleton
    arm = ["lclavicle", "lhumerus", "lradius", "lwrist", "lhand", "lfingers", "lthumb"]
    for name in reversed(arm):   # leaves first, so no joint is re-hung
        skeleton = without(skeleton, name)
    assert not any(n.startswith(("lclav", "lhum", "lrad", "lwr", "lhand", "lfing", "lthu")) for n in skeleton.names)
    with pytest.raises(MissingKeyJoints, match="left_wrist.*shape does not show one") as error:
        Rig.of(skeleton, label="one_arm.asf")
    assert not {"left_ankle", "right_ankle", "head"} & set(error.value.missing)


def test_an_unknown_layout_is_refused_naming_what_is_missing():
    chain = Skeleton(["a", "b", "c"], [-1, 0, 1], [[0, 1, 0], [0, 0.5, 0], [0, 0.5, 0]])
    with pytest.raises(MissingKeyJoints, match="head.*left_wrist"):
        Rig.of(chain)


def test_override_file_fixes_joints_and_parts(mocap, tmp_path):
    game = skeleton_of(mocap, "game_100")
    skeleton = renamed(game)  # names say nothing: the head is found where the face bones fork
    j = {name: f"j{game.index(name)}" for name in ("CC_Base_FacialBone", "CC_Base_Head", "CC_Base_L_Clavicle", "CC_Base_L_Hand")}
    assert find_key_joints(skeleton)["head"] == j["CC_Base_FacialBone"]
    path = tmp_path / "rig.json"
    path.write_text(json.dumps({"joints": {"head": j["CC_Base_Head"]}, "parts": {j["CC_Base_L_Clavicle"]: "torso"}}))
    rig = Rig.of(skeleton, load_overrides(path))
    assert rig.key_joints["head"] == j["CC_Base_Head"]
    assert rig.part_of(j["CC_Base_L_Clavicle"]) == "torso" and rig.part_of(j["CC_Base_L_Hand"]) == "torso"
    toml = tmp_path / "rig.toml"
    toml.write_text('[joints]\nleft_knee = "nope"\n')
    with pytest.raises(ValueError, match="nope"):
        Rig.of(skeleton, load_overrides(toml))
    path.write_text(json.dumps({"joints": {"left_kneee": "j1"}}))
    with pytest.raises(ValueError, match="left_kneee"):
        load_overrides(path)

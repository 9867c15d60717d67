"""Rigs as they are (issue 22 item 3): BVH units and channel orders kept, a root bone on the
floor, no legs, twist bones and fingers, the target's floor. The rigs are built here from the
canonical body; the motion is a real CMU walk."""

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from humotion import rotations as rot
from humotion.canonical import JOINTS, canonical_skeleton, to_canonical
from humotion.cli import main
from humotion.io import load_motion
from humotion.io.bvh import read_bvh, write_bvh
from humotion.motion import Motion
from humotion.retarget import Rig, retarget
from humotion.skeleton import Skeleton

from data_root import DATA

BODY = canonical_skeleton()


@pytest.fixture(scope="module")
def walk(mocap):
    """CMU 02_01, a walk on subject 02's 31-joint skeleton, at 30 fps."""
    return load_motion(mocap / "cmu_mocgui_s02/02_01.amc").resample(30.0)


def with_joints(skeleton: Skeleton, added: list[tuple[str, str, tuple]]) -> Skeleton:
    """The skeleton with joints (name, parent name, offset in metres) appended."""
    names = list(skeleton.names) + [n for n, _, _ in added]
    parents = list(skeleton.parents) + [names.index(p) for _, p, _ in added]
    offsets = np.concatenate([skeleton.offsets, np.array([o for _, _, o in added], dtype=float).reshape(-1, 3)])
    return Skeleton(names, parents, offsets, skeleton.end_site_parents, skeleton.end_site_offsets, skeleton.end_site_names)


def pelvis_relative(motion: Motion, names) -> torch.Tensor:
    p = motion.world_positions()
    index = [motion.skeleton.index(n) for n in names]
    return p[:, index] - p[:, motion.skeleton.index("pelvis")][:, None]


def test_bvh_output_keeps_a_centimetre_zxy_rigs_units_and_orders(walk, tmp_path):
    """A centimetre rig in ZXY is written back in centimetres and ZXY by `humotion retarget`
    (onto it) and `humotion convert` (its own takes); before, always metres and ZYX."""
    rig = tmp_path / "rig_cm_zxy.bvh"
    rig.write_text(_bvh_text(BODY, 100.0, "Zrotation Xrotation Yrotation"))
    out = tmp_path / "walk_on_rig.bvh"
    result = CliRunner().invoke(main, ["retarget", str(walk_path(walk, tmp_path)), "--to", str(rig), "-o", str(out)])
    assert result.exit_code == 0, result.output
    text = out.read_text().split("MOTION")[0]
    assert "OFFSET 9.000000 -7.000000 0.000000" in text                  # left hip, in cm
    assert text.count("Zrotation Xrotation Yrotation") == BODY.num_joints and "Yrotation Xrotation" not in text
    back = read_bvh(out, units="cm")
    expected = retarget(load_motion(walk_path(walk, tmp_path)), BODY)
    order = [back.skeleton.index(n) for n in BODY.names]                     # BVH lists joints depth first
    assert torch.allclose(back.world_positions()[:, order], expected.world_positions(), atol=1e-4)
    again = tmp_path / "again.bvh"
    assert CliRunner().invoke(main, ["convert", str(out), str(again)]).exit_code == 0
    assert again.read_text().split("MOTION")[0] == text


def _bvh_text(skeleton: Skeleton, per_metre: float, rotations: str) -> str:
    """A BVH file of the skeleton at rest (2 frames), lengths times per_metre, every joint with
    the given rotation channels."""
    lines = ["HIERARCHY"]

    def block(j: int, depth: int) -> None:
        pad = "  " * depth
        lines.extend([pad + ("ROOT " if j == 0 else "JOINT ") + skeleton.names[j], pad + "{",
                      pad + "  OFFSET " + " ".join(f"{x * per_metre:.6f}" for x in skeleton.offsets[j]),
                      pad + "  CHANNELS " + ("6 Xposition Yposition Zposition " if j == 0 else "3 ") + rotations])
        for c in skeleton.children(j):
            block(c, depth + 1)
        for e, p in enumerate(skeleton.end_site_parents):
            if p == j:
                lines.extend([pad + "  End Site", pad + "  {", pad + "    OFFSET " + " ".join(
                    f"{x * per_metre:.6f}" for x in skeleton.end_site_offsets[e]), pad + "  }"])
        lines.append(pad + "}")

    block(0, 0)
    row = " ".join(["0"] * (3 + 3 * skeleton.num_joints))
    return "\n".join(lines + ["MOTION", "Frames: 2", "Frame Time: 0.0333333", row, row]) + "\n"


def walk_path(walk: Motion, tmp_path) -> str:
    path = tmp_path / "walk.bvh"
    if not path.exists():
        write_bvh(walk, path)
    return path


def test_iclone_rig_keeps_its_centimetres(mocap, walk, tmp_path):
    """The iClone rig's hip OFFSET 105.214241 cm stays 105.214241, not 1.052142."""
    out = tmp_path / "on_iclone.bvh"
    result = CliRunner().invoke(main, ["retarget", str(walk_path(walk, tmp_path)), "--to",
                                       str(mocap / "cmu_iclone_ccskeleton/002_01.bvh.gz"), "-o", str(out)])
    assert result.exit_code == 0, result.output
    assert "OFFSET 0.000000 0.000000 105.214241" in out.read_text().split("MOTION")[0]


def test_a_root_bone_stays_on_the_floor_under_the_hips(mocap, walk):
    """A root bone on the floor under the pelvis (as iClone's RL_BoneRoot): in the result it stays
    on the floor under the hips, facing their way (before: at hip height, 0.95 m behind them)."""
    rig = Skeleton(["Root"] + list(BODY.names), [-1] + [p + 1 for p in BODY.parents],
                   np.concatenate([[[0, 0, 0]], [[0, 0.95, 0]], BODY.offsets[1:]]),
                   [p + 1 for p in BODY.end_site_parents], BODY.end_site_offsets, BODY.end_site_names)
    assert Rig.of(rig).on_floor
    result, plain = retarget(walk, rig), retarget(walk, BODY)
    p = result.world_positions()
    root, pelvis = p[:, 0], p[:, rig.index("pelvis")]
    assert float((root - pelvis)[:, [0, 2]].norm(dim=-1).max()) < 1e-4           # under the hips
    assert abs(float(root[:, 1].median())) < 1e-4 and float(root[:, 1].abs().max()) < 0.08  # on the floor
    facing = result.world()[0][:, 0][:, :, 2]                                    # the root's forward
    hips = plain.world()[0][:, 0][:, :, 2] * torch.tensor([1.0, 0.0, 1.0])       # the body's forward, level
    assert float(torch.nn.functional.cosine_similarity(facing, hips, dim=-1).min()) > 0.9999
    # the body itself is the one retargeted onto the plain canonical rig
    assert torch.allclose(pelvis_relative(result, JOINTS), pelvis_relative(plain, JOINTS), atol=1e-4)

    # The real iClone rig, whose RL_BoneRoot holds its hips 105 cm up along its Z (a Z-up zero pose).
    game = load_motion(mocap / "cmu_iclone_ccskeleton/002_01.bvh.gz")
    p = retarget(walk, game.skeleton).world_positions()
    root, pelvis = p[:, 0], p[:, game.skeleton.index("CC_Base_Hip")]
    assert float((root - pelvis)[:, [0, 2]].norm(dim=-1).max()) < 1e-4
    assert abs(float(root[:, 1].median())) < 1e-4 and float(root[:, 1].abs().max()) < 0.08


def _upper_body() -> Skeleton:
    """The canonical body without legs (an upper-body avatar)."""
    legs = {n for n in BODY.names if n.split("_")[-1] in ("hip", "knee", "ankle", "foot")}
    keep = [j for j, n in enumerate(BODY.names) if n not in legs]
    new = {old: i for i, old in enumerate(keep)}
    ends = [e for e, p in enumerate(BODY.end_site_parents) if p in new]
    return Skeleton([BODY.names[j] for j in keep], [-1 if BODY.parents[j] < 0 else new[BODY.parents[j]] for j in keep],
                    BODY.offsets[keep], [new[BODY.end_site_parents[e]] for e in ends], BODY.end_site_offsets[ends],
                    [BODY.end_site_names[e] for e in ends])


def test_an_upper_body_rig_retargets_without_feet(walk):
    """No legs: no refusal, no feet, no leg IK; the upper body moves as on the full body, the
    pelvis at its rest height plus the walk's rise and fall (before: 'cannot find key joint(s)')."""
    upper = _upper_body()
    rig = Rig.of(upper)
    assert not rig.legs and rig.key_joints["left_ankle"] == "pelvis"
    parts = {"pelvis": "torso", "spine3": "torso", "left_wrist": "left_arm", "right_collar": "right_arm", "head": "head"}
    assert {n: rig.part_of(n) for n in parts} == parts
    result, full = retarget(walk, upper), retarget(walk, BODY, feet=False)
    names = [n for n in upper.names if n != "pelvis"]
    assert torch.allclose(pelvis_relative(result, names), pelvis_relative(full, names), atol=1e-4)
    height = result.world_positions()[:, 0, 1]
    assert float((height - 0.95).abs().max()) < 0.1
    body = to_canonical(result)                      # the canonical body reads it too: legs of no length
    assert body.skeleton.names == JOINTS


def test_twist_bones_take_their_share_of_the_wrists_twist(walk):
    """A forearm twist bone half way from elbow to wrist turns about the forearm by half the
    wrist's twist (before: it kept the elbow's rotation, so a skin would wrap at the wrist)."""
    arm = BODY.offsets[BODY.index("left_wrist")]
    rig = with_joints(BODY, [("left_forearm_twist", "left_elbow", 0.5 * arm), ("left_upperarm_twist", "left_shoulder",
                                                                              0.5 * BODY.offsets[BODY.index("left_elbow")])])
    assert Rig.of(rig).twists[rig.index("left_forearm_twist")] == (rig.index("left_wrist"), 0.5)
    world = retarget(walk, rig).world()[0]
    elbow, wrist, twist = (world[:, rig.index(n)] for n in ("left_elbow", "left_wrist", "left_forearm_twist"))
    axis = torch.as_tensor(arm / np.linalg.norm(arm))

    def twist_angle(relative):
        q = rot.matrix_to_quat(relative)
        return 2 * torch.atan2(q[:, 1:] @ axis.to(q.dtype), q[:, 0])

    wrist_twist = twist_angle(elbow.transpose(-1, -2) @ wrist)
    assert float(wrist_twist.abs().max()) > np.radians(10)
    bone = elbow.transpose(-1, -2) @ twist
    assert torch.allclose(twist_angle(bone), 0.5 * wrist_twist, atol=1e-4)
    assert torch.allclose(bone @ axis.to(bone.dtype), axis.to(bone.dtype).expand(len(bone), 3), atol=1e-5)  # about the forearm only


def _hand(names: list[str], lengths: list[float], direction=(1.0, 0.0, 0.0)) -> list[tuple[str, str, tuple]]:
    """A left finger: a straight chain of joints from the wrist, along direction."""
    parents = ["left_wrist"] + names[:-1]
    unit = np.array(direction) / np.linalg.norm(direction)
    return [(n, p, tuple(length * unit)) for n, p, length in zip(names, parents, lengths)]


def test_fingers_follow_the_sources_fingers_of_the_same_name(walk):
    """A Mixamo-named curling middle finger drives a 3ds-Max-named one of other lengths and another
    rest direction (30 degrees forward): each phalanx points where the source's does (before: it
    kept its rest, only a same-named joint was copied)."""
    mixamo = ["LeftHandMiddle1", "LeftHandMiddle2", "LeftHandMiddle3"]
    biped = ["Bip01_L_Finger2", "Bip01_L_Finger21", "Bip01_L_Finger22"]
    source_rig = with_joints(BODY, _hand(mixamo, [0.09, 0.04, 0.03]))
    target_rig = with_joints(BODY, _hand(biped, [0.10, 0.05, 0.025], (np.cos(np.pi / 6), 0.0, np.sin(np.pi / 6))))
    source = retarget(walk, source_rig, feet=False)
    curl = torch.linspace(0, 1.2, len(source))                                     # radians, about -Z: down
    bend = rot.convert(torch.stack([torch.zeros_like(curl), torch.zeros_like(curl), -curl], -1), "rotvec", "quat")
    rotations = source.rotations.clone()
    rotations[:, [source_rig.index(n) for n in mixamo]] = bend[:, None].float()
    source = Motion(source_rig, rotations, source.root_positions, source.fps)
    result = retarget(source, target_rig, feet=False)

    def phalanges(motion, names):
        p = motion.world_positions()[:, [motion.skeleton.index(n) for n in names]]
        return torch.nn.functional.normalize(p[:, 1:] - p[:, :-1], dim=-1)

    cos = (phalanges(result, biped) * phalanges(source, mixamo)).sum(-1)
    assert float(cos.min()) > 0.9999
    assert float((phalanges(source, mixamo)[-1] * phalanges(source, mixamo)[0]).sum(-1).min()) < 0.5  # it did curl


def test_the_result_stands_on_the_targets_floor(walk):
    """A source whose floor is 12 cm up (a capture volume's offset) gives the same result as
    one on y = 0: the target's lowest key point stands on its floor (before: 12 cm up, scaled)."""
    raised = Motion(walk.skeleton, walk.rotations, walk.root_positions + torch.tensor([0.0, 0.12, 0.0]), walk.fps)
    tall = BODY.scaled(1.1)
    a, b = retarget(walk, tall), retarget(raised, tall)
    assert torch.allclose(a.world_positions(), b.world_positions(), atol=1e-4)
    lowest = Rig.of(tall).key_points(*a.world())[..., 1].amin(-1)
    assert float(torch.quantile(lowest.double(), 0.05)) == pytest.approx(0.0, abs=1e-4)
    assert float(retarget(walk, tall, floor=0.3).world_positions()[:, 0, 1].mean()) == pytest.approx(
        float(a.world_positions()[:, 0, 1].mean()) + 0.3, abs=1e-4)


def test_the_command_stands_the_result_where_the_rigs_own_clip_stands(mocap, walk, tmp_path):
    """`humotion retarget --to` a clip on the 100-joint iClone rig (no root bone; its key points
    stand about 8 cm up): the result's lowest key points stand as high as that clip's."""
    rig_file = mocap / "cmu_iclone_ccskeleton/001_01.bvh.gz"
    out = tmp_path / "on_game.bvh"
    result = CliRunner().invoke(main, ["retarget", str(walk_path(walk, tmp_path)), "--to", str(rig_file), "-o", str(out)])
    assert result.exit_code == 0, result.output
    clip, rig = load_motion(rig_file), Rig.of(load_motion(rig_file).skeleton)
    assert rig.floor_of(clip) > 0.05
    assert rig.floor_of(load_motion(out)) == pytest.approx(rig.floor_of(clip), abs=0.005)


def test_a_middle_joint_named_as_an_elbow_is_trusted_whatever_its_length():
    """A stylised character (the three.js robot) has a forearm twice its upper arm: named
    LowerArm, it is taken as the elbow instead of refusing the arm as one without an elbow."""
    from humotion.io.character import read_character
    from humotion.retarget.character import character_rig
    path = DATA / "characters" / "RobotExpressive.glb"
    if not path.is_file():
        pytest.skip(f"{path} is not there")
    rig = character_rig(read_character(path))
    assert rig.key_joints["left_elbow"] == "LowerArmL" and rig.key_joints["right_wrist"] == "Palm2R"

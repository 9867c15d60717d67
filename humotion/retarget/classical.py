"""Classical retargeting between skeletons of any structure, and the naive baseline.

:func:`retarget` (the baseline that always works):
1. Rotations are transferred in the world frame through the key-joint correspondence, each
   rig's rest pose aligned to the canonical T-pose (humotion.retarget.rig): a target key joint
   takes W_source @ A_source @ A_target^T. Target joints that are no key joint copy the local
   rotation of a source joint of the same name (so a rig onto itself is reproduced exactly),
   else keep their rest (identity) rotation: twists, fingers and extra spine joints follow
   their parent.
   Finger joints named by finger (thumb, index, middle, ring, little or 3ds Max's Finger0-4)
   turn as the source's finger of the same name and segment, through per-finger alignments made
   as the key joints' are (Rig.finger_alignment), so a bent finger bends whatever each rig's
   finger rest directions; twist bones (named twist or roll) between two key joints
   take their share of the second one's twist about the segment (half way along the forearm:
   half the wrist's twist). Joints above the pelvis (a root bone such as iClone's RL_BoneRoot)
   stand upright under the hips, facing where the hips face.
2. The root trajectory is scaled by the ratio of leg lengths, measured as hip heights (pelvis
   above the soles in the T-pose): stride and pelvis height scale with the leg (by the trunks,
   pelvis to head, when a rig has no legs). The result is then moved vertically to stand on the
   target's floor (y = 0, or floor=), whatever the source's floor was: its lowest key point,
   over the frames it stands, at the rig's own clearance above it (Rig.clearance: a character's
   toe joint sits a few cm above its soles). A root bone under the hips (Rig.on_floor) has its
   median height on the floor instead: it moves up and down only as the hips do, the rig
   holding its hips at a fixed offset from it.
3. Foot contacts found on the source (contacts.foot_contacts) are kept on the target: during
   each contact the target's ankle (or, heel raised, its toes) stays where it stood on average,
   and analytic two-bone IK on the legs puts it there, blended in and out over 0.1 s; the foot
   keeps its transferred orientation. Optional hand targets use the same IK on the arms.
   A rig without legs (an upper-body avatar) gets no foot contacts and no leg IK.

:func:`copy_rotations` is the naive baseline: local rotations copied joint to joint through the
same correspondence, the root copied unscaled, no rest-pose alignment, no IK.
"""

from __future__ import annotations

import torch
from tqdm.auto import tqdm

from humotion import rotations as rot
from humotion.canonical import JOINTS
from humotion.motion import Motion
from humotion.retarget.contacts import floor_height, foot_contacts
from humotion.retarget.ik import two_bone_ik
from humotion.retarget.rig import Rig, correspondence
from humotion.skeleton import Skeleton, forward_kinematics, local_rotations

FOOT_POINTS = ("left_ankle", "left_foot", "right_ankle", "right_foot")
BLEND_SECONDS = 0.1
CHUNK = 2000  # frames transferred at a time (one progress-bar step)


def check_finite(motion: Motion, label: str = "") -> None:
    """Raise ValueError naming the motion (file) when it has no frames, or the first frame and
    joint holding NaN or infinity."""
    label = label or motion.name or "motion"
    if motion.num_frames == 0:
        raise ValueError(f"{label}: the motion has no frames")
    checks = [("rotation", motion.rotations), ("root position", motion.root_positions[:, None])]
    if motion.joint_offsets is not None:
        checks.append(("offset", motion.joint_offsets))
    for what, values in checks:
        bad = ~torch.isfinite(values).all(-1)                    # (T, J)
        if bad.any():
            frame, joint = (int(i) for i in torch.nonzero(bad)[0])
            raise ValueError(f"{label}: frame {frame}, joint {motion.skeleton.names[joint]!r}: {what} is NaN or infinite")


def as_rig(x: Skeleton | Rig, label: str) -> Rig:
    """x itself when it is a Rig, else the Rig of the skeleton x (label names it in errors)."""
    return x if isinstance(x, Rig) else Rig.of(x, label=label)


def root_for(local: torch.Tensor, skeleton: Skeleton, joint: int, position: torch.Tensor) -> torch.Tensor:
    """(T, 3) root positions that put `joint` at position (T, 3), given local rotations."""
    _, at_origin = forward_kinematics(local, torch.zeros_like(position), skeleton.offsets, skeleton.parents)
    return position - at_origin[:, joint]


def _heading(pose: torch.Tensor) -> torch.Tensor:
    """(T, 3, 3) turns about the vertical to where canonical pelvis rotations (T, 3, 3) face."""
    forward = pose[:, :, 2]
    yaw = torch.atan2(forward[:, 0], forward[:, 2])
    return rot.convert(torch.stack([torch.zeros_like(yaw), yaw, torch.zeros_like(yaw)], -1), "rotvec", "matrix")


def _twist(relative: torch.Tensor, axis: torch.Tensor) -> torch.Tensor:
    """(T,) angle of rotations (T, 3, 3) about a unit axis (3,): the twist of their swing-twist split."""
    q = rot.matrix_to_quat(relative)
    return 2 * torch.atan2(q[:, 1:] @ axis, q[:, 0])


def _scale(src: Rig, tgt: Rig) -> float:
    """Root motion's scale: the ratio of hip heights, of trunks where a rig has no legs."""
    return tgt.hip_height() / src.hip_height() if src.legs and tgt.legs else tgt.trunk_length() / src.trunk_length()


def _transfer(source: Motion, src: Rig, tgt: Rig) -> tuple[torch.Tensor, ...]:
    """Target local rotations (T, J, 3, 3), root positions (T, 3), and of the source the foot
    points (T, 4, 3), the pelvis (T, 3) and the lowest key point's height (T,), in float64."""
    offsets = source.skeleton.offsets if source.joint_offsets is None else source.joint_offsets.double()
    world, positions = forward_kinematics(source.rotations.double(), source.root_positions.double(), offsets,
                                          source.skeleton.parents)
    pose = world[:, src.drivers] @ src.alignment                        # (T, 22, 3, 3): away from T-pose
    source_local = rot.quat_to_matrix(source.rotations.double())
    same_name = {j: source.skeleton.names.index(n) for j, n in enumerate(tgt.skeleton.names)
                 if n in source.skeleton.names}
    source_finger = {role: j for j, role in src.fingers.items()}
    ground = _heading(pose[:, 0]) @ tgt.standing if tgt.ground else None
    eye = torch.eye(3, dtype=torch.float64).expand(len(source), 3, 3)
    target_world: list[torch.Tensor] = []
    for j, p in enumerate(tgt.skeleton.parents):
        k = int(tgt.owners[j])
        if k >= 0:
            target_world.append(pose[:, k] @ tgt.alignment[k].T)
            continue
        if j in tgt.ground:
            target_world.append(ground)
            continue
        if tgt.fingers.get(j) in source_finger:
            f = source_finger[tgt.fingers[j]]
            target_world.append(world[:, f] @ (src.finger_alignment[f] @ tgt.finger_alignment[j].T))
            continue
        local = source_local[:, same_name[j]] if j in same_name else eye
        target_world.append(local if p < 0 else target_world[p] @ local)
    rest = tgt.skeleton.rest_positions(torch.float64)
    for j, (b, share) in tgt.twists.items():
        if j in same_name:
            continue
        a = tgt.skeleton.parents[j]
        axis = torch.nn.functional.normalize(rest[b] - rest[a], dim=0)
        angle = share * _twist(target_world[a].transpose(-1, -2) @ target_world[b], axis)
        target_world[j] = target_world[a] @ rot.convert(angle[:, None] * axis, "rotvec", "matrix")
    local = local_rotations(torch.stack(target_world, dim=1), tgt.skeleton.parents)
    root = root_for(local, tgt.skeleton, tgt.joint("pelvis"), _scale(src, tgt) * positions[:, src.joint("pelvis")])
    lowest = src.key_points(world, positions)[..., 1].amin(-1)
    return local, root, src.points(world, positions, FOOT_POINTS), positions[:, src.joint("pelvis")], lowest


def _stand(local: torch.Tensor, root: torch.Tensor, src: Rig, tgt: Rig, source_lowest: torch.Tensor,
           source_pelvis: torch.Tensor, floor: float) -> torch.Tensor:
    """Root positions (T, 3) moved vertically onto the target's floor at height floor: its root
    bone's median height there (Rig.on_floor), else its lowest key point, over the frames it
    stands, at Rig.clearance above it. A rig without legs keeps its pelvis at its rest height
    plus the source pelvis's scaled rise above its own standing height."""
    root = root.clone()
    world, positions = forward_kinematics(local, root, tgt.skeleton.offsets, tgt.skeleton.parents)
    if tgt.on_floor:
        root[:, 1] += floor - positions[:, tgt.ground[0], 1].median()
    elif tgt.legs:
        root[:, 1] += floor + tgt.clearance() - floor_height(tgt.key_points(world, positions))
    else:
        standing = (float(torch.quantile(source_lowest, 0.05)) + src.hip_height() if src.legs
                    else float(source_pelvis[:, 1].mean()))
        rise = _scale(src, tgt) * (source_pelvis[:, 1] - standing)
        pelvis = tgt.joint("pelvis")
        root[:, 1] += tgt.skeleton.rest_positions()[pelvis, 1] + rise - positions[:, pelvis, 1]
    return root


def retarget(source: Motion, target: Skeleton | Rig, *, source_rig: Rig | None = None, feet: bool = True,
             hand_targets: dict[str, torch.Tensor] | None = None, progress: bool | None = None,
             floor: float = 0.0) -> Motion:
    """The source motion on the target skeleton (same frames and fps).

    target: a Skeleton, or a Rig made with overrides (Rig.of(skeleton, overrides)).
    feet: keep the source's foot contacts with leg IK (False: rotations and root only; always
        off when either rig has no legs).
    hand_targets: {"left": (T, 3), "right": (T, 3)} world wrist positions in metres to reach
        with arm IK; rows of NaN leave that frame alone.
    progress: show a progress bar (default: for clips over CHUNK frames).
    floor: height of the floor the result stands on, metres (Rig.floor_of(a clip on the target
        rig): where that clip stands). A rig without legs ignores it (its pelvis stays at its
        rest height, rising and falling as the source's).
    Raises ValueError for NaNs in the source (frame and joint named) and MissingKeyJoints for a
    rig without the joints retargeting needs.
    """
    check_finite(source)
    src = source_rig or as_rig(source.skeleton, source.name or "source")
    tgt = as_rig(target, "target rig")
    show = progress if progress is not None else len(source) > CHUNK
    parts = []
    with tqdm(total=len(source), desc="retargeting", unit="frame", disable=not show) as bar:
        for start in range(0, len(source), CHUNK):
            parts.append(_transfer(source[start:start + CHUNK], src, tgt))
            bar.update(len(parts[-1][0]))
    local, root, source_feet, pelvis, source_lowest = (torch.cat(x) for x in zip(*parts))
    root = _stand(local, root, src, tgt, source_lowest, pelvis, floor)
    if feet and src.legs and tgt.legs:
        contacts = foot_contacts(source_feet, source.fps, src.standing_height())
        local = plant_feet(local, root, tgt, contacts, source.fps)
    for side, wanted in (hand_targets or {}).items():
        wanted = torch.as_tensor(wanted, dtype=torch.float64)
        if side not in ("left", "right") or wanted.shape != (len(source), 3):
            raise ValueError(f"hand target {side!r}: expected 'left'/'right' with ({len(source)}, 3) positions, one per "
                             f"source frame, got shape {tuple(wanted.shape)} (resample it to {source.fps:g} fps)")
        local = reach(local, root, tgt, side, wanted, arm=True)
    return Motion(tgt.skeleton, rot.matrix_to_quat(local).float(), root.float(), source.fps, name=source.name)


def copy_rotations(source: Motion, target: Skeleton | Rig, *, source_rig: Rig | None = None) -> Motion:
    """Naive baseline: local rotations copied joint to joint (key joints and same-named joints),
    the pelvis placed where the source's is, unscaled; other joints at rest."""
    check_finite(source)
    src = source_rig or as_rig(source.skeleton, source.name or "source")
    tgt = as_rig(target, "target rig")
    local = torch.eye(3, dtype=torch.float64).repeat(len(source), tgt.skeleton.num_joints, 1, 1)
    source_local = rot.quat_to_matrix(source.rotations.double())
    for a, b in correspondence(src, tgt).items():
        local[:, tgt.skeleton.index(b)] = source_local[:, source.skeleton.index(a)]
    pelvis = source.world_positions().double()[:, src.joint("pelvis")]
    root = root_for(local, tgt.skeleton, tgt.joint("pelvis"), pelvis)
    return Motion(tgt.skeleton, rot.matrix_to_quat(local).float(), root.float(), source.fps, name=source.name)


def _segments(mask: torch.Tensor) -> list[tuple[int, int]]:
    """[start, end) of each run of True in a (T,) bool tensor."""
    padded = torch.cat([mask.new_zeros(1), mask, mask.new_zeros(1)])
    edges = (padded[1:] != padded[:-1]).nonzero()[:, 0]
    return list(zip(edges[::2].tolist(), edges[1::2].tolist()))


def _locks(points: torch.Tensor, contacts: torch.Tensor, blend: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Per frame, where a point should stay (T, 3) and how strongly (T,) in [0, 1]: during a
    contact at its mean horizontal position over that contact (its height free: a planted foot
    rolls), fading out over `blend` frames either side."""
    frames = points.shape[0]
    lock, weight = points.clone(), torch.zeros(frames, dtype=points.dtype)
    t = torch.arange(frames, dtype=points.dtype)
    for start, end in _segments(contacts):
        gap = torch.clamp(torch.maximum(start - t, t - (end - 1)), min=0)
        w = torch.clamp(1 - gap / (blend + 1), min=0)
        stronger = w > weight
        lock[stronger, 0::2] = points[start:end, 0::2].mean(0)
        weight = torch.maximum(weight, w)
    return lock, weight


def plant_feet(local: torch.Tensor, root: torch.Tensor, tgt: Rig, contacts: torch.Tensor, fps: float) -> torch.Tensor:
    """Local rotations with each foot held in place during the source's contacts (T, 4)."""
    world, positions = forward_kinematics(local, root, tgt.skeleton.offsets, tgt.skeleton.parents)
    feet = tgt.points(world, positions, FOOT_POINTS)
    blend = max(1, round(BLEND_SECONDS * fps))
    for s, side in enumerate(("left", "right")):
        ankle, toes = feet[:, 2 * s], feet[:, 2 * s + 1]
        ankle_lock, ankle_w = _locks(ankle, contacts[:, 2 * s], blend)
        toe_lock, toe_w = _locks(toes, contacts[:, 2 * s + 1], blend)
        # Heel down: hold the ankle. Heel raised, toes down: hold the toes (the ankle follows).
        shift = torch.where((ankle_w >= toe_w)[:, None], ankle_w[:, None] * (ankle_lock - ankle),
                            toe_w[:, None] * (toe_lock - toes))
        wanted = torch.where((torch.maximum(ankle_w, toe_w) > 0)[:, None], ankle + shift, torch.nan)
        local = reach(local, root, tgt, side, wanted, arm=False)
    return local


def reach(local: torch.Tensor, root: torch.Tensor, tgt: Rig, side: str, wanted: torch.Tensor, arm: bool) -> torch.Tensor:
    """Local rotations with the wrist (arm) or ankle brought onto wanted (T, 3) by two-bone IK,
    on the frames where wanted is finite; the end joint keeps its world rotation."""
    names = ("shoulder", "elbow", "wrist") if arm else ("hip", "knee", "ankle")
    a, b, c = (tgt.joint(f"{side}_{n}") for n in names)
    frames = torch.isfinite(wanted).all(-1)
    if not frames.any():
        return local
    parents = tgt.skeleton.parents
    world, positions = forward_kinematics(local[frames], root[frames], tgt.skeleton.offsets, parents)
    facing = (world[:, tgt.joint("pelvis")] @ tgt.alignment[JOINTS.index("pelvis")])[..., 2]
    turn_a, turn_b = two_bone_ik(positions[:, a], positions[:, b], positions[:, c], wanted[frames],
                                 -facing if arm else facing)
    new = local[frames]
    new[:, a] = world[:, parents[a]].transpose(-1, -2) @ turn_a @ world[:, a]
    new[:, b] = (turn_a @ world[:, parents[b]]).transpose(-1, -2) @ turn_b @ world[:, b]
    new[:, c] = (turn_b @ world[:, parents[c]]).transpose(-1, -2) @ world[:, c]
    local = local.clone()
    local[frames] = new
    return local

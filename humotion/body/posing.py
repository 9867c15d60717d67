"""Poses for the body rig: canonical (mocap) poses retargeted onto Anny's 76-joint rig, finger
curls and gaze, and the samplers the training data draws poses and expressions with.

    poses = sample_mocap_poses(clips, count, rng)               # canonical body, heading removed
    local = retarget(poses.world_rotations, poses.rest, rig_points(rest_v, rest_j, names), names, parents)

Rotations follow the convention of :mod:`humotion.body.skinning` (rest-relative, world-aligned
rest axes); conversions go through :mod:`humotion.rotations`. Torch tensors throughout: float64
rotations and points (metres), int64 indices; the samplers draw with a numpy Generator, as the
training data always has, so that a seed gives the same poses and expressions as before.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
import math
from pathlib import Path

import numpy as np
import torch

from humotion import rotations as rot
from humotion.canonical import END_SITES, JOINTS, canonical_skeleton, to_canonical
from humotion.skeleton import local_rotations

# -- the rig mapping ---------------------------------------------------------------------------

CANONICAL_TO_RIG = {
    "pelvis": "root", "spine1": "spine04", "spine2": "spine02", "spine3": "spine01", "neck": "neck01", "head": "head",
    **{f"{side}_{joint}": f"{bone}.{s}" for side, s in (("left", "L"), ("right", "R")) for joint, bone in (
        ("hip", "upperleg01"), ("knee", "lowerleg01"), ("ankle", "foot"), ("collar", "clavicle"),
        ("shoulder", "upperarm01"), ("elbow", "lowerarm01"), ("wrist", "wrist"))},
}
"""Canonical joint -> Anny bone it drives (the collars' only nominally: :data:`HELD_AT_REST`).
The canonical feet (toe bend) have no Anny bone; Anny's
twist bones (upperleg02, lowerleg02, upperarm02, lowerarm02), spine05/03, shoulder01, neck02/03
follow their parents, so each mapped bone's aim point below moves rigidly with it."""

AIMS = {
    "spine1": ("spine02", "spine2"), "spine2": ("spine01", "spine3"), "spine3": ("neck01", "neck"),
    "neck": ("head", "head"), "head": ("head_top", "head_top"),
    **{f"{side}_{joint}": (rig.format(s=s), canon.format(side=side)) for side, s in (("left", "L"), ("right", "R"))
       for joint, rig, canon in (
           ("hip", "lowerleg01.{s}", "{side}_knee"), ("knee", "foot.{s}", "{side}_ankle"),
           ("ankle", "toe_tip.{s}", "{side}_toe"), ("collar", "upperarm01.{s}", "{side}_shoulder"),
           ("shoulder", "lowerarm01.{s}", "{side}_elbow"), ("elbow", "wrist.{s}", "{side}_wrist"),
           ("wrist", "finger3-1.{s}", "{side}_hand"))},
}
"""Canonical joint -> (rig point, canonical point) whose direction from the joint defines the
bone's rest alignment. Rig points are bone heads or the extra points of :data:`RIG_POINTS`;
canonical points are joints or end sites (head_top, hands at the knuckles, toe tips)."""

HELD_AT_REST = ("left_collar", "right_collar")
"""Canonical joints whose rig bones keep their rest orientation relative to their parents,
whatever the mocap's: the clavicles stay as in the rig's rest (A) pose relative to the chest,
rising only with a raised arm (:data:`CLAVICLE_RISE`), and the arms' aims (from the shoulders)
still follow the mocap. A mocap collar's rotation
carries its skeleton's own idea of where the shoulder sits above the collar joint: every frame
of CMU subject 02 has its collars turned 14.6 / 13.3 degrees up from the canonical T-pose, and
aimed onto Anny's clavicles (which slope 8 degrees down) they shrugged both shoulders 21-23
degrees in every pose. With the arms hanging, that raised the tops of the shoulders into peaks
with a notch beside the neck, in Anny's own dual-quaternion meshes as in the learned model's
(bench/body_eval.py, pose set: worst edge stretch at the tops of the shoulders)."""

CLAVICLE_RISE = 0.3
"""Share of an upper arm's elevation above the horizontal that its held clavicle rises by (27
degrees with the arm straight up; scapulohumeral rhythm: the shoulder girdle takes about a third
of an arm's elevation). Without it, raised arms fold the tops of the shoulders (bench/body_eval.py
--pose-set, arms_up)."""

RIG_POINTS = {"head_top": "head", "toe_tip.L": "foot.L", "toe_tip.R": "foot.R"}
"""Rig points that are not joints -> the bone carrying them (found on the rest mesh)."""

CANONICAL_POINTS = JOINTS + END_SITES
_TEMPLATE = canonical_skeleton()
_TEMPLATE_POINTS = _TEMPLATE.rest_points(torch.float64)

FINGER_MAX_DEGREES = {1: (20.0, 35.0, 45.0), 2: (75.0, 95.0, 65.0), 3: (75.0, 95.0, 65.0),
                      4: (75.0, 95.0, 65.0), 5: (75.0, 95.0, 65.0)}
"""Largest flexion of each finger's three bones (finger<k>-1..3; 1 is the thumb) at curl 1."""


def _rotvec_matrix(rotvec: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation matrices of rotation vectors (..., 3) (axis x angle, radians)."""
    return rot.convert(rotvec, "rotvec", "matrix")


def retarget(world_rotations: torch.Tensor, canonical_rest: torch.Tensor, rig_rest: dict[str, torch.Tensor],
             names, parents, extra: torch.Tensor | None = None, held=HELD_AT_REST) -> torch.Tensor:
    """Canonical poses onto the rig: local rotations (P, J, 3, 3) float64 in the convention above.

    All tensors float64. world_rotations (P, 22, 3, 3): canonical joints' world rotations
    (identity = the canonical T-pose). canonical_rest (P, 27, 3): canonical rest points
    (:data:`CANONICAL_POINTS`, metres) of each pose's source skeleton. rig_rest: rest position
    (3,) (metres) of every rig joint and of the extra points of :data:`RIG_POINTS`. extra
    (P, J, 3, 3): local rotations of unmapped bones (fingers, eyes), identity when None. held:
    canonical joints whose bones keep their rest orientation (:data:`HELD_AT_REST`; () aims the
    collars too, for comparison).

    Rest alignment S_j (the rig's A-pose -> the mocap's T-pose): the root's is the identity (both
    face +Z); a mapped bone adds to its parent's the smallest turn taking its aim direction onto
    the canonical one; an unmapped bone, or one of :data:`HELD_AT_REST` (the clavicles), keeps
    its parent's. A mapped bone's world rotation is then
    G_c S_j (G_c: its canonical joint's), an unmapped one's its parent's times its extra rotation.
    """
    names, parents = list(names), list(parents)
    count = len(world_rotations)
    eye = torch.eye(3, dtype=torch.float64).expand(count, 3, 3)
    driver = {names.index(bone): JOINTS.index(joint) for joint, bone in CANONICAL_TO_RIG.items()
              if joint not in held}
    S = torch.empty(count, len(names), 3, 3, dtype=torch.float64)
    A = torch.empty(count, len(names), 3, 3, dtype=torch.float64)
    for j, p in enumerate(parents):
        S_parent = S[:, p] if p >= 0 else eye
        A_parent = A[:, p] if p >= 0 else eye
        if j not in driver:
            S[:, j] = S_parent
            A[:, j] = A_parent if extra is None else A_parent @ extra[:, j]
            held_joint = next((c for c, bone in CANONICAL_TO_RIG.items() if bone == names[j] and c in held), None)
            if held_joint is not None:
                A[:, j] = A_parent @ _clavicle_rise(held_joint, world_rotations, canonical_rest, A_parent, rig_rest,
                                                    names[j])
            continue
        joint = JOINTS[driver[j]]
        if joint in AIMS:
            rig_aim, canon_aim = AIMS[joint]
            a = S_parent @ (rig_rest[rig_aim] - rig_rest[names[j]])
            turn = rot.rotation_between(a, _canonical_aim(canonical_rest, joint, canon_aim))
            S[:, j] = rot.quat_to_matrix(turn) @ S_parent
        else:
            S[:, j] = S_parent
        A[:, j] = world_rotations[:, driver[j]] @ S[:, j]
    return local_rotations(A, parents)


def _clavicle_rise(collar: str, world_rotations: torch.Tensor, canonical_rest: torch.Tensor, A_parent: torch.Tensor,
                   rig_rest: dict[str, torch.Tensor], bone: str) -> torch.Tensor:
    """(P, 3, 3) the local rotation of a held clavicle: raised by :data:`CLAVICLE_RISE` times the
    mocap upper arm's elevation above the horizontal of the chest (A_parent (P, 3, 3): the
    chest's world rotations), about the axis that lifts the clavicle's outer end; identity with
    the arm at or below the horizontal."""
    shoulder = collar.replace("collar", "shoulder")
    arm = torch.einsum("pij,pj->pi", world_rotations[:, JOINTS.index(shoulder)],
                       _canonical_aim(canonical_rest, shoulder, shoulder.replace("shoulder", "elbow")))
    arm = torch.einsum("pji,pj->pi", A_parent, arm)                    # in the chest's rest axes (+Y up)
    elevation = torch.arcsin((arm[:, 1] / torch.linalg.norm(arm, dim=-1)).clamp(-1.0, 1.0))
    side = bone.split(".")[-1]
    outward = rig_rest[f"upperarm01.{side}"] - rig_rest[bone]
    axis = torch.linalg.cross(outward, outward.new_tensor([0.0, 1.0, 0.0]))
    axis = axis / torch.linalg.norm(axis)
    return _rotvec_matrix(axis * (CLAVICLE_RISE * elevation.clamp(min=0.0))[:, None])


def _canonical_aim(canonical_rest: torch.Tensor, joint: str, point: str) -> torch.Tensor:
    """(P, 3) rest vector from a canonical joint to a canonical point; the template's where a
    source skeleton puts both at one place (e.g. a neck joint on the chest's end)."""
    b = canonical_rest[:, CANONICAL_POINTS.index(point)] - canonical_rest[:, CANONICAL_POINTS.index(joint)]
    template = _TEMPLATE_POINTS[CANONICAL_POINTS.index(point)] - _TEMPLATE_POINTS[CANONICAL_POINTS.index(joint)]
    return torch.where(torch.linalg.norm(b, dim=-1, keepdim=True) > 1e-6, b, template)


def _angle(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(...,) angles in degrees between the vectors a and b (..., 3)."""
    cos = (a * b).sum(-1) / (torch.linalg.norm(a, dim=-1) * torch.linalg.norm(b, dim=-1))
    return torch.rad2deg(torch.arccos(cos.clamp(-1.0, 1.0)))


def _posed_rig_point(point: str, A: torch.Tensor, joints: torch.Tensor, rig_rest: dict[str, torch.Tensor],
                     names) -> torch.Tensor:
    names = list(names)
    if point in names:
        return joints[:, names.index(point)]
    bone = names.index(RIG_POINTS[point])
    return joints[:, bone] + torch.einsum("pij,j->pi", A[:, bone], rig_rest[point] - rig_rest[RIG_POINTS[point]])


def aim_errors(A: torch.Tensor, joints: torch.Tensor, rig_rest: dict[str, torch.Tensor], names,
               world_rotations: torch.Tensor, canonical_rest: torch.Tensor) -> dict[str, torch.Tensor]:
    """Per mapped canonical joint, the angle (degrees, (P,) float64) between the rig's posed aim direction
    (from its posed joints) and the mocap's (the canonical joint's world rotation applied to its
    rest aim vector): ~0 when the rest alignment and the kinematics are right.

    A (P, J, 3, 3), joints (P, J, 3) (metres), float64: the rig's posed world rotations and
    joints; world_rotations (P, 22, 3, 3), canonical_rest (P, 27, 3): as given to :func:`retarget`."""
    names = list(names)
    errors = {}
    for joint, (rig_aim, canon_aim) in AIMS.items():
        if joint in HELD_AT_REST:   # not aimed
            continue
        a = _posed_rig_point(rig_aim, A, joints, rig_rest, names) - joints[:, names.index(CANONICAL_TO_RIG[joint])]
        b = torch.einsum("pij,pj->pi", world_rotations[:, JOINTS.index(joint)],
                         _canonical_aim(canonical_rest, joint, canon_aim))
        errors[joint] = _angle(a, b)
    return errors


REACH = {f"{side}_{name}": (f"{start}.{s}", f"{end}.{s}", f"{side}_{canon_start}", f"{side}_{canon_end}")
         for side, s in (("left", "L"), ("right", "R"))
         for name, start, end, canon_start, canon_end in (("arm", "upperarm01", "finger3-1", "shoulder", "hand"),
                                                          ("leg", "upperleg01", "toe_tip", "hip", "toe"))}
"""Limbs compared by :func:`reach_errors`: name -> (rig start, rig end, canonical start, end)."""


def reach_errors(A: torch.Tensor, joints: torch.Tensor, rig_rest: dict[str, torch.Tensor], names,
                 canonical_posed: torch.Tensor) -> dict[str, torch.Tensor]:
    """An end-to-end check on whole limbs: the angle (degrees, (P,) float64) between the shoulder-to-
    knuckles (hip-to-toe-tip) direction of the posed rig and of the mocap's posed canonical
    skeleton. Not zero, since segment proportions differ between the bodies and the rig's toes
    do not bend, but a few degrees when poses transfer right. A, joints, rig_rest: as for
    :func:`aim_errors`; canonical_posed (P, 27, 3) float64, metres."""
    errors = {}
    for name, (start, end, canon_start, canon_end) in REACH.items():
        a = _posed_rig_point(end, A, joints, rig_rest, names) - _posed_rig_point(start, A, joints, rig_rest, names)
        b = canonical_posed[:, CANONICAL_POINTS.index(canon_end)] - canonical_posed[:, CANONICAL_POINTS.index(canon_start)]
        errors[name] = _angle(a, b)
    return errors


def hand_and_eye_rotations(rest_joints: torch.Tensor, names, finger_curl: torch.Tensor,
                           gaze: torch.Tensor) -> torch.Tensor:
    """Local rotations (P, J, 3, 3) float64 curling the fingers and turning the eyes, identity
    elsewhere.

    All float64: rest_joints (J, 3) (metres) of one shape; finger_curl (P, 2, 5) in [0, 1] per
    hand (left, right) and finger (thumb first), scaling :data:`FINGER_MAX_DEGREES`; gaze (P, 2)
    yaw, pitch in radians (both eyes). Flexion turns each finger bone about (bone direction x palm normal), so the tip
    moves to the palm side; the palm normal comes from the rest hand (wrist, index and little
    finger knuckles)."""
    names = list(names)
    index = {n: i for i, n in enumerate(names)}
    count = len(finger_curl)
    out = torch.eye(3, dtype=torch.float64).expand(count, len(names), 3, 3).clone()
    for h, s in enumerate(("L", "R")):
        if f"wrist.{s}" not in index:
            continue
        wrist = rest_joints[index[f"wrist.{s}"]]
        forward = rest_joints[index[f"finger3-1.{s}"]] - wrist
        across = rest_joints[index[f"finger2-1.{s}"]] - rest_joints[index[f"finger5-1.{s}"]]  # little -> index
        normal = torch.linalg.cross(forward, across) if s == "L" else torch.linalg.cross(across, forward)
        normal = normal / torch.linalg.norm(normal)
        for finger in range(1, 6):
            for k in range(1, 4):
                bone = index[f"finger{finger}-{k}.{s}"]
                if k < 3:
                    direction = rest_joints[index[f"finger{finger}-{k + 1}.{s}"]] - rest_joints[bone]
                else:
                    direction = rest_joints[bone] - rest_joints[index[f"finger{finger}-{k - 1}.{s}"]]
                axis = torch.linalg.cross(direction, normal)
                axis = axis / torch.linalg.norm(axis)
                angle = math.radians(FINGER_MAX_DEGREES[finger][k - 1]) * finger_curl[:, h, finger - 1]
                out[:, bone] = _rotvec_matrix(axis * angle[:, None])
    eyes = [index[n] for n in ("eye.L", "eye.R") if n in index]
    if eyes:
        yaw, pitch = (torch.zeros(len(gaze), 3, dtype=torch.float64) for _ in range(2))
        yaw[:, 1], pitch[:, 0] = gaze[:, 0], gaze[:, 1]
        turn = _rotvec_matrix(yaw) @ _rotvec_matrix(pitch)
        for e in eyes:
            out[:, e] = turn
    return out


def rig_points(rest_vertices: torch.Tensor, rest_joints: torch.Tensor, names) -> dict[str, torch.Tensor]:
    """(3,) points in metres by name (in the inputs' dtype, float64 for :func:`retarget`): the rest
    joints (J, 3) by `names`, plus the extra RIG_POINTS found on a full-resolution rest mesh
    (V, 3): the top of the head and each foot's toe tip (the most forward vertices of its side
    below the knees)."""
    names = list(names)
    points = {n: rest_joints[i] for i, n in enumerate(names)}
    points["head_top"] = rest_vertices[rest_vertices[:, 1].argmax()]
    knee = min(points["lowerleg01.L"][1], points["lowerleg01.R"][1])
    for s, sign in (("L", 1.0), ("R", -1.0)):
        side = rest_vertices[(rest_vertices[:, 0] * sign > 0) & (rest_vertices[:, 1] < knee)]
        points[f"toe_tip.{s}"] = side[torch.argsort(side[:, 2])[-5:]].mean(0)
    return points



# -- mocap poses ---------------------------------------------------------------------------------

@dataclass
class MocapPoses:
    """Poses drawn from mocap, on the canonical body, heading removed, pelvis at the origin.

    world_rotations (P, 22, 3, 3) float64; rest (P, 27, 3) and posed (P, 27, 3) float64 canonical
    points (CANONICAL_POINTS, metres); local (P, 22, 4) float64 wxyz canonical local rotations;
    clip (P,) file paths relative to the mocap root; frame (P,) int64 frame in its clip;
    subject (P,) subject ids."""

    world_rotations: torch.Tensor
    rest: torch.Tensor
    posed: torch.Tensor
    local: torch.Tensor
    clip: list[str]
    frame: torch.Tensor
    subject: list[str]


def remove_heading(world_rotations: torch.Tensor) -> torch.Tensor:
    """(P, 3, 3) float64 turns about +Y that bring each pose's root facing (its +Z) onto +Z, from
    world rotations (P, J, 3, 3) float64 (joint 0 the root)."""
    forward = world_rotations[:, 0, :, 2]
    yaw = torch.atan2(forward[:, 0], forward[:, 2])
    rotvec = torch.zeros(len(yaw), 3, dtype=torch.float64)
    rotvec[:, 1] = -yaw
    return _rotvec_matrix(rotvec)


def sample_mocap_poses(clips, count: int, rng: np.random.Generator, root: Path | None = None,
                       margin: float = 0.1) -> MocapPoses:
    """count frames drawn from clips (humotion.data Clip list): a clip with probability
    proportional to its length, then a frame uniformly in its middle (1 - 2 margin). rng is a
    numpy Generator so that a seed draws the same frames as the training data always has."""
    if not clips:
        raise ValueError("no mocap clips to draw poses from")
    frames = np.array([c.frames for c in clips], dtype=np.float64)
    choice = torch.from_numpy(rng.choice(len(clips), size=count, p=frames / frames.sum()))
    position = torch.from_numpy(rng.uniform(margin, 1.0 - margin, size=count))
    out = MocapPoses(torch.empty(count, len(JOINTS), 3, 3, dtype=torch.float64),
                     torch.empty(count, len(CANONICAL_POINTS), 3, dtype=torch.float64),
                     torch.empty(count, len(CANONICAL_POINTS), 3, dtype=torch.float64),
                     torch.empty(count, len(JOINTS), 4, dtype=torch.float64),
                     [str(clips[c].path.relative_to(root)) if root else str(clips[c].path) for c in choice.tolist()],
                     torch.zeros(count, dtype=torch.int64), [clips[c].subject for c in choice.tolist()])
    for c in torch.unique(choice).tolist():
        rows = torch.nonzero(choice == c)[:, 0]
        motion = clips[c].load()
        picks = (position[rows] * motion.num_frames).long().clamp(max=motion.num_frames - 1)
        out.frame[rows] = picks
        sub = replace(motion, rotations=motion.rotations[picks], root_positions=motion.root_positions[picks],
                      joint_offsets=None if motion.joint_offsets is None else motion.joint_offsets[picks])
        canon = to_canonical(sub)
        world, positions = (x.double() for x in canon.world())
        heading = remove_heading(world)
        world = heading[:, None] @ world
        points = torch.cat([positions, canon.end_site_positions().double()], dim=1) - positions[:, :1]
        out.world_rotations[rows] = world
        out.posed[rows] = torch.einsum("pij,pkj->pki", heading, points)
        local = canon.rotations.double().clone()
        local[:, 0] = rot.matrix_to_quat(world[:, 0])
        out.local[rows] = local
        out.rest[rows] = canon.skeleton.rest_points(torch.float64)
    return out


def sample_hand_and_gaze(rng: np.random.Generator, count: int, open_fraction: float = 0.3,
                         gaze_fraction: float = 0.5) -> tuple[torch.Tensor, torch.Tensor]:
    """Random finger curls (count, 2, 5) float64 in [0, 1] (a grip per hand plus per-finger
    jitter; an open hand with probability open_fraction) and gazes (count, 2) float64 radians
    (yaw within +-20 degrees, pitch within +-12 degrees, with probability gaze_fraction, else
    straight ahead). rng is a numpy Generator so that a seed draws what it always has."""
    grip = torch.from_numpy(rng.uniform(0.0, 1.0, size=(count, 2, 1))
                            * (rng.uniform(size=(count, 2, 1)) >= open_fraction))
    curl = (grip + torch.from_numpy(rng.normal(0.0, 0.15, size=(count, 2, 5))) * (grip > 0)).clamp(0.0, 1.0)
    gaze = torch.deg2rad(torch.from_numpy(rng.uniform([-20.0, -12.0], [20.0, 12.0], size=(count, 2))))
    gaze = gaze * torch.from_numpy(rng.uniform(size=(count, 1)) < gaze_fraction)
    return curl, gaze


def sample_expressions(rng: np.random.Generator, count: int, num_actions: int, fraction: float = 0.5,
                       max_active: int = 4) -> torch.Tensor:
    """(B, num_actions) float64 sparse facial-action activations, B = count: with probability
    fraction a mesh gets 1..max_active actions at strengths uniform in [0.3, 1], else all zeros
    (neutral). rng is a numpy Generator so that a seed draws what it always has."""
    out = torch.zeros(count, num_actions, dtype=torch.float64)
    for i in np.flatnonzero(rng.uniform(size=count) < fraction).tolist():
        active = torch.from_numpy(rng.choice(num_actions, size=rng.integers(1, max_active + 1), replace=False))
        out[i, active] = torch.from_numpy(rng.uniform(0.3, 1.0, size=len(active)))
    return out



def canonical_to_rig(canonical_rotations: torch.Tensor, rest_vertices: torch.Tensor, rest_joints: torch.Tensor, names,
                     parents, held=HELD_AT_REST) -> torch.Tensor:
    """Poses of humotion's 22-joint canonical body onto the rig of one body: local rotations
    (P, J, 3, 3) float64 in the convention of :mod:`humotion.body.skinning`.

    canonical_rotations (P, 22, 4) wxyz or (P, 22, 3, 3): canonical local rotations (identity =
    the canonical T-pose; the root's is the body's orientation), computed in float64;
    rest_vertices (V, 3), rest_joints (J, 3) float64, metres: the body's rest mesh and joints (any
    resolution). Fingers and eyes stay at rest; the canonical template's proportions define the
    aim directions (:func:`retarget`)."""
    from humotion.skeleton import forward_kinematics

    local = canonical_rotations.double()
    world = forward_kinematics(local, local.new_zeros(len(local), 3), _TEMPLATE.offsets, _TEMPLATE.parents)[0]
    canonical_rest = _TEMPLATE_POINTS.expand((len(local),) + _TEMPLATE_POINTS.shape)
    return retarget(world, canonical_rest, rig_points(rest_vertices, rest_joints, names), names, parents, held=held)

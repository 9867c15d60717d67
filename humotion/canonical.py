"""The canonical body skeleton that all of humotion's systems speak, and mappings onto it.

22 joints named as in the SMPL family (pelvis to head, wrists and feet) plus five end sites
(head top, hands at the knuckles, toe tips). Its rest pose is a T-pose facing +Z, Y up, left
side +X. :func:`canonical_skeleton` gives the template at a chosen height; :func:`to_canonical`
moves a motion from any humanoid rig onto it, keeping the source's bone lengths.

Which source joint is which canonical one: the retargeter's key-joint finder
(:func:`humotion.retarget.keyjoints.find_key_joints`: joint names, else the tree's shape, with the
same override files as `humotion retarget --overrides`), so every command that needs the canonical
body reads a rig as the retargeter does. The hand-made tables of the rigs in ../shared/data
(MAPPINGS) are no longer needed for that: the finder gives exactly them (tests check it); they
name a file's rig family in `humotion info` and can be forced with to_canonical(layout=...).

How a source maps: every canonical joint names the source joint whose world rotation drives it;
each canonical bone takes the source's rest vector between the two mapped points, turned into the
template's rest directions by a per-joint alignment (so a rig whose zero pose is not a T-pose,
like the 100-joint game rig, still lands in a T-pose). The alignment of the root is the yaw that
turns its hips to the template's (its facing); every other joint inherits its parent's alignment and
adds the smallest turn onto its own bone, so the same pose gives the same canonical rotations
whichever T-pose rig it came from (a rig whose zero pose is no T-pose keeps that difference). Mapped joint positions are then exact,
except where the source has extra rotating joints between two mapped ones (CMU's upper neck,
the game rig's second neck twist): :func:`mapping_error` measures that.
"""

from __future__ import annotations

import math

import torch

from humotion import rotations as rot
from humotion.motion import Motion
from humotion.skeleton import Skeleton, local_rotations

# name, parent, template rest position (metres, T-pose, height 1.70 m; proportions after
# Drillis & Contini as tabulated by Winter, Biomechanics and Motor Control of Human Movement).
_TEMPLATE = [
    ("pelvis", None, (0.0, 0.95, 0.0)),
    ("left_hip", "pelvis", (0.09, 0.88, 0.0)),
    ("right_hip", "pelvis", (-0.09, 0.88, 0.0)),
    ("spine1", "pelvis", (0.0, 1.05, 0.0)),
    ("left_knee", "left_hip", (0.09, 0.485, 0.0)),
    ("right_knee", "right_hip", (-0.09, 0.485, 0.0)),
    ("spine2", "spine1", (0.0, 1.17, 0.0)),
    ("left_ankle", "left_knee", (0.09, 0.07, 0.0)),
    ("right_ankle", "right_knee", (-0.09, 0.07, 0.0)),
    ("spine3", "spine2", (0.0, 1.30, 0.0)),
    ("left_foot", "left_ankle", (0.09, 0.02, 0.13)),
    ("right_foot", "right_ankle", (-0.09, 0.02, 0.13)),
    ("neck", "spine3", (0.0, 1.46, 0.0)),
    ("left_collar", "spine3", (0.03, 1.40, 0.0)),
    ("right_collar", "spine3", (-0.03, 1.40, 0.0)),
    ("head", "neck", (0.0, 1.54, 0.0)),
    ("left_shoulder", "left_collar", (0.17, 1.40, 0.0)),
    ("right_shoulder", "right_collar", (-0.17, 1.40, 0.0)),
    ("left_elbow", "left_shoulder", (0.49, 1.40, 0.0)),
    ("right_elbow", "right_shoulder", (-0.49, 1.40, 0.0)),
    ("left_wrist", "left_elbow", (0.74, 1.40, 0.0)),
    ("right_wrist", "right_elbow", (-0.74, 1.40, 0.0)),
]
_TEMPLATE_END_SITES = [
    ("head_top", "head", (0.0, 1.70, 0.0)),
    ("left_hand", "left_wrist", (0.83, 1.40, 0.0)),
    ("right_hand", "right_wrist", (-0.83, 1.40, 0.0)),
    ("left_toe", "left_foot", (0.09, 0.0, 0.20)),
    ("right_toe", "right_foot", (-0.09, 0.0, 0.20)),
]
TEMPLATE_HEIGHT = 1.70

JOINTS: tuple[str, ...] = tuple(name for name, _, _ in _TEMPLATE)
END_SITES: tuple[str, ...] = tuple(name for name, _, _ in _TEMPLATE_END_SITES)
PARENTS: tuple[int, ...] = tuple(-1 if p is None else JOINTS.index(p) for _, p, _ in _TEMPLATE)
END_SITE_PARENTS: tuple[int, ...] = tuple(JOINTS.index(p) for _, p, _ in _TEMPLATE_END_SITES)
_REST = torch.tensor([pos for _, _, pos in _TEMPLATE], dtype=torch.float64)
_REST_END = torch.tensor([pos for _, _, pos in _TEMPLATE_END_SITES], dtype=torch.float64)


def canonical_skeleton(height: float = TEMPLATE_HEIGHT) -> Skeleton:
    """The canonical skeleton in its T-pose, scaled to a standing height in metres."""
    s = height / TEMPLATE_HEIGHT
    offsets = torch.cat([_REST[:1], _REST[1:] - _REST[list(PARENTS[1:])]]) * s
    end_offsets = (_REST_END - _REST[list(END_SITE_PARENTS)]) * s
    return Skeleton(JOINTS, PARENTS, offsets, END_SITE_PARENTS, end_offsets, END_SITES)


def _sided(table: dict[str, str | None], left: str, right: str) -> dict[str, str | None]:
    """Expand 'left_*' entries written once with {s} into left and right entries."""
    out: dict[str, str | None] = {}
    for name, source in table.items():
        if name.startswith("{side}_"):
            for side, mark in (("left", left), ("right", right)):
                out[name.replace("{side}", side)] = None if source is None else source.format(s=mark)
        else:
            out[name] = source
    return out


# The known rigs: canonical joint or end site -> source joint (or end-site) name; None: no such
# point in the source (the template's offset is used, scaled to the source's size).
MAPPINGS: dict[str, dict[str, str | None]] = {
    # CMU ASF (31 joints; a joint sits at the start of its bone) and the 38-joint exp-map set.
    "cmu_asf": _sided({
        "pelvis": "root", "{side}_hip": "{s}femur", "{side}_knee": "{s}tibia", "{side}_ankle": "{s}foot",
        "{side}_foot": "{s}toes", "{side}_toe": "{s}toes_end", "spine1": "lowerback", "spine2": "upperback",
        "spine3": "thorax", "neck": "lowerneck", "head": "head", "head_top": "head_end",
        "{side}_collar": "{s}clavicle", "{side}_shoulder": "{s}humerus", "{side}_elbow": "{s}radius",
        "{side}_wrist": "{s}wrist", "{side}_hand": "{s}fingers",
    }, "l", "r"),
    # CMU in the cgspeed BVH release (31 joints, thorax dropped).
    "cmu_bvh": _sided({
        "pelvis": "Hips", "{side}_hip": "{s}UpLeg", "{side}_knee": "{s}Leg", "{side}_ankle": "{s}Foot",
        "{side}_foot": "{s}ToeBase", "{side}_toe": "{s}ToeBase_end", "spine1": "LowerBack", "spine2": "Spine",
        "spine3": "Spine1", "neck": "Neck", "head": "Head", "head_top": "Head_end",
        "{side}_collar": "{s}Shoulder", "{side}_shoulder": "{s}Arm", "{side}_elbow": "{s}ForeArm",
        "{side}_wrist": "{s}Hand",
    }, "Left", "Right") | {"left_hand": "LFingers", "right_hand": "RFingers"},
    # Reallusion Character Creator rig (CC_Base_*, 100 joints with fingers and twist bones).
    "cc_base": _sided({
        "pelvis": "CC_Base_Hip", "{side}_hip": "CC_Base_{s}_Thigh", "{side}_knee": "CC_Base_{s}_Calf",
        "{side}_ankle": "CC_Base_{s}_Foot", "{side}_foot": "CC_Base_{s}_ToeBase", "{side}_toe": "CC_Base_{s}_MidToe1",
        "spine1": "CC_Base_Waist", "spine2": "CC_Base_Spine01", "spine3": "CC_Base_Spine02",
        "neck": "CC_Base_NeckTwist01", "head": "CC_Base_Head", "head_top": None,
        "{side}_collar": "CC_Base_{s}_Clavicle", "{side}_shoulder": "CC_Base_{s}_Upperarm",
        "{side}_elbow": "CC_Base_{s}_Forearm", "{side}_wrist": "CC_Base_{s}_Hand", "{side}_hand": "CC_Base_{s}_Mid1",
    }, "L", "R"),
    # DAZ-style BVH (the CMU salsa release: hip, abdomen, chest, lCollar, lShldr, ...).
    "daz": _sided({
        "pelvis": "hip", "{side}_hip": "{s}Thigh", "{side}_knee": "{s}Shin", "{side}_ankle": "{s}Foot",
        "{side}_foot": "{s}Foot_end", "{side}_toe": None, "spine1": "abdomen", "spine2": "chest",
        "spine3": "chest", "neck": "neck", "head": "head", "head_top": None,
        "{side}_collar": "{s}Collar", "{side}_shoulder": "{s}Shldr", "{side}_elbow": "{s}ForeArm",
        "{side}_wrist": "{s}Hand", "{side}_hand": "{s}Mid1",
    }, "l", "r"),
    "canonical": {name: name for name in JOINTS + END_SITES},
    # The canonical body read back from BVH, which names end sites after their parent joints.
    "canonical_bvh": {name: name for name in JOINTS}
    | {end: f"{JOINTS[parent]}_end" for end, parent in zip(END_SITES, END_SITE_PARENTS)},
}


def detect_layout(skeleton: Skeleton) -> str:
    """Name of the known rig in MAPPINGS whose source joints all exist in the skeleton (of several,
    the first whose source end sites exist too); ValueError for any other rig (which
    :func:`to_canonical` maps all the same)."""
    points = set(skeleton.names) | set(skeleton.end_site_names)
    layouts = [layout for layout, table in MAPPINGS.items()
               if all(src in points for name, src in table.items() if name in JOINTS and src is not None)]
    if layouts:
        return next((layout for layout in layouts if all(src in points for src in MAPPINGS[layout].values() if src)),
                    layouts[0])
    raise ValueError(
        "cannot map this skeleton onto the canonical body: its joint names match none of the known rigs "
        f"({', '.join(MAPPINGS)}); joints: {', '.join(skeleton.names[:12])}{' ...' if skeleton.num_joints > 12 else ''}"
    )


def _source_points(skeleton: Skeleton, table: dict[str, str | None]):
    """Per canonical joint, the driving source joint, and a function giving a mapped point's
    rest position (3,) float64 in metres (None for a point the table leaves out)."""
    rest = skeleton.rest_positions(torch.float64)
    rest_end = skeleton.rest_end_site_positions(torch.float64)

    def driving_joint(src: str) -> int:
        # A canonical joint mapped onto an end site turns with that end site's parent.
        if src in skeleton.names:
            return skeleton.index(src)
        return skeleton.end_site_parents[skeleton.end_site_names.index(src)]

    driver = [driving_joint(table[name]) for name in JOINTS]

    def position(name: str) -> torch.Tensor | None:
        src = table.get(name)
        if src is None:
            return None
        if src in skeleton.names:
            return rest[skeleton.index(src)]
        return rest_end[skeleton.end_site_names.index(src)]

    return driver, position


def rest_alignments(skeleton: Skeleton, table: dict[str, str | None]) -> tuple[torch.Tensor, ...]:
    """Per canonical joint: the driving source joint (22,) int64, the alignment rotation
    (22, 3, 3) float64 taking template directions to the source's rest directions, and the
    canonical offsets (22, 3) and end-site offsets (5, 3), float32 metres."""
    driver, position = _source_points(skeleton, table)
    joint_vectors = [None if p < 0 else position(JOINTS[j]) - position(JOINTS[p]) for j, p in enumerate(PARENTS)]
    end_vectors = []
    for name, p in zip(END_SITES, END_SITE_PARENTS):
        point = position(name)
        end_vectors.append(None if point is None else point - position(JOINTS[p]))

    template = canonical_skeleton()
    template_offsets, template_ends = template.offsets.double(), template.end_site_offsets.double()
    align = torch.eye(3, dtype=torch.float64).repeat(len(JOINTS), 1, 1)
    for j in range(len(JOINTS)):
        pairs = [(template_offsets[c], joint_vectors[c]) for c in range(len(JOINTS)) if PARENTS[c] == j]
        pairs += [(template_ends[e], end_vectors[e]) for e, p in enumerate(END_SITE_PARENTS) if p == j and end_vectors[e] is not None]
        pairs = [(a / a.norm(), b / b.norm(), b.norm()) for a, b in pairs if b.norm() > 1e-6]
        inherited = align[PARENTS[j]] if PARENTS[j] >= 0 else torch.eye(3, dtype=torch.float64)
        if PARENTS[j] < 0:
            # The root's facing: the yaw that turns the template's hip-to-hip (left) direction
            # onto the source's, about the vertical, so an upright rig keeps an upright pelvis
            # (shoulder to shoulder for a rig without legs).
            side = joint_vectors[JOINTS.index("left_hip")] - joint_vectors[JOINTS.index("right_hip")]
            if side.norm() < 1e-6:
                side = position("left_shoulder") - position("right_shoulder")
            yaw = math.atan2(-side[2], side[0])
            align[j] = rot.convert(torch.tensor([0.0, yaw, 0.0], dtype=torch.float64), "rotvec", "matrix")
        elif pairs:
            # Every other joint keeps its parent's frame (so no twist appears from nowhere) and
            # adds the smallest turn taking its mean child direction onto the source's.
            a = inherited @ sum(w * a for a, _, w in pairs)
            b = sum(w * b for _, b, w in pairs)
            align[j] = turn_between(a, b, inherited[:, 2]) @ inherited
        else:
            align[j] = inherited

    scale = skeleton.height() / TEMPLATE_HEIGHT
    offsets = torch.zeros(len(JOINTS), 3, dtype=torch.float64)
    offsets[0] = position(JOINTS[0])
    for j, p in enumerate(PARENTS):
        if p >= 0:
            offsets[j] = align[p].T @ joint_vectors[j]
    end_offsets = torch.stack([
        template_ends[e] * scale if v is None else align[p].T @ v
        for e, (v, p) in enumerate(zip(end_vectors, END_SITE_PARENTS))
    ])
    return torch.tensor(driver), align, offsets.float(), end_offsets.float()


def turn_between(a: torch.Tensor, b: torch.Tensor, forward: torch.Tensor) -> torch.Tensor:
    """(3, 3) smallest rotation taking direction a (3,) onto b (3,), in their dtype (float64 for
    the rest alignments). When they are (nearly) opposite that rotation's axis is arbitrary, so
    it turns half way about the body's forward axis (3,) first: the choice that makes the game
    rig (whose zero pose points the legs up) agree with CMU on the rotations of the same takes."""
    a, b = a / a.norm(), b / b.norm()
    if a @ b > -0.98:
        return rot.rotation_matrix_between(a, b)
    axis = forward - (forward @ a) * a
    half = rot.convert(axis / axis.norm() * math.pi, "rotvec", "matrix")
    return rot.rotation_matrix_between(half @ a, b) @ half


def key_points(skeleton: Skeleton, layout: str | None = None, overrides: dict | None = None,
               label: str = "") -> dict[str, str | None]:
    """Canonical joint or end site -> the skeleton's joint (or end-site) name.

    layout: a key of MAPPINGS, taken as it is. Otherwise the retargeter's key-joint finder, with
    overrides as humotion.retarget.Rig.of takes them ({"joints": key point -> joint name, ...},
    what humotion.retarget.parts.load_overrides reads from an override file). Raises
    humotion.retarget.MissingKeyJoints (a ValueError) naming what cannot be found; label names
    the rig (a file) there.
    """
    if layout:
        return MAPPINGS[layout]
    from humotion.retarget.keyjoints import find_key_joints  # (keyjoints builds on this module)

    return find_key_joints(skeleton, (overrides or {}).get("joints"), label)


def to_canonical(motion: Motion, layout: str | None = None, overrides: dict | None = None) -> Motion:
    """The motion on the canonical skeleton (same frames and fps, source bone lengths).

    layout, overrides: how the source's key joints are found (:func:`key_points`: by default the
    retargeter's finder). A rig without legs gets legs of no length at the pelvis.
    """
    table = key_points(motion.skeleton, layout, overrides, motion.name)
    driver, align, offsets, end_offsets = rest_alignments(motion.skeleton, table)
    world_rot, world_pos = motion.world()
    canon_world = world_rot[:, driver] @ align.to(world_rot.dtype)        # (T, 22, 3, 3)
    skeleton = Skeleton(JOINTS, PARENTS, offsets, END_SITE_PARENTS, end_offsets, END_SITES)
    return Motion(skeleton, rot.matrix_to_quat(local_rotations(canon_world, PARENTS)), world_pos[:, driver[0]],
                  motion.fps, name=motion.name)


def mapping_error(motion: Motion, layout: str | None = None, overrides: dict | None = None) -> dict[str, float]:
    """Largest distance (metres, over frames) between each canonical joint and its source joint."""
    table = key_points(motion.skeleton, layout, overrides, motion.name)
    canon = to_canonical(motion, layout, overrides).world_positions()
    source = motion.world_positions()
    source = torch.cat([source, motion.end_site_positions()], dim=1)
    points = list(motion.skeleton.names) + list(motion.skeleton.end_site_names)
    return {name: float((canon[:, j] - source[:, points.index(table[name])]).norm(dim=-1).max())
            for j, name in enumerate(JOINTS)}

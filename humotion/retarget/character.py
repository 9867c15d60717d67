"""A motion onto a rigged character (glTF, VRM, FBX: humotion.io.character), for the commands
that write the animated character directly (retarget --to, capture/track --character).

    from humotion.retarget.character import animate_character
    result, character = animate_character(motion, "hero.vrm", "hero_walk.vrm")
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from humotion.io.character import Character, posed_mesh, read_character, write_character
from humotion.motion import Motion
from humotion import rotations as rot
from humotion.retarget.classical import FOOT_POINTS, reach, retarget
from humotion.retarget.contacts import foot_contacts
from humotion.retarget.rig import Rig
from humotion.skeleton import Skeleton, forward_kinematics


def character_rig(character: Character, overrides: dict | None = None) -> Rig:
    """The character's Rig: its skeleton with the override table given, else the one its file
    carries (a VRM's humanoid map), else none. A foot whose toe joint lies under the ankle
    rather than in front of it (CesiumMan) would be aligned as a foot pointing down: such a foot
    gets a sole point instead as its toes key point (the toe joint then moves with the ankle),
    an end site at the toe joint's height and in front of the ankle by 2.2 times that drop, the
    slope of a typical foot from ankle to toes (about 24 degrees). A foot with no toe joint (its
    toes key point an end site) gets the tip of its mesh's sole instead (_toe_tip): a big foot
    (RobotExpressive's reaches 0.84 m in front of its ankle, its end site 0.33 m) is then turned
    as a whole, so its front does not dip through the floor when the source's toes point down."""
    overrides = overrides or character.overrides
    label = str(character.path)
    rig = Rig.of(character.skeleton, overrides, label=label)
    skeleton = rig.skeleton
    rest = dict(zip(skeleton.names + skeleton.end_site_names, skeleton.rest_points(torch.float64)))
    soles, mesh = {}, None
    for side in ("left", "right"):
        ankle, toes = rig.key_joints[f"{side}_ankle"], rig.key_joints.get(f"{side}_foot")
        if ankle is None or toes is None or toes == ankle:
            continue
        bone = rest[toes] - rest[ankle]
        ahead = float(torch.hypot(bone[0], bone[2]))
        if abs(bone[1]) > ahead > 1e-9:                               # steeper than 45 degrees
            sole = bone * 2.2 * abs(bone[1]) / ahead
            sole[1] = bone[1]
            soles[f"{side}_foot"] = (ankle, sole)
        elif toes in skeleton.end_site_names and ahead > 1e-9 and character.num_meshes:
            if mesh is None:
                mesh = torch.from_numpy(posed_mesh(character, Motion.rest(character.skeleton))[0][0]).double()
            other = rest[rig.key_joints["right_ankle" if side == "left" else "left_ankle"]]
            tip = _toe_tip(mesh, rest[ankle], rest[rig.key_joints[f"{side}_knee"]], other, bone / ahead)
            if tip is not None:
                soles[f"{side}_foot"] = (ankle, tip - rest[ankle])
    if not soles:
        return rig
    names = [f"{ankle}_sole" for ankle, _ in soles.values()]
    skeleton = Skeleton(skeleton.names, skeleton.parents, skeleton.offsets,
                        skeleton.end_site_parents + tuple(skeleton.index(a) for a, _ in soles.values()),
                        torch.cat([skeleton.end_site_offsets, torch.stack([o for _, o in soles.values()]).float()]),
                        skeleton.end_site_names + tuple(names))
    joints = dict((overrides or {}).get("joints", {})) | dict(zip(soles, names))
    return Rig.of(skeleton, {**(overrides or {}), "joints": joints}, label=label)


def _toe_tip(vertices: torch.Tensor, ankle: torch.Tensor, knee: torch.Tensor, other: torch.Tensor,
             forward: torch.Tensor) -> torch.Tensor | None:
    """The tip of a foot's sole in the rest pose (3,), scene units: its mesh's frontmost point
    along forward (3,) (the horizontal ankle-to-toes direction), at the ankle's side and the
    sole's height. The foot's vertices are those of vertices (V, 3) nearer this ankle than the
    other, horizontally, and below a quarter of the way up to the knee. None when there are none
    in front of the ankle. Points and vertices float64."""
    forward = forward.clone()
    forward[1] = 0.0
    flat = vertices[:, [0, 2]]
    foot = vertices[((flat - ankle[[0, 2]]).norm(dim=1) < (flat - other[[0, 2]]).norm(dim=1))
                    & (vertices[:, 1] < ankle[1] + 0.25 * (knee[1] - ankle[1]))]
    front = (foot - ankle) @ forward
    if not (front > 0).any():
        return None
    tip = ankle + forward * front.max()
    tip[1] = foot[:, 1].min()
    return tip


def onto_character(motion: Motion, character: Character, *, rig: Rig | None = None, source_rig: Rig | None = None,
                   feet: bool = True, progress: bool | None = None) -> Motion:
    """The motion retargeted (classical) onto the character's skeleton and put on the floor of
    its bind pose (on_floor). Raises MissingKeyJoints for a rig
    whose key joints are not found."""
    rig = rig or character_rig(character)
    return on_floor(retarget(motion, rig, source_rig=source_rig, feet=feet, progress=progress), character, rig, feet)


FEET = ("left_ankle", "right_ankle", "left_foot", "right_foot", "left_toe", "right_toe")


def stand_on_floor(motion: Motion, rig: Rig, character: Character, frames: int = 120) -> Motion:
    """The motion moved up or down so its planted soles rest on the floor of the character's bind
    pose. Planted frames: those where a foot point (ankles, toes, toe tips: Rig.key_joints) is
    low and slow as the retargeter's contacts define them (humotion.retarget.contacts); the 10%
    of frames where the feet are lowest for a clip with none. The median over (at most frames,
    evenly spaced, of) those of the posed mesh's lowest vertex comes to the bind pose's lowest
    vertex, so the sole, not the ankle joint, meets the floor whatever the foot's shape; a
    character with no mesh has its lowest foot point meet the bind pose's instead. rig:
    humotion.retarget.Rig of motion.skeleton (character.skeleton). A rig whose root is no key
    joint (a ground bone) keeps working: only the root's height changes."""
    keys = [k for k in FEET if rig.key_joints.get(k)]
    if not keys:
        return motion
    world, positions = motion.world()
    points = rig.points(world.double(), positions.double(), keys)                 # (T, K, 3)
    planted = foot_contacts(points, motion.fps, rig.standing_height()).any(1)
    lowest = points[..., 1].min(1).values
    chosen = planted.nonzero()[:, 0] if planted.any() else lowest.argsort()[:max(1, len(lowest) // 10)]
    chosen = chosen[torch.linspace(0, len(chosen) - 1, min(frames, len(chosen))).round().long()]
    skeleton = motion.skeleton
    if character.num_meshes:
        offsets = motion.joint_offsets[chosen] if motion.joint_offsets is not None else None
        clip = Motion(skeleton, motion.rotations[chosen], motion.root_positions[chosen], motion.fps, offsets)
        posed = torch.from_numpy(posed_mesh(character, clip)[0])                      # (K, V, 3)
        bind = torch.from_numpy(posed_mesh(character, Motion.rest(skeleton))[0][0])  # (V, 3)
        shift = bind[:, 1].min() - posed[..., 1].amin(1).quantile(0.5)
    else:
        rest = dict(zip(skeleton.names + skeleton.end_site_names,
                        skeleton.rest_points(torch.float64)[:, 1].tolist()))
        shift = min(rest[rig.key_joints[k]] for k in keys) - float(lowest[chosen].median())
    root = motion.root_positions.clone()
    root[:, 1] += float(shift)
    return Motion(skeleton, motion.rotations, root, motion.fps, motion.joint_offsets, name=motion.name)


def on_floor(motion: Motion, character: Character, rig: Rig, feet: bool = True) -> Motion:
    """A motion on the character's skeleton (rig: its Rig) with its planted soles on the floor of
    the bind pose (stand_on_floor by the posed mesh) and, with feet, its
    toes kept above that floor (toes_above_floor)."""
    motion = stand_on_floor(motion, rig, character)
    return toes_above_floor(motion, rig) if feet and rig.legs else motion


def toes_above_floor(motion: Motion, rig: Rig) -> Motion:
    """The motion with each foot's toes key point kept above the rest pose's floor (its lowest
    foot key point): on a frame where the toes are lower, the leg (two-bone IK) lifts the ankle
    by as much, the foot keeping its rotation. A long foot turned toes down (RobotExpressive's
    reaches 0.84 m in front of its ankle, on a 1.34 m leg) would otherwise push through the floor."""
    skeleton = motion.skeleton
    rest_world, rest_positions = (x.double() for x in Motion.rest(skeleton).world())
    floor = float(rig.points(rest_world, rest_positions, FOOT_POINTS)[0, :, 1].min())
    local = rot.quat_to_matrix(motion.rotations.double())
    root = motion.root_positions.double()
    for s, side in enumerate(("left", "right")):
        world, positions = forward_kinematics(local, root, skeleton.offsets, skeleton.parents)
        ankle, toes = rig.points(world, positions, FOOT_POINTS[2 * s:2 * s + 2]).unbind(1)
        below = (floor - toes[:, 1]).clamp_min(0.0)
        wanted = torch.where((below > 0)[:, None], ankle + below[:, None] * torch.tensor([0.0, 1.0, 0.0],
                                                                                       dtype=ankle.dtype), torch.nan)
        local = reach(local, root, rig, side, wanted, arm=False)
    return Motion(skeleton, rot.matrix_to_quat(local).float(), motion.root_positions, motion.fps,
                  motion.joint_offsets, name=motion.name)


def animate_character(motion: Motion, character: str | Path | Character, out: str | Path,
                      name: str | None = None) -> tuple[Motion, Character]:
    """Retarget motion onto the character file and write it, animated, to out (.glb, .gltf,
    .vrm; .fbx with humotion[fbx]). Returns the motion on the character's skeleton and the
    character read."""
    if not isinstance(character, Character):
        character = read_character(character)
    result = onto_character(motion, character)
    write_character(character, result, out, name)
    return result, character


def viewer_mesh(character: Character, motion: Motion) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (T, V, 3), faces (faces, 3)) of the character posed by a motion on its skeleton,
    for humotion.viewer.MotionViewer's meshes."""
    return posed_mesh(character, motion)


__all__ = ["character_rig", "onto_character", "on_floor", "toes_above_floor", "animate_character", "viewer_mesh"]

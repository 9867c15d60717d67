"""A motion onto a rigged character (glTF, VRM, FBX: humotion.io.character), for the commands
that write the animated character directly (retarget --to, capture/track --character).

    from humotion.retarget.character import animate_character
    result, character = animate_character(motion, "hero.vrm", "hero_walk.vrm")
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from humotion.io.character import Character, posed_mesh, read_character, stand_on_floor, write_character
from humotion.motion import Motion
from humotion.retarget.classical import retarget
from humotion.retarget.rig import Rig
from humotion.skeleton import Skeleton


def character_rig(character: Character, overrides: dict | None = None) -> Rig:
    """The character's Rig: its skeleton with the override table given, else the one its file
    carries (a VRM's humanoid map), else none. A foot whose toe joint lies under the ankle
    rather than in front of it (CesiumMan) would be aligned as a foot pointing down: such a foot
    gets a sole point instead as its toes key point (the toe joint then moves with the ankle),
    an end site at the toe joint's height and in front of the ankle by 2.2 times that drop, the
    slope of a typical foot from ankle to toes (about 24 degrees)."""
    overrides = overrides or character.overrides
    label = str(character.path)
    rig = Rig.of(character.skeleton, overrides, label=label)
    skeleton = rig.skeleton
    rest = dict(zip(skeleton.names + skeleton.end_site_names,
                    np.concatenate([skeleton.rest_positions(), skeleton.rest_end_site_positions()])))
    soles = {}
    for side in ("left", "right"):
        ankle, toes = rig.key_joints[f"{side}_ankle"], rig.key_joints.get(f"{side}_foot")
        if ankle is None or toes is None or toes == ankle:
            continue
        bone = rest[toes] - rest[ankle]
        ahead = np.hypot(bone[0], bone[2])
        if abs(bone[1]) > ahead > 1e-9:                               # steeper than 45 degrees
            soles[f"{side}_foot"] = (ankle, np.array([bone[0], 0.0, bone[2]]) * 2.2 * abs(bone[1]) / ahead
                                     + [0.0, bone[1], 0.0])
    if not soles:
        return rig
    names = [f"{ankle}_sole" for ankle, _ in soles.values()]
    skeleton = Skeleton(skeleton.names, skeleton.parents, skeleton.offsets,
                        skeleton.end_site_parents + tuple(skeleton.index(a) for a, _ in soles.values()),
                        np.concatenate([skeleton.end_site_offsets, [o for _, o in soles.values()]]),
                        skeleton.end_site_names + tuple(names))
    joints = dict((overrides or {}).get("joints", {})) | dict(zip(soles, names))
    return Rig.of(skeleton, {**(overrides or {}), "joints": joints}, label=label)


def onto_character(motion: Motion, character: Character, *, rig: Rig | None = None, source_rig: Rig | None = None,
                   feet: bool = True, progress: bool | None = None) -> Motion:
    """The motion retargeted (classical) onto the character's skeleton and stood on the floor of
    its bind pose (humotion.io.character.stand_on_floor). Raises MissingKeyJoints for a rig
    whose key joints are not found."""
    rig = rig or character_rig(character)
    return stand_on_floor(retarget(motion, rig, source_rig=source_rig, feet=feet, progress=progress), rig)


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
    """(vertices (F, V, 3), faces (T, 3)) of the character posed by a motion on its skeleton,
    for humotion.viewer.MotionViewer's meshes."""
    return posed_mesh(character, motion)


__all__ = ["character_rig", "onto_character", "animate_character", "viewer_mesh"]

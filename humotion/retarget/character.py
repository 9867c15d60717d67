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


def character_rig(character: Character, overrides: dict | None = None) -> Rig:
    """The character's Rig: its skeleton with the override table given, else the one its file
    carries (a VRM's humanoid map), else none."""
    return Rig.of(character.skeleton, overrides or character.overrides, label=str(character.path))


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

"""FBX characters through Blender (humotion[fbx]): Adventurer.gltf converted to FBX by Blender's
own exporter stands in for a Mixamo/engine FBX (no FBX character with a quotable licence is
shared). `retarget --to hero.fbx` reads it with no override file and writes the character with
the motion as FBX and as glTF; both play the clip for its duration with the feet where the glTF
route puts them. Skipped without bpy; without it, .fbx is a one-line error (test_character)."""

from __future__ import annotations


import numpy as np
import pytest
from click.testing import CliRunner

from humotion.assets import demo_clip_path
from humotion.cli import main
from humotion.io import load_motion
from humotion.io.character import _blender_convert, read_character
from humotion.io.gltf import read_gltf_animation

from test_character import character_path

pytest.importorskip("bpy", reason="humotion[fbx] (Blender's bpy) is not installed")


def feet(motion, names=("Foot.L", "Foot.R")) -> np.ndarray:
    return motion.world_positions().numpy()[:, [motion.skeleton.index(n) for n in names]]


def test_fbx_character_in_and_out(tmp_path):
    hero = tmp_path / "hero.fbx"
    _blender_convert(character_path("Adventurer.gltf"), hero)
    character = read_character(hero)
    assert character.kind == "FBX" and character.skeleton.num_joints == 62

    runner = CliRunner()
    clip = load_motion(demo_clip_path())
    glb, fbx = tmp_path / "hero_punch.glb", tmp_path / "hero_punch.fbx"
    for out in (glb, fbx):
        result = runner.invoke(main, ["retarget", str(demo_clip_path()), "--to", str(hero), "-o", str(out)])
        assert result.exit_code == 0, result.output
        assert "Blender" not in result.output and len(result.output.splitlines()) == 2   # Blender's prints kept out

    played = read_gltf_animation(glb, animation=0)
    assert played.num_frames == clip.num_frames and played.fps == clip.fps
    assert len(read_character(glb).gltf.meshes) == character.num_meshes

    back = tmp_path / "back.glb"                      # the FBX written, read back through Blender
    _blender_convert(fbx, back)
    replayed = read_gltf_animation(back, animation=0, fps=clip.fps)
    assert abs(replayed.duration - played.duration) < 0.05
    frames = min(len(replayed), len(played))
    assert np.abs(feet(replayed)[:frames] - feet(played)[:frames]).max() < 0.02     # metres

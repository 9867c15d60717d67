"""The character route of retargeting (humotion retarget SRC --to character.glb|.vrm): rows for
bench/retarget_eval.py, runnable alone.

    .venv/bin/python bench/retarget_characters.py [--data ../shared/data] [--takes 5]

Sources: CMU subject 02's first takes (cmu_mocgui_s02, ASF/AMC, 120 Hz, resampled to 60 Hz).
Targets: the shared characters (data/characters: CesiumMan, Adventurer, Soldier, debug_robot.vrm,
RobotExpressive), each with no override file.
Columns:
- err rel / err glob: the character route against the BVH route, i.e. the same source
  retargeted onto the character's skeleton written as a BVH rig and read back as one (no
  humanoid map, no floor); key-joint positions of the glTF the character route wrote (read back
  by humotion.io.gltf) against the BVH route's, squared error / height^2 x 1000 as in
  retarget_eval ("rel": pelvis subtracted; "glob": with the root, so the floor the character
  route stands the result on counts).
- feet cm: lowest foot key point (ankles, toes, toe tips) above the bind pose's, median and 95th
  percentile of |difference| over frames, in cm of a 1.7 m person (units scaled by height).
- mesh cm: the lowest vertex of the posed mesh (humotion.io.character.posed_mesh) against the
  rest pose's lowest vertex, signed (below the floor is negative), same units: its median over
  frames, over the frames where a foot is planted (low and slow: humotion.retarget.contacts, on
  the source's ankles and toes), and its minimum (the deepest a foot goes through the floor).
- s/min: seconds to retarget one minute of motion (60 Hz) onto the character and write the
  file, one thread (reading the character not counted: it is done once).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from humotion.canonical import JOINTS
from humotion.io import load_motion, save_motion
from humotion.io.character import posed_mesh, read_character, write_character
from humotion.io.gltf import read_gltf_animation
from humotion.motion import Motion
from humotion.retarget import MissingKeyJoints, Rig, retarget
from humotion.retarget.contacts import foot_contacts
from humotion.retarget.character import FEET, character_rig, onto_character

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
CHARACTERS = ("CesiumMan.glb", "Adventurer.gltf", "Soldier.gltf", "debug_robot.vrm", "RobotExpressive.glb")


def key_points(names: list[str], motion: Motion) -> torch.Tensor:
    """(F, K, 3) world positions of the named joints of a motion."""
    return motion.world_positions().double()[:, [motion.skeleton.index(n) for n in names]]


def errors(rig: Rig, got: Motion, want: Motion) -> tuple[float, float]:
    """Over the key joints that are joints (not end sites) of the rig, pelvis first."""
    names = [rig.key_joints[k] for k in JOINTS if rig.key_joints[k] in rig.skeleton.names]
    a, b = key_points(names, got), key_points(names, want)
    height2 = rig.standing_height() ** 2
    glob = ((a - b) ** 2).sum(-1)[:, 1:].mean() / height2
    rel = (((a - a[:, :1]) - (b - b[:, :1])) ** 2).sum(-1)[:, 1:].mean() / height2
    return 1000 * float(rel), 1000 * float(glob)


def floor_gaps(rig: Rig, motion: Motion) -> np.ndarray:
    """(F,) lowest foot point above the rest pose's, in the motion's units (motion on the rig)."""
    keys = [k for k in FEET if rig.key_joints.get(k)]
    world, positions = (x.double() for x in motion.world())
    low = rig.points(world, positions, keys)[..., 1].min(1).values.numpy()
    rest_world, rest_positions = (x.double() for x in Motion.rest(motion.skeleton).world())
    return low - rig.points(rest_world, rest_positions, keys)[..., 1].min().item()


def concatenated(motions: list[Motion], frames: int) -> Motion:
    parts, total = [], 0
    while total < frames:
        for m in motions:
            parts.append(m)
            total += len(m)
    return Motion(motions[0].skeleton, torch.cat([m.rotations for m in parts])[:frames],
                  torch.cat([m.root_positions for m in parts])[:frames], motions[0].fps)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--takes", type=int, default=5)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    folder = args.data / "mocap" / "cmu_mocgui_s02"
    sources = [load_motion(p).resample(60.0) for p in sorted(folder.glob("02_*.amc"))[: args.takes]]
    minute = concatenated(sources, 3600)
    frames = sum(len(s) for s in sources)
    print(f"character route: {len(sources)} takes of CMU subject 02 ({frames} frames at 60 Hz) onto each character, "
          "no override file")
    planted, source_gaps = [], []
    for source in sources:
        rig = Rig.of(source.skeleton)
        world, positions = (x.double() for x in source.world())
        planted.append(foot_contacts(rig.points(world, positions, FEET[:4]), source.fps,
                                     rig.standing_height()).any(1).numpy())
        gaps = floor_gaps(rig, source)                     # its floor: where its planted frames put it
        source_gaps.append((gaps - np.median(gaps[planted[-1]])) * 1.7 / rig.standing_height() * 100)
    planted, source_gaps = np.concatenate(planted), np.concatenate(source_gaps)
    header = (f"{'character':<22}{'joints':>7}{'err rel':>9}{'err glob':>10}{'feet cm':>14}"
              f"{'mesh cm: median planted lowest':>32}{'s/min':>7}")
    print(header)
    print("-" * len(header))
    print(f"{'the source (joints)':<22}{sources[0].skeleton.num_joints:>7}{'-':>9}{'-':>10}"
          f"{np.median(np.abs(source_gaps)):>7.1f} /{np.percentile(np.abs(source_gaps), 95):>5.1f}"
          f"{np.median(source_gaps):>16.1f}{np.median(source_gaps[planted]):>8.1f}{source_gaps.min():>8.1f}")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for name in CHARACTERS:
            character = read_character(args.data / "characters" / name)
            try:
                rig = character_rig(character)
            except MissingKeyJoints as error:
                print(f"{name:<22}{character.skeleton.num_joints:>7}  refused: {str(error).split(': ', 1)[1][:90]}")
                continue
            scale = 1.7 / rig.standing_height()
            bvh = tmp / f"{Path(name).stem}.bvh"
            save_motion(Motion.rest(character.skeleton), bvh)
            try:
                bvh_rig = Rig.of(load_motion(bvh).skeleton)
            except MissingKeyJoints:     # the key joints the reader found by the rig's shape (the robot's)
                bvh_rig = Rig.of(load_motion(bvh).skeleton, character.overrides)
            rel, glob, gaps, mesh = [], [], [], []
            for i, source in enumerate(sources):
                out = tmp / f"{Path(name).stem}_{i}.glb"
                result = onto_character(source, character, rig=rig)
                write_character(character, result, out)
                played = read_gltf_animation(out, animation=0)   # the file, as another program reads it
                r, g = errors(rig, played, retarget(source, bvh_rig, progress=False))
                rel.append(r * len(source))
                glob.append(g * len(source))
                gaps.append(floor_gaps(rig, result) * scale * 100)
                vertices, _ = posed_mesh(character, result)
                rest_vertices, _ = posed_mesh(character, Motion.rest(character.skeleton))
                mesh.append((vertices[..., 1].min(1) - rest_vertices[..., 1].min()) * scale * 100)
            start = time.perf_counter()
            write_character(character, onto_character(minute, character, rig=rig, progress=False), tmp / "minute.glb")
            seconds = time.perf_counter() - start
            gaps, mesh = np.concatenate(gaps), np.concatenate(mesh)
            print(f"{name:<22}{character.skeleton.num_joints:>7}{sum(rel) / frames:>9.3f}{sum(glob) / frames:>10.3f}"
                  f"{np.median(np.abs(gaps)):>7.1f} /{np.percentile(np.abs(gaps), 95):>5.1f}{np.median(mesh):>16.1f}"
                  f"{np.median(mesh[planted]):>8.1f}{mesh.min():>8.1f}"
                  f"{seconds:>7.1f}")
    print("err: squared key-joint position error / height^2 x 1000 against the BVH route; feet: median / 95th "
          "percentile; cm scaled to a 1.7 m person; the source's row: its lowest foot joint against its median over "
          "its planted frames, in the mesh columns too (it has no mesh)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Motion onto real characters (../shared/data/characters): glTF, VRM 1.0 and 0.x, with no
override file. Each result keeps the character's bones, meshes, materials, skins and its own
animations, lasts as long as the source, stands on the character's floor, passes the Khronos
validator with no issue the character did not already have (HUMOTION_GLTF_VALIDATOR), and
plays in three.js (GLTFLoader + AnimationMixer in headless Chromium): the skinned or rigid mesh
keeps its height and its lowest point on the floor while it moves. HUMOTION_CHARACTER_SCREENSHOTS
names a folder to keep a rendered frame of each (docs and eyes).
"""

from __future__ import annotations

import functools
import http.server
import json
import os
import shutil
import subprocess
import threading
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from humotion import rotations
from humotion.assets import demo_clip_path
from humotion.cli import main
from humotion.io import load_motion
from humotion.io.character import humanoid_bones, posed_mesh, read_character, write_character
from humotion.io.errors import MotionFileError
from humotion.io.gltf import read_gltf_animation, read_gltf_document
from humotion.motion import Motion
from humotion.retarget import retarget
from humotion.retarget.character import character_rig, on_floor, onto_character

from data_root import DATA

CHARACTERS = DATA / "characters"
NAMES = ("CesiumMan.glb", "Adventurer.gltf", "Soldier.gltf", "debug_robot.vrm", "RobotExpressive.glb")


def character_path(name: str) -> Path:
    path = CHARACTERS / name
    if not path.is_file():
        pytest.skip(f"{path} is not there")
    return path


def vrm0_variant(folder: Path) -> Path:
    """debug_robot.vrm rewritten as a VRM 0.x file: the humanoid map as 0.x's list under
    extensions.VRM, and the model turned to face -Z as 0.x models do."""
    gltf, buffers = read_gltf_document(character_path("debug_robot.vrm"))
    _, bones = humanoid_bones(gltf)
    gltf.extensions = {"VRM": {"specVersion": "0.0", "humanoid": {
        "humanBones": [{"bone": b, "node": n, "useDefaultValues": True} for b, n in bones.items()]}}}
    gltf.extensionsUsed = [e for e in gltf.extensionsUsed if e != "VRMC_vrm"] + ["VRM"]
    root = gltf.nodes[gltf.scenes[0].nodes[0]]
    root.rotation = [0.0, 1.0, 0.0, 0.0]  # 180 degrees about Y
    gltf.set_binary_blob(buffers[0])
    path = folder / "debug_robot_vrm0.vrm"
    path.write_bytes(b"".join(gltf.save_to_bytes()))
    return path


@functools.cache
def retargeted(name: str, folder: str) -> tuple[Path, Path]:
    """(character, result .glb) of the demo clip retargeted by the command, with no override."""
    folder = Path(folder)
    source = vrm0_variant(folder) if name == "vrm0" else character_path(name)
    out = folder / f"{source.stem}_punch.glb"
    result = CliRunner().invoke(main, ["retarget", str(demo_clip_path()), "--to", str(source), "-o", str(out)])
    assert result.exit_code == 0, result.output
    return source, out


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> str:
    return str(tmp_path_factory.mktemp("characters"))


@pytest.mark.parametrize("name", NAMES + ("vrm0",))
def test_character_keeps_everything_and_plays_the_clip_on_its_floor(name, folder):
    source, out = retargeted(name, folder)
    before, after = read_gltf_document(source)[0], read_gltf_document(out)[0]
    for kind in ("nodes", "meshes", "materials", "textures", "images", "skins", "samplers"):
        assert len(getattr(after, kind)) == len(getattr(before, kind)), kind
    assert [n.name for n in after.nodes] == [n.name for n in before.nodes]
    assert [m.primitives[0].targets and len(m.primitives[0].targets) for m in after.meshes] == \
           [m.primitives[0].targets and len(m.primitives[0].targets) for m in before.meshes]   # morph targets kept
    assert [a.name for a in after.animations[1:]] == [a.name for a in before.animations]    # its own clips kept
    assert after.extensions == before.extensions or (after.extensions or {}).keys() == (before.extensions or {}).keys()
    assert read_character(out).skeleton.names == read_character(source).skeleton.names

    clip = load_motion(demo_clip_path())
    played = read_gltf_animation(out, animation=0)
    assert played.fps == clip.fps and played.num_frames == clip.num_frames       # the duration
    # Feet on the floor: the posed mesh's lowest point (python skinning of the character's own
    # skins; three.js's below) stays where the rest pose's is. The clip stands almost throughout:
    # on the median frame the soles touch the floor (Adventurer and Soldier stood 1.8% of their
    # height above it when the floor was met by the joints on the 10% lowest frames), and the
    # robot's long feet, turned toes down, no longer push 5.3% of its height through it.
    character = read_character(source)
    result = onto_character(clip, character)
    vertices, _ = posed_mesh(character, result)
    rest, _ = posed_mesh(character, Motion.rest(character.skeleton))
    height = np.ptp(rest[0, :, 1])
    lowest = vertices[..., 1].min(1) - rest[0, :, 1].min()
    assert abs(np.median(lowest)) < 0.005 * height, np.median(lowest) / height
    assert lowest.min() > -0.02 * height, lowest.min() / height


def test_the_result_is_the_retargeted_motion(folder):
    """The file's animation, read back by the independent glTF reader, puts the joints where the
    retargeter put them (Adventurer: a Y-up rig whose feet hang off the root)."""
    source, out = retargeted("Adventurer.gltf", folder)
    character = read_character(source)
    rig = character_rig(character)
    expected = on_floor(retarget(load_motion(demo_clip_path()), rig), character, rig)
    played = read_gltf_animation(out, animation=0)
    got = played.world_positions().numpy()[:, [played.skeleton.index(n) for n in character.skeleton.names]]
    assert np.abs(got - expected.world_positions().numpy()).max() < 1e-4


def test_vrm_humanoid_maps_name_the_key_joints(folder):
    for path in (character_path("debug_robot.vrm"), vrm0_variant(Path(folder))):
        character = read_character(path)
        assert character.kind == ("VRM 1.0" if path.name == "debug_robot.vrm" else "VRM 0.x")
        joints = character.overrides["joints"]
        assert (joints["pelvis"], joints["left_wrist"], joints["right_ankle"], joints["spine3"]) == \
               ("hips", "hand.L", "foot.R", "chest")


def test_bind_pose_under_a_z_up_root():
    """CesiumMan: a Z-up armature under a Y-up root matrix; its bind pose stands up in Y."""
    character = read_character(character_path("CesiumMan.glb"))
    rest = character.skeleton.rest_positions()
    assert rest[:, 1].min() > -0.01 and 1.1 < rest[:, 1].max() - rest[:, 1].min() < 1.3
    assert rest[:, 2].max() - rest[:, 2].min() < 0.15


def test_errors(tmp_path, monkeypatch):
    runner = CliRunner()
    plain = tmp_path / "plain.gltf"
    plain.write_text(json.dumps({"asset": {"version": "2.0"}, "nodes": [{"name": "a"}]}))
    with pytest.raises(MotionFileError, match="no skin and no VRM humanoid"):
        read_character(plain)
    result = runner.invoke(main, ["retarget", str(demo_clip_path()), "--to", str(plain), "-o", str(tmp_path / "o.glb")])
    assert result.exit_code == 1 and "no skin" in result.output and "Traceback" not in result.output
    fbx = tmp_path / "hero.fbx"
    fbx.write_bytes(b"Kaydara FBX Binary  \x00")
    monkeypatch.setattr("humotion.io.character._bpy", lambda: None)   # as without humotion[fbx]
    result = runner.invoke(main, ["retarget", str(demo_clip_path()), "--to", str(fbx), "-o", str(tmp_path / "o.glb")])
    assert result.exit_code == 1 and "humotion[fbx]" in result.output and len(result.output.splitlines()) == 1


# -- the Khronos validator and three.js, when at hand ------------------------------------------
def tools() -> Path:
    folder = os.environ.get("HUMOTION_GLTF_VALIDATOR")
    if not folder or shutil.which("node") is None or not (Path(folder) / "node_modules" / "gltf-validator").is_dir():
        pytest.skip("set HUMOTION_GLTF_VALIDATOR to a folder holding node_modules/gltf-validator (scripts/test.sh does)")
    return Path(folder)


VALIDATE_JS = """
const v = require('gltf-validator'); const fs = require('fs');
v.validateBytes(new Uint8Array(fs.readFileSync(process.argv[1])), {maxIssues: 0})
  .then(r => console.log(JSON.stringify(r.issues)));
"""


def issues(path: Path) -> dict:
    result = subprocess.run(["node", "-e", VALIDATE_JS, str(path)], cwd=tools(), capture_output=True, text=True,
                            timeout=120, check=True)
    found = json.loads(result.stdout)
    counts: dict[str, int] = {}
    for message in found["messages"]:
        counts[message["code"]] = counts.get(message["code"], 0) + 1
    return {"errors": found["numErrors"], "codes": counts}


@pytest.mark.parametrize("name", NAMES + ("vrm0",))
def test_khronos_validator_adds_nothing(name, folder):
    source, out = retargeted(name, folder)
    got, had = issues(out), issues(source)
    assert got["errors"] == 0
    assert got["codes"] == had["codes"]   # only what the character's own file already reports (none of ours)


PAGE = """<!doctype html><html><body style="margin:0">
<script type="importmap">{"imports": {"three": "./three/build/three.module.js", "three/addons/": "./three/examples/jsm/"}}</script>
<script type="module">
import * as THREE from 'three';
import {GLTFLoader} from 'three/addons/loaders/GLTFLoader.js';
try {
  const gltf = await new GLTFLoader().loadAsync('model.glb');
  const scene = new THREE.Scene(); scene.add(gltf.scene);
  const v = new THREE.Vector3();
  const box = () => { gltf.scene.updateMatrixWorld(true); const b = new THREE.Box3();
    gltf.scene.traverse(o => { if (!o.isMesh) return; const n = o.geometry.attributes.position.count;
      for (let i = 0; i < n; i += Math.max(1, Math.floor(n / 3000))) { o.getVertexPosition(i, v); b.expandByPoint(v.applyMatrix4(o.matrixWorld)); } });
    return [b.min.toArray(), b.max.toArray()]; };
  const rest = box();
  const clip = gltf.animations[0], mixer = new THREE.AnimationMixer(gltf.scene);
  mixer.clipAction(clip).play();
  const frames = [0, 0.2, 0.4, 0.6, 0.8, 1].map(f => { mixer.setTime(f * clip.duration * 0.999); return box(); });
  mixer.setTime(clip.duration * SHOW);
  const b = box(), c = [(b[0][0] + b[1][0]) / 2, (b[0][1] + b[1][1]) / 2, (b[0][2] + b[1][2]) / 2], h = b[1][1] - b[0][1];
  const camera = new THREE.PerspectiveCamera(35, innerWidth / innerHeight, h / 100, h * 100);
  camera.position.set(c[0] + h * 0.9, c[1] + h * 0.3, c[2] + h * 2.6); camera.lookAt(c[0], c[1], c[2]);
  scene.background = new THREE.Color(0xe8e8e8);
  scene.add(new THREE.HemisphereLight(0xffffff, 0x666666, 2.5)); const sun = new THREE.DirectionalLight(0xffffff, 2);
  sun.position.set(1, 2, 3); scene.add(sun);
  const floor = new THREE.GridHelper(h * 3, 12, 0x555555, 0x999999); floor.position.y = rest[0][1]; scene.add(floor);
  const renderer = new THREE.WebGLRenderer({antialias: true}); renderer.setSize(innerWidth, innerHeight);
  document.body.appendChild(renderer.domElement); renderer.render(scene, camera);
  window.result = {name: clip.name, duration: clip.duration, clips: gltf.animations.length, rest, frames};
} catch (e) { window.result = {error: String(e)}; }
</script></body></html>"""


@pytest.mark.parametrize("name", NAMES + ("vrm0",))
def test_plays_in_threejs(name, folder, tmp_path):
    from test_viewer import CHROMIUM, headless_chromium, wait_for

    three = tools() / "node_modules" / "three"
    if not Path(CHROMIUM).exists() or not three.is_dir():
        pytest.skip("needs /usr/bin/chromium and node_modules/three beside the validator")
    source, out = retargeted(name, folder)
    site = tmp_path / "site"
    site.mkdir()
    (site / "three").symlink_to(three)
    shutil.copy(out, site / "model.glb")
    (site / "index.html").write_text(PAGE.replace("SHOW", "0.45"))
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(site))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    handler.log_message = lambda *a: None
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        with headless_chromium(tmp_path / "profile", 640, 640) as chromium:
            chromium.call("Page.enable")
            chromium.call("Page.navigate", url=f"http://127.0.0.1:{server.server_address[1]}/index.html")

            def result():
                answer = chromium.call("Runtime.evaluate", expression="JSON.stringify(window.result || null)",
                                       returnByValue=True)
                return json.loads(answer["result"].get("value") or "null")

            played = wait_for(result, 60, "three.js to load and play the character")
            keep = os.environ.get("HUMOTION_CHARACTER_SCREENSHOTS")
            if keep:
                from PIL import Image

                Path(keep).mkdir(parents=True, exist_ok=True)
                Image.fromarray(chromium.screenshot()).save(Path(keep) / f"{out.stem}.png")
    finally:
        server.shutdown()
    assert "error" not in played, played
    clip = load_motion(demo_clip_path())
    assert abs(played["duration"] - (clip.num_frames - 1) / clip.fps) < 1e-3
    assert played["clips"] == len(read_gltf_document(source)[0].animations) + 1
    rest_min, rest_max = np.array(played["rest"])
    height = rest_max[1] - rest_min[1]
    for low, high in np.array(played["frames"]):
        assert abs(low[1] - rest_min[1]) < 0.05 * height        # on the floor
        assert 0.75 * height < high[1] - low[1] < 1.15 * height  # standing (the punch bends a little)
    centres = np.array(played["frames"]).mean(1)
    assert np.ptp(centres, axis=0).max() > 0.01 * height         # it moves


def test_track_writes_the_animated_character(tmp_path):
    """track --character: the headset body on a character, written beside -o (VRM out for a VRM),
    and the posed mesh the viewer would show (one row of vertices per frame)."""
    from humotion.retarget.character import viewer_mesh
    from humotion.viewer.app import _checked_meshes

    vrm = character_path("debug_robot.vrm")
    result = CliRunner().invoke(main, ["track", "--demo", "-o", str(tmp_path / "body.bvh"), "--character", str(vrm),
                                       "--no-view"])
    assert result.exit_code == 0, result.output
    out = tmp_path / "body_debug_robot.vrm"
    assert f"wrote {out}" in result.output
    body = load_motion(tmp_path / "body.bvh")
    played = read_gltf_animation(out, animation=0)
    assert played.num_frames == body.num_frames and played.fps == body.fps
    assert read_character(out).kind == "VRM 1.0"
    character = read_character(vrm)
    on_it = onto_character(body, character)
    vertices, faces = viewer_mesh(character, on_it)
    assert vertices.shape == (body.num_frames, 1584, 3) and faces.shape == (792, 3)
    assert _checked_meshes([(vertices, faces)], [on_it])[0] is not None


def test_retarget_view_shows_the_skinned_character(tmp_path, monkeypatch):
    """retarget --to character --view: the viewer shows the source's skeleton and, beside it, the
    character's own mesh posed by the result on every frame."""
    import webbrowser

    from humotion.viewer import MotionViewer

    shown = {}

    def run(viewer):
        shown["mesh"] = viewer.server.scene.get_handle_by_name("/motions/1/mesh")
        shown["none"] = viewer.server.scene.get_handle_by_name("/motions/0/mesh")
        shown["vertices"] = shown["mesh"].vertices.copy()
        viewer.set_frame(30)
        shown["moved"] = np.abs(shown["mesh"].vertices - shown["vertices"]).max()
        viewer.stop()

    monkeypatch.setattr(MotionViewer, "run", run)
    monkeypatch.setattr(webbrowser, "open", lambda url: None)
    vrm = character_path("debug_robot.vrm")
    result = CliRunner().invoke(main, ["retarget", str(demo_clip_path()), "--to", str(vrm),
                                       "-o", str(tmp_path / "punch.vrm"), "--view", "--port", "0"])
    assert result.exit_code == 0, result.output
    assert shown["none"] is None and shown["vertices"].shape == (1584, 3)
    assert shown["moved"] > 0.05                       # metres: the punch moves the mesh between frames 0 and 30


def test_capture_writes_the_animated_character(tmp_path):
    """capture --character on the shipped photo: each person also on the character, as a VRM."""
    from humotion.assets import demo_photo_path

    vrm = character_path("debug_robot.vrm")
    result = CliRunner().invoke(main, ["capture", str(demo_photo_path()), "-o", str(tmp_path), "--character", str(vrm)])
    assert result.exit_code == 0, result.output
    written = sorted(tmp_path.glob("person*_debug_robot.vrm"))
    assert written and all(f"wrote {path}" in result.output for path in written)
    for path in written:
        character = read_character(path)
        assert character.kind == "VRM 1.0" and character.skeleton.names == read_character(vrm).skeleton.names
        assert read_gltf_animation(path, animation=0).num_frames == 1


def test_several_skins_and_a_scaled_armature_round_trip(tmp_path):
    """RobotExpressive (4 skins sharing 43 joints, an armature scaled by 100 and turned, rigid
    parts under bones, morph targets, 14 clips): a motion written onto it is read back by the
    independent glTF reader with every joint where the motion put it, everything else kept."""
    source = character_path("RobotExpressive.glb")
    character = read_character(source)
    frames = 20
    yaw = torch.linspace(0, 1.5, frames, dtype=torch.float64)
    turn = rotations.convert(torch.stack([torch.zeros(frames), yaw, torch.zeros(frames)], -1), "rotvec", "quat")
    bend = rotations.convert(torch.stack([0.8 * yaw, torch.zeros(frames), torch.zeros(frames)], -1), "rotvec", "quat")
    motion = Motion.rest(character.skeleton, frames=frames, fps=30.0)
    local = motion.rotations.clone()
    local[:, 0] = turn.float()
    local[:, character.skeleton.index("UpperArmL")] = bend.float()
    root = motion.root_positions.clone() + torch.linspace(0, 1, frames)[:, None] * torch.tensor([1.0, 0.0, 0.5])
    motion = Motion(character.skeleton, local, root, 30.0)
    out = tmp_path / "robot.glb"
    write_character(character, motion, out)
    before, after = read_gltf_document(source)[0], read_gltf_document(out)[0]
    assert (len(after.skins), len(after.meshes), len(after.animations)) == (4, 19, 15)
    assert [m.primitives[0].targets and len(m.primitives[0].targets) for m in after.meshes] == \
           [m.primitives[0].targets and len(m.primitives[0].targets) for m in before.meshes]
    played = read_gltf_animation(out, animation=0)
    names = list(character.skeleton.names)
    got = played.world_positions().numpy()[:, [played.skeleton.index(n) for n in names]]
    assert np.abs(got - motion.world_positions().numpy()).max() < 1e-3 * character.skeleton.height()

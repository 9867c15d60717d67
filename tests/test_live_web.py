"""The live page that humotion serve serves: its files over HTTP (and nothing else), its avatar
(a body of humotion body and the table that drives its rig, checked against the body model's own
retargeting), and its replay mode in headless Chromium: the demo clip's frames out, the tracked
body drawn back as the skinned body, upright, feet on the floor, moving."""

import asyncio
import contextlib
import json
import math
import os
import threading
import time
import urllib.error
import urllib.request

import numpy as np
import pytest
import torch
from PIL import Image

from humotion import rotations as rot
from humotion.live.server import LiveServer, ServeSettings


@contextlib.contextmanager
def live_server(**settings):
    """A LiveServer on 127.0.0.1 (any free port) in a thread of its own, stopped afterwards."""
    ready, holder = threading.Event(), {}

    async def main():
        async with LiveServer(ServeSettings(port=0, **settings)) as server:
            holder.update(server=server, stop=asyncio.Event(), loop=asyncio.get_running_loop())
            ready.set()
            await asyncio.wait_for(holder["stop"].wait(), 300)

    thread = threading.Thread(target=asyncio.run, args=(main(),), daemon=True)
    thread.start()
    assert ready.wait(60), "the server did not start"
    try:
        yield holder["server"]
    finally:
        holder["loop"].call_soon_threadsafe(holder["stop"].set)
        thread.join(30)


def get(url: str) -> tuple[int, str, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=30) as answer:
            return answer.status, answer.headers["Content-Type"], answer.read()
    except urllib.error.HTTPError as error:
        return error.code, error.headers["Content-Type"], error.read()


def test_the_page_its_files_and_nothing_else_are_served():
    with live_server() as server:
        base = f"http://127.0.0.1:{server.port}"
        status, kind, page = get(base + "/")
        assert status == 200 and kind.startswith("text/html") and b'"three": "./vendor/three.module.js"' in page
        status, kind, script = get(base + "/vendor/three.module.js")
        assert status == 200 and kind == "text/javascript" and b"three.core.js" in script
        for path in ("/live.js", "/vendor/three.core.js", "/vendor/addons/loaders/GLTFLoader.js",
                     "/vendor/addons/utils/BufferGeometryUtils.js", "/vendor/addons/utils/SkeletonUtils.js"):
            assert get(base + path)[0] == 200
        for path in ("/../server.py", "/web/index.html", "/vendor/README.md", "/etc/passwd", "/index.html?x=1/../.."):
            assert get(base + path)[0] == 404, path
        status, kind, demo = get(base + "/demo.json")
        frames = json.loads(demo)["frames"]
        assert status == 200 and len(frames) > 100 and len(frames[0][1]) == 7


@pytest.mark.browser
def test_the_replay_mode_draws_the_tracked_body_in_chromium(tmp_path):
    from test_viewer import CHROMIUM, headless_chromium, wait_for

    if not os.path.exists(CHROMIUM):
        pytest.skip(f"{CHROMIUM} not found: install Debian's chromium package to run browser tests")
    with live_server() as server, headless_chromium(tmp_path / "profile") as chromium:
        chromium.watch_network()
        chromium.call("Page.enable")
        chromium.call("Page.navigate", url=f"http://127.0.0.1:{server.port}/?replay=1")

        def state():
            answer = chromium.call("Runtime.evaluate", returnByValue=True,
                                   expression="window.humotion && JSON.stringify(window.humotion)")
            value = answer["result"].get("value")
            return json.loads(value) if value else None

        def probe():
            answer = chromium.call("Runtime.evaluate", returnByValue=True,
                                   expression="JSON.stringify(window.humotion.probe())")
            return json.loads(answer["result"]["value"])

        seen = wait_for(lambda: (s := state()) and s["poses"] >= 90 and (s["body"] or s["errors"]) and s, 180,
                        "90 poses back from the server and the body loaded")
        assert seen["mode"] == "replay" and not seen["errors"] and seen["welcome"]["joints"][0] == "pelvis"
        assert seen["body"]["bones"] == 76 and seen["body"]["vertices"] > 1000
        positions = seen["last"]
        assert len(positions) == 22 and all(math.isfinite(v) for p in positions for v in p)
        assert 1.2 < positions[15][1] < 2.0                      # the head joint, above the floor (metres)
        assert server.stats.frames >= 90
        # the skinned body: upright, the feet on the floor, and moving from one moment to the next
        shapes = []
        for _ in range(3):
            shapes.append(probe())
            time.sleep(0.5)
        for shape in shapes:
            assert -0.06 < shape["low"] < 0.06, shape["low"]        # the lowest vertex: a sole on the floor
            assert 1.4 < shape["high"] < 2.1, shape["high"]        # the top: standing (a 1.7 m body; the head or a raised hand)
        moved = [np.linalg.norm(np.subtract(a["sample"], b["sample"]), axis=1).max() for a, b in zip(shapes, shapes[1:])]
        assert min(moved) > 0.02, moved                            # vertices moved by centimetres in half a second
        picture = chromium.screenshot()
        Image.fromarray(picture).save(tmp_path / "live_page.png")
        body = (np.abs(picture.astype(int) - [0x20, 0x24, 0x28]).sum(-1) > 60)      # not the background or grid
        rows, columns = np.nonzero(body)
        assert body.mean() > 0.01 and rows.max() - rows.min() > 0.25 * picture.shape[0]   # a standing figure
        urls = chromium.requested_urls()
        assert urls and all(u.startswith((f"http://127.0.0.1:{server.port}/", f"ws://127.0.0.1:{server.port}/"))
                            for u in urls), urls                 # no CDN: everything from the server


# The page's own script (live.js) run by Node with three.js and the DOM stubbed: its frames,
# its replay clock and its pose decoding against the real server (where Chromium is missing).
NODE_STUBS = r"""
const stub = () => new Proxy(function () {}, {
  get: (t, k) => (k === "then" ? undefined : k in t ? t[k] : (t[k] = stub())),
  apply: () => stub(), construct: () => stub(), set: (t, k, v) => { t[k] = v; return true; } });
export class WebGLRenderer {
  constructor() { return new Proxy(this, { get: (t, k) => (k in t ? t[k] : (t[k] = stub())) }); }
  setAnimationLoop(callback) { setInterval(() => callback(performance.now(), null), 11); }
}
export const Scene = stub(), Color = stub(), PerspectiveCamera = stub(), GridHelper = stub(),
  HemisphereLight = stub(), DirectionalLight = stub(), Group = stub(), Quaternion = stub(), Vector3 = stub();
"""
NODE_LOADER = "export class GLTFLoader { loadAsync() { return new Promise(() => {}); } }   // the body never loads\n"
NODE_MAIN = r"""
const [url, script, seconds] = process.argv.slice(2);
globalThis.location = new URL(url);
globalThis.window = globalThis;
Object.assign(globalThis, { innerWidth: 800, innerHeight: 600, devicePixelRatio: 1, addEventListener() {} });
globalThis.navigator ??= {};
const element = () => ({ textContent: "", disabled: false, onclick: null });
const elements = {};
globalThis.document = { body: { appendChild() {} }, getElementById: (id) => (elements[id] ??= element()) };
const fetchAbsolute = globalThis.fetch;
globalThis.fetch = (u) => fetchAbsolute(new URL(u, location));
await import(script);
setTimeout(() => { console.log(JSON.stringify(window.humotion)); process.exit(0); }, 1000 * Number(seconds));
"""


def test_the_page_script_replays_and_decodes_poses_in_node(tmp_path):
    import shutil
    import subprocess
    from pathlib import Path

    node = shutil.which("node")
    if node is None:
        pytest.skip("node not found")
    three = tmp_path / "node_modules" / "three"
    three.mkdir(parents=True)
    (three / "package.json").write_text('{"name": "three", "type": "module", "main": "index.js"}')
    (three / "index.js").write_text(NODE_STUBS)
    (three / "addons" / "loaders").mkdir(parents=True)
    (three / "addons" / "loaders" / "GLTFLoader.js").write_text(NODE_LOADER)
    script = tmp_path / "live.mjs"
    script.write_text((Path(__import__("humotion.live").live.__file__).parent / "web" / "live.js").read_text())
    (tmp_path / "main.mjs").write_text(NODE_MAIN)
    with live_server() as server:
        url = f"http://127.0.0.1:{server.port}/?replay=1"
        done = subprocess.run([node, "--experimental-websocket", "--no-warnings", str(tmp_path / "main.mjs"), url,
                               str(script), "6"], capture_output=True, text=True, timeout=120, cwd=tmp_path)
        frames = server.stats.frames
    assert done.returncode == 0, done.stderr
    state = json.loads(done.stdout.strip().splitlines()[-1])
    assert state["mode"] == "replay" and not state["errors"] and state["welcome"]["joints"][0] == "pelvis"
    assert state["poses"] >= 90 and frames >= state["poses"]           # about 90 a second once the tracker is built
    positions = state["last"]
    assert len(positions) == 22 and all(math.isfinite(v) for p in positions for v in p)
    assert 1.2 < positions[15][1] < 2.0                                  # the head joint, metres above the floor


def test_tls_serves_https_and_wss(tmp_path):
    import shutil
    import ssl
    import subprocess

    from websockets.sync.client import connect

    if shutil.which("openssl") is None:
        pytest.skip("openssl not found")
    cert, key = tmp_path / "cert.pem", tmp_path / "key.pem"
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1", "-subj", "/CN=127.0.0.1",
                    "-addext", "subjectAltName=IP:127.0.0.1", "-keyout", str(key), "-out", str(cert)],
                   check=True, capture_output=True, timeout=60)
    trust = ssl.create_default_context(cafile=str(cert))
    with live_server(tls=(str(cert), str(key))) as server:
        with urllib.request.urlopen(f"https://127.0.0.1:{server.port}/", context=trust, timeout=30) as answer:
            assert answer.status == 200
        with connect(f"wss://127.0.0.1:{server.port}/", ssl=trust, open_timeout=30) as ws:
            ws.send(json.dumps({"type": "hello"}))
            assert json.loads(ws.recv(timeout=30))["type"] == "welcome"


@pytest.fixture(scope="module")
def avatar():
    from humotion.live.avatar import make_avatar

    return make_avatar(1.7)


def page_world_rotations(table: dict, canonical_local: torch.Tensor) -> torch.Tensor:
    """What live.js does, in Python: canonical local rotations (22, 3, 3) -> the rig's world
    rotations (J, 3, 3) by the avatar's table."""
    from humotion.canonical import PARENTS
    from humotion.skeleton import forward_kinematics

    world, _ = forward_kinematics(canonical_local, torch.zeros(3, dtype=torch.float64), np.zeros((22, 3)), PARENTS)
    rest = rot.quat_to_matrix(torch.tensor(table["rest"], dtype=torch.float64))
    clavicles = {c["bone"]: c for c in table["clavicles"]}
    out = []
    for b, (driver, parent) in enumerate(zip(table["drivers"], table["parents"])):
        out.append(world[driver] @ rest[b] if driver >= 0 else out[parent] if parent >= 0 else torch.eye(3, dtype=torch.float64))
        if b in clavicles:
            c = clavicles[b]
            arm = out[parent].T @ world[c["shoulder"]] @ torch.tensor(c["aim"], dtype=torch.float64)
            elevation = torch.asin((arm[1] / arm.norm()).clamp(-1, 1)).clamp(min=0)
            out[b] = out[b] @ rot.convert(torch.tensor(c["axis"], dtype=torch.float64) * c["rise"] * elevation, "rotvec", "matrix")
    return torch.stack(out)


def test_the_avatar_table_retargets_as_the_body_model_does(avatar):
    """The page's rig rotations equal humotion.body's own retargeting (canonical_to_rig) on the
    demo clip's poses and on poses with the arms raised (the clavicles rise with them)."""
    from humotion.assets import demo_clip_path
    from humotion.body.export import body_measurements, rest_body
    from humotion.body.model import load_body_model
    from humotion.body.posing import canonical_to_rig
    from humotion.canonical import JOINTS, to_canonical
    from humotion.io import load_motion
    from humotion.skeleton import forward_kinematics

    table = avatar.table
    assert len(table["bones"]) == 76 and sum(d >= 0 for d in table["drivers"]) == 18 and table["height"] == pytest.approx(1.7, abs=0.01)
    model = load_body_model("low")
    body = rest_body(model, model.shape_from_measurements(*body_measurements(1.7, None)))
    motion = to_canonical(load_motion(demo_clip_path()))
    poses = rot.quat_to_matrix(motion.rotations[::40].double())                  # (P, 22, 3, 3)
    raised = poses[:4].clone()                                   # upper arms turned 30-120 degrees up
    for k, angle in enumerate((30.0, 60.0, 90.0, 120.0)):
        for side, sign in (("left", 1.0), ("right", -1.0)):
            up = rot.convert(torch.tensor([0.0, 0.0, sign * np.radians(angle)], dtype=torch.float64), "rotvec", "matrix")
            raised[k, JOINTS.index(f"{side}_shoulder")] = up
    poses = torch.cat([poses, raised])
    local = canonical_to_rig(poses, body.vertices.double(), body.joints.double(), model.joint_names, model.parents)
    for pose, rig_local in zip(poses, local):
        expected, _ = forward_kinematics(rig_local, torch.zeros(3, dtype=torch.float64),
                                         np.zeros((76, 3)), table["parents"])
        page = page_world_rotations(table, pose)
        assert torch.allclose(page, expected, atol=1e-5)
    clavicle = table["bones"].index("clavicle.L")
    rise = np.degrees(np.arccos(np.clip((np.trace(local[-4:, clavicle].numpy(), axis1=-2, axis2=-1) - 1) / 2, -1, 1)))
    assert (rise > 10).all(), rise                    # the clavicles did rise with the arms (0.3 x the elevation)


def test_a_body_file_of_humotion_body_is_served_as_it_is(tmp_path, avatar):
    from test_viewer import wait_for

    from humotion.live.avatar import make_avatar

    path = tmp_path / "mine.glb"
    path.write_bytes(avatar.glb)
    mine = make_avatar(path=path)
    assert mine.glb == avatar.glb and mine.table == avatar.table            # its shape read back from the file
    (tmp_path / "other.glb").write_bytes(b"glTF" + bytes(40))
    with pytest.raises(ValueError, match="not a body written by `humotion body`"):
        make_avatar(path=tmp_path / "other.glb")
    with live_server(body=str(path)) as server:
        base = f"http://127.0.0.1:{server.port}"
        wait_for(lambda: get(base + "/body.json")[0] != 503, 120, "the body made")
        status, kind, glb = get(base + "/body.glb")
        assert status == 200 and kind == "model/gltf-binary" and glb == avatar.glb
        status, kind, table = get(base + "/body.json")
        assert status == 200 and json.loads(table) == avatar.table

"""The browser viewer: timeline logic without a browser, and a real render in headless Chromium.

The browser test opens the viewer in Debian's Chromium (/usr/bin/chromium), driven over the
DevTools protocol with the `websockets` package viser already depends on, and proves the scene
rendered: the page connects as a viser client; a screenshot of the WebGL canvas alone (page
controls hidden) shows both skeletons in their bone colours, side by side and standing; the
picture changes when the frame changes; the page's Play/Pause button drives playback on the
server; a render the server requests from the browser's WebGL renderer shows the skeletons too;
every request the page and its workers made went to the local server (nothing from a CDN); and
stopping frees the port at once. Set HUMOTION_VIEWER_SCREENSHOT=/path.png to keep a screenshot
of the whole page. Skipped only when /usr/bin/chromium is missing.
"""

from __future__ import annotations

import base64
import dataclasses
import contextlib
import io
import itertools
import json
import logging
import os
import shutil
import signal
import socket
import subprocess
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import torch

from humotion import rotations
from humotion.motion import Motion
from humotion.skeleton import Skeleton

pytest.importorskip("viser", reason="viser is not installed")
viewer_module = pytest.importorskip("humotion.viewer")
from humotion.viewer.app import LABEL_GAP, LABEL_HEIGHT, MESH_COLOR, legend, side_by_side  # noqa: E402  (after the viser check)
MotionViewer = viewer_module.MotionViewer

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--enable-unsafe-swiftshader",  # WebGL on the CPU (SwiftShader), as there is no GPU
    "--disable-dev-shm-usage", "--mute-audio", "--hide-scrollbars",
]


def small_skeleton() -> Skeleton:
    """A 16-joint humanoid, 1.7 m tall, facing +Z, with five end sites."""
    names = ["hips", "spine", "neck", "head", "lshoulder", "lelbow", "lwrist", "rshoulder", "relbow",
             "rwrist", "lhip", "lknee", "lankle", "rhip", "rknee", "rankle"]
    parents = [-1, 0, 1, 2, 2, 4, 5, 2, 7, 8, 0, 10, 11, 0, 13, 14]
    offsets = [[0, 0.95, 0], [0, 0.25, 0], [0, 0.25, 0], [0, 0.12, 0], [0.18, 0, 0], [0.28, 0, 0],
               [0.25, 0, 0], [-0.18, 0, 0], [-0.28, 0, 0], [-0.25, 0, 0], [0.1, -0.05, 0], [0, -0.42, 0],
               [0, -0.42, 0], [-0.1, -0.05, 0], [0, -0.42, 0], [0, -0.42, 0]]
    return Skeleton(names, parents, offsets, end_site_parents=[3, 6, 9, 12, 15],
                    end_site_offsets=[[0, 0.12, 0], [0.08, 0, 0], [-0.08, 0, 0], [0, -0.05, 0.15], [0, -0.05, 0.15]])


def random_motion(frames: int = 30, fps: float = 30.0, seed: int = 0, name: str = "") -> Motion:
    skeleton = small_skeleton()
    generator = torch.Generator().manual_seed(seed)
    rotvec = torch.randn(frames, skeleton.num_joints, 3, generator=generator) * 0.3
    root = skeleton.offsets[0].expand(frames, 3).clone()
    root[:, 2] += torch.linspace(0, 0.5, frames)
    return Motion(skeleton, rotations.convert(rotvec, "rotvec", "quat"), root, fps, name=name)


def port_is_free(port: int) -> bool:
    """Whether a server could listen on the port again (with SO_REUSEADDR, as servers do)."""
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


# -- without a browser --------------------------------------------------------------------

def test_the_legend_counts_in_words_and_shows_a_surface_in_its_own_colour():
    """A photo's one frame is '1 frame'; a motion drawn as a surface gets the surface's colour,
    not its skeleton's (the demo's grey body was listed in magenta)."""
    still, walk = random_motion(frames=1), random_motion(frames=30)
    text = legend(["photo", "body"], [(255, 0, 0), (200, 0, 200)], [still, walk], [None, ("vertices", "faces")])
    photo, body = text.split("  \n")
    assert "1 frame," in photo and "rgb(255, 0, 0)" in photo
    assert "30 frames," in body and f"rgb{MESH_COLOR}" in body and "(200, 0, 200)" not in body


def test_bone_segments_match_forward_kinematics():
    motion = random_motion(frames=4)
    segments, joints = viewer_module.bone_segments(motion)
    sk = motion.skeleton
    assert segments.shape == (4, sk.num_joints - 1 + len(sk.end_site_parents), 2, 3)
    world = motion.world_positions().numpy()
    np.testing.assert_allclose(joints, world, atol=1e-6)
    np.testing.assert_allclose(segments[:, 0, 0], world[:, 0], atol=1e-6)   # spine's parent: hips
    np.testing.assert_allclose(segments[:, 0, 1], world[:, 1], atol=1e-6)
    np.testing.assert_allclose(segments[:, -1, 1], motion.end_site_positions().numpy()[:, -1], atol=1e-6)


def test_timeline_by_time_and_clean_stop():
    slow, fast = random_motion(frames=30, fps=30, name="slow"), random_motion(frames=50, fps=60, seed=1)
    viewer = MotionViewer([slow, fast], port=0, loop=False)
    try:
        assert viewer.labels == ["slow", "motion 1"]
        assert viewer.fps == 60 and viewer.num_frames == 59  # slow lasts 29/30 s, the longer
        assert viewer.motion_frames(0) == [0, 0]
        assert viewer.motion_frames(20) == [10, 20]
        assert viewer.motion_frames(58) == [29, 49]          # the fast motion holds its last frame
        viewer.set_frame(1000)
        assert viewer.frame == 58
        viewer.set_time(0.5)
        assert viewer.frame == 30
        bones = viewer.server.scene.get_handle_by_name("/motions/0/bones")
        np.testing.assert_allclose(bones.points, viewer._segments[0][15])
        # Side by side along X, left to right, a margin apart (see the layout test).
        assert viewer.offsets[1, 0] > viewer.offsets[0, 0]
        # Playback advances in real time (60 fps): about 18 frames in 0.3 s.
        viewer.set_frame(0)
        began = time.monotonic()
        viewer.play()
        time.sleep(0.3)
        viewer.pause()
        elapsed = time.monotonic() - began
        assert 8 <= viewer.frame <= min(elapsed * 60 + 3, 58)
        # Without looping, playback stops on the last frame.
        viewer.set_frame(55)
        viewer.play()
        wait_for(lambda: not viewer.playing, 5, "playback to stop at the end")
        assert viewer.frame == 58
        port = viewer.port
    finally:
        viewer.stop()
    viewer.stop()  # twice is fine
    assert not viewer._thread.is_alive()
    assert port_is_free(port)


def test_run_serves_until_stopped(caplog):
    caplog.set_level(logging.INFO, logger="humotion.viewer")
    viewer = MotionViewer(random_motion(frames=5), port=0)
    timer = threading.Timer(0.3, viewer.stop)
    timer.start()
    viewer.run()  # returns once stop() is called (Ctrl-C does the same)
    timer.join()
    assert viewer.url in caplog.text     # logged, not printed: `humotion view` prints it (test_cli_viewer_address)
    assert not viewer._thread.is_alive()



def test_serve_opens_a_tab_at_the_viewer_address_and_blocks_until_stopped(monkeypatch, capsys):
    """viewer.serve, the one way the commands start the viewer: with open_browser a tab opens at
    the address run() logs; without it none does."""
    import webbrowser

    opened = []
    monkeypatch.setattr(webbrowser, "open", opened.append)
    monkeypatch.setattr(MotionViewer, "run", lambda self: self.stop())   # serve until stopped at once
    viewer_module.serve(random_motion(frames=5), port=0, open_browser=True)
    viewer_module.serve(random_motion(frames=5), port=0)
    assert len(opened) == 1 and opened[0].startswith("http://")

def test_side_by_side_lines_things_up_a_margin_apart_centred():
    offsets = side_by_side(np.array([[-0.3, 0.3], [1.0, 3.0], [-0.5, 0.5]]), margin=1.0)
    placed = np.array([[-0.3, 0.3], [1.0, 3.0], [-0.5, 0.5]]) + offsets[:, None]
    np.testing.assert_allclose(placed, [[-2.8, -2.2], [-1.2, 0.8], [1.8, 2.8]])   # widths 0.6 + 2 + 1, gaps 1


def test_each_motion_moves_by_its_own_width_surface_included():
    """A motion that walks along X, and a body surface wider than its skeleton, push their
    neighbours away: no two motions' X ranges (joints and surfaces, all frames) come closer than
    the margin, so bodies and their labels do not overlap."""
    walker = random_motion(frames=30, seed=0)
    walker = dataclasses.replace(walker, root_positions=walker.root_positions
                                 + torch.linspace(0, 3, 30)[:, None] * torch.tensor([1.0, 0, 0]))
    standing = random_motion(frames=30, seed=1)
    wide = np.zeros((30, 2, 3), np.float32)
    wide[:, 0, 0], wide[:, 1, 0] = -1.5, 1.5   # a surface 3 m wide around the origin
    viewer = MotionViewer([walker, standing, random_motion(frames=30, seed=2)], port=0,
                          meshes=[None, (wide, np.array([[0, 1, 1]])), None])
    try:
        ranges = []
        for i in range(3):
            xs = [viewer._joints[i][..., 0]] + ([] if viewer._meshes[i] is None else [viewer._meshes[i][0][..., 0]])
            ranges.append((min(x.min() for x in xs), max(x.max() for x in xs)))
        assert viewer.margin > 0
        for (_, high), (low, _) in zip(ranges, ranges[1:]):
            assert low - high == pytest.approx(viewer.margin, abs=1e-4)
        assert ranges[1][1] - ranges[1][0] == pytest.approx(3.0, abs=1e-4)   # the surface's width counted
        assert ranges[0][0] == pytest.approx(-ranges[-1][1], abs=1e-4)       # centred on X = 0
    finally:
        viewer.stop()
    fixed = MotionViewer([standing, standing], port=0, spacing=2.0)   # an explicit spacing: origins that far apart
    try:
        assert fixed.offsets[1, 0] - fixed.offsets[0, 0] == pytest.approx(2.0)
    finally:
        fixed.stop()


def test_motions_stand_in_one_row_framed_below_the_top_left_notices():
    """Motions far apart in depth (video capture puts a person metres in front of its camera)
    stand in one row (Z centred on 0); the first view keeps the top 30% of its height free, the
    labels included, where the client shows its notices (Chromium's software-WebGL notice hid
    the 'prediction' label)."""
    near = random_motion(frames=30, seed=0)
    far = dataclasses.replace(random_motion(frames=30, seed=1),
                              root_positions=random_motion(frames=30, seed=1).root_positions + torch.tensor([0.0, 0, -3.0]))
    viewer = MotionViewer([near, far], labels=["prediction", "truth"], port=0)
    try:
        for joints in viewer._joints:
            assert (joints[..., 2].min() + joints[..., 2].max()) / 2 == pytest.approx(0.0, abs=1e-4)
        camera = viewer.server.initial_camera
        position, look = np.array(camera.position, float), np.array(camera.look_at, float)
        forward = (look - position) / np.linalg.norm(look - position)
        up = np.array([0.0, 1, 0]) - forward[1] * forward
        up /= np.linalg.norm(up)
        half_view = np.tan(np.radians(75.0) / 2)
        for i in range(2):
            top = np.array(viewer._label_position(i, 0)) + [0, LABEL_HEIGHT - LABEL_GAP, 0]
            ray = top - position
            height = (ray @ up) / (ray @ forward) / half_view   # +1: the view's top edge, -1: its bottom
            assert height <= 0.4 + 1e-3, f"label {i} reaches {(1 - height) / 2:.0%} from the view's top"
    finally:
        viewer.stop()


def test_rejects_mismatched_labels():
    with pytest.raises(ValueError, match="labels"):
        MotionViewer([random_motion()], labels=["a", "b"], port=0)


# -- in a browser -------------------------------------------------------------------------

class DevTools:
    """Minimal Chrome DevTools protocol client on one page target.

    A reader thread takes every message as it comes: answers go to the waiting call, events
    are recorded, and workers the page starts are set up at once (see watch_network).
    """

    def __init__(self, ws_url: str):
        from websockets.sync.client import connect

        self.ws = connect(ws_url, max_size=None, open_timeout=10)
        self.ids = itertools.count(1)
        self.events: list[dict] = []
        self.answers: dict[int, dict] = {}
        self.arrived = threading.Condition()
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self) -> None:
        try:
            for raw in self.ws:
                message = json.loads(raw)
                if "id" in message:
                    with self.arrived:
                        self.answers[message["id"]] = message
                        self.arrived.notify_all()
                elif "method" in message:
                    self.events.append(message)
                    if message["method"] == "Target.attachedToTarget":
                        self._watch_session(message["params"]["sessionId"])
        except Exception:  # connection closed
            pass

    def send(self, method: str, session: str | None = None, **params) -> int:
        """Send a command; returns its id without waiting for the answer."""
        call_id = next(self.ids)
        message = {"id": call_id, "method": method, "params": params}
        if session:
            message["sessionId"] = session
        self.ws.send(json.dumps(message))
        return call_id

    def call(self, method: str, timeout: float = 15.0, **params) -> dict:
        call_id = self.send(method, **params)
        with self.arrived:
            if not self.arrived.wait_for(lambda: call_id in self.answers, timeout=timeout):
                raise TimeoutError(f"DevTools {method}: no answer in {timeout} s")
            message = self.answers.pop(call_id)
        if "error" in message:
            raise RuntimeError(f"{method}: {message['error']}")
        return message["result"]

    def watch_network(self) -> None:
        """Record network events of the page and of the workers it starts (viser talks to its
        server from a web worker), each worker held at start until its recording is on."""
        self.call("Network.enable")
        self.call("Target.setAutoAttach", autoAttach=True, waitForDebuggerOnStart=True, flatten=True)

    def _watch_session(self, session: str) -> None:
        self.send("Network.enable", session)
        self.send("Target.setAutoAttach", session, autoAttach=True, waitForDebuggerOnStart=True, flatten=True)
        self.send("Runtime.runIfWaitingForDebugger", session)

    def requested_urls(self) -> list[str]:
        """Every URL requested so far, websockets included."""
        events = list(self.events)
        urls = [e["params"]["request"]["url"] for e in events if e["method"] == "Network.requestWillBeSent"]
        return urls + [e["params"]["url"] for e in events if e["method"] == "Network.webSocketCreated"]

    def screenshot(self) -> np.ndarray:
        from PIL import Image

        data = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))

    def close(self) -> None:
        try:
            self.ws.close()
        except Exception:
            pass
        self.reader.join(timeout=5)


@contextlib.contextmanager
def headless_chromium(profile: Path, width: int = 1000, height: int = 700):
    """Start headless Chromium with a fresh profile; yield a DevTools client on its blank page."""
    profile.mkdir(parents=True, exist_ok=True)
    process = subprocess.Popen(
        [CHROMIUM, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", "--remote-debugging-port=0",
         f"--window-size={width},{height}", "about:blank"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    devtools = None
    try:
        port_file = profile / "DevToolsActivePort"
        deadline = time.monotonic() + 20
        while not (port_file.exists() and port_file.read_text().strip()):
            if process.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"Chromium did not start (exit code {process.poll()})")
            time.sleep(0.05)
        port = int(port_file.read_text().split()[0])
        targets: list = []
        while not targets:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=5) as answer:
                targets = [t for t in json.load(answer) if t.get("type") == "page"]
            if not targets:
                if time.monotonic() > deadline:
                    raise RuntimeError("Chromium opened no page")
                time.sleep(0.05)
        devtools = DevTools(targets[0]["webSocketDebuggerUrl"])
        yield devtools
    finally:
        if devtools is not None:
            try:
                devtools.call("Browser.close", timeout=3)
            except Exception:
                pass
            devtools.close()
        try:
            process.wait(timeout=5)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait(timeout=5)
        shutil.rmtree(profile, ignore_errors=True)


@pytest.fixture
def chromium(tmp_path):
    """A headless Chromium with a DevTools connection to a blank page; ended afterwards."""
    if not os.path.exists(CHROMIUM):
        pytest.skip(f"{CHROMIUM} not found: install Debian's chromium package to run browser tests")
    with headless_chromium(tmp_path / "chromium-profile") as devtools:
        yield devtools


def colour_mask(image: np.ndarray, rgb, tolerance: int = 40) -> np.ndarray:
    return (np.abs(image.astype(np.int16) - np.array(rgb, dtype=np.int16)) <= tolerance).all(axis=-1)


def wait_for(condition, timeout: float, what: str, interval: float = 0.2):
    deadline = time.monotonic() + timeout
    while True:
        value = condition()
        if value is not None and value is not False and not (isinstance(value, (dict, list)) and not value):
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(interval)


# Hide every page element but the WebGL canvas (the control panel, notifications and the axes
# gizmo share colours with the skeletons), so a screenshot shows only what WebGL drew.
CANVAS_ONLY = """(() => {
  const style = document.createElement('style');
  style.id = 'canvas-only';
  style.textContent = 'body * {visibility: hidden !important} canvas {visibility: visible !important}';
  document.head.appendChild(style);
  return document.querySelectorAll('canvas').length;
})()"""
SHOW_ALL = "document.getElementById('canvas-only')?.remove()"


def drawn(image: np.ndarray, rgb, minimum: int) -> np.ndarray | None:
    """Mask of pixels of a colour when there are at least `minimum` of them, else None."""
    mask = colour_mask(image, rgb)
    return mask if mask.sum() >= minimum else None


@pytest.mark.browser
def test_renders_skeletons_in_headless_chromium(chromium, tmp_path):
    from PIL import Image

    started = time.monotonic()
    motions = [random_motion(frames=30, seed=0, name="prediction"), random_motion(frames=30, seed=3, name="truth")]
    viewer = MotionViewer(motions, port=0)
    port = viewer.port
    orange, blue = viewer.colors
    try:
        chromium.watch_network()
        chromium.call("Page.enable")
        chromium.call("Page.navigate", url=viewer.url)

        # 1. The page's viser client connected (it reports its camera once its scene is up).
        clients = wait_for(lambda: viewer.server.get_clients(), 30, "the browser to connect")
        assert len(clients) == 1
        for i in range(2):
            assert viewer.server.scene.get_handle_by_name(f"/motions/{i}/bones") is not None

        # 2. The WebGL canvas alone shows both skeletons in their bone colours: the first on the
        # left, the second on the right, each standing (many rows tall). Nodes fade in, so wait
        # until the colours are drawn at full strength.
        assert wait_for(lambda: chromium.call("Runtime.evaluate", expression=CANVAS_ONLY, returnByValue=True)
                        ["result"].get("value"), 15, "a canvas on the page") >= 1

        def both_skeletons():
            image = chromium.screenshot()
            left, right = drawn(image, orange, 300), drawn(image, blue, 300)
            return (image, left, right) if left is not None and right is not None else None

        canvas, left, right = wait_for(both_skeletons, 30, "both skeletons drawn in the canvas", interval=0.3)
        Image.fromarray(canvas).save(tmp_path / "canvas.png")
        assert np.nonzero(left)[1].mean() < np.nonzero(right)[1].mean(), "first motion should be left of the second"
        for mask in (left, right):
            rows = np.nonzero(mask)[0]
            assert rows.max() - rows.min() > 100, "a standing skeleton should span many rows"

        # 3. Moving the timeline moves the drawn skeleton.
        viewer.set_frame(20)
        wait_for(lambda: (colour_mask(chromium.screenshot(), orange) != left).sum() > 100, 15,
                 "the picture to change after set_frame(20)", interval=0.3)

        # 4. The Play button in the page drives playback on the server, and Pause stops it.
        def click(label: str) -> bool:
            return chromium.call("Runtime.evaluate", returnByValue=True, expression=f"""(() => {{
                const button = [...document.querySelectorAll('button')].find(b => b.textContent.trim() === {label!r});
                if (button) button.click();
                return Boolean(button);
            }})()""")["result"]["value"]

        wait_for(lambda: click("Play"), 10, "a Play button")
        wait_for(lambda: viewer.playing, 10, "playback to start from the page")
        wait_for(lambda: click("Pause"), 10, "the button to turn into Pause")
        wait_for(lambda: not viewer.playing, 10, "playback to pause from the page")
        viewer.set_frame(20)

        # 5. The page with its controls, kept for people to look at.
        chromium.call("Runtime.evaluate", expression=SHOW_ALL)
        page = chromium.screenshot()
        Image.fromarray(page).save(tmp_path / "viewer.png")
        if os.environ.get("HUMOTION_VIEWER_SCREENSHOT"):
            Image.fromarray(page).save(os.environ["HUMOTION_VIEWER_SCREENSHOT"])

        # 6. A render the server asks of the browser's WebGL renderer shows the skeleton too.
        client = next(iter(viewer.server.get_clients().values()))
        render = client.get_render(height=300, width=400, transport_format="png", timeout=20)
        assert render.shape == (300, 400, 4)
        assert colour_mask(render[..., :3], orange).sum() > 30 and colour_mask(render[..., :3], blue).sum() > 30

        # 7. Offline: everything the page loaded came from the viewer's own server.
        urls = chromium.requested_urls()
        local = (f"http://127.0.0.1:{port}", f"ws://127.0.0.1:{port}", "data:", "blob:")
        assert any(u.startswith("ws://") for u in urls), "no websocket recorded"
        assert [u for u in urls if not u.startswith(local)] == []

        # 8. Stopping with the browser still connected is quick and frees the port: a new
        # viewer gets the very same port.
        stop_started = time.monotonic()
        viewer.stop()
        assert time.monotonic() - stop_started < 4.5  # viser alone waits 5 s for idle sockets
        again = MotionViewer(motions[0], port=port)
        try:
            assert again.port == port
        finally:
            again.stop()
    finally:
        viewer.stop()
    assert time.monotonic() - started < 60

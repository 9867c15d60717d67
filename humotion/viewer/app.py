"""A browser viewer for Motions: skeletons as lines and points, a timeline, playback.

Built on viser, which serves its own prebuilt web client from its wheel, so the viewer works
with no network beyond the local socket. World positions are computed once with forward
kinematics when the viewer starts; showing a frame only sends the precomputed bone segments
and joint points of each motion (one line-segment node and one point-cloud node per motion).

Several motions are shown side by side along X (e.g. prediction and ground truth). Motions of
different frame rates or lengths share one timeline driven by time: timeline frame k is the time
k / fps of the fastest motion; each motion shows its frame at that time, holding its last frame
once it has ended.

    from humotion.viewer import MotionViewer
    viewer = MotionViewer([predicted, truth], labels=["prediction", "truth"])
    viewer.run()                # logs its address (INFO, humotion.viewer), serves until Ctrl-C

Mesh mode: a motion can carry a triangle mesh with one set of vertices per frame (a posed body
of humotion.body), drawn instead of its bones and joints and sent per frame like them:

    MotionViewer([rig_motion], meshes=[(vertices, faces)])    # (T, V, 3) metres, (faces, 3)
"""

from __future__ import annotations

import contextlib
import io
import logging
import math
import threading
import time
from collections.abc import Sequence

import numpy as np

from humotion.motion import Motion

log = logging.getLogger(__name__)

#: Bone colours (RGB, 0-255) given to motions in order; joint points are a darker shade.
PALETTE: tuple[tuple[int, int, int], ...] = (
    (235, 110, 20),   # orange
    (30, 120, 235),   # blue
    (40, 170, 70),    # green
    (200, 40, 160),   # magenta
    (120, 80, 220),   # violet
    (20, 170, 180),   # teal
)

#: Default gap between neighbouring motions, in tallest-skeleton heights: labels are drawn at a
#: fixed size on screen, and at this gap two words fit between standing people framed together.
LAYOUT_MARGIN: float = 0.75

#: A label's bottom above its motion's highest joint, and the label's top above it (metres).
LABEL_GAP: float = 0.25
#: The colour a surface is drawn in (and its motion's legend square), 0-255 RGB.
MESH_COLOR: tuple[int, int, int] = (200, 190, 180)
LABEL_HEIGHT: float = 0.45

SPEEDS: tuple[str, ...] = ("0.1x", "0.25x", "0.5x", "1x", "2x", "4x")


def bone_segments(motion: Motion) -> tuple[np.ndarray, np.ndarray]:
    """Bones of every frame, computed once by forward kinematics.

    Returns (segments (T, S, 2, 3), joints (T, J, 3)) as float32 numpy arrays in metres: one
    segment from each non-root joint to its parent, then one from each end site to its joint.
    """
    skeleton = motion.skeleton
    joints = motion.world_positions().detach().cpu().numpy().astype(np.float32)
    starts = [joints[:, p] for p in skeleton.parents[1:]]
    ends = [joints[:, j] for j in range(1, skeleton.num_joints)]
    if skeleton.end_site_parents:
        sites = motion.end_site_positions().detach().cpu().numpy().astype(np.float32)
        starts += [joints[:, p] for p in skeleton.end_site_parents]
        ends += [sites[:, e] for e in range(sites.shape[1])]
    frames = joints.shape[0]
    if not starts:  # a one-joint skeleton has no bones
        return np.zeros((frames, 0, 2, 3), np.float32), joints
    segments = np.stack([np.stack(starts, axis=1), np.stack(ends, axis=1)], axis=2)
    return np.ascontiguousarray(segments, dtype=np.float32), joints


class MotionViewer:
    """Serve one or several motions in a browser, side by side, with a timeline.

    The server starts when the object is made and runs in background threads, so the
    constructor returns at once: call :meth:`run` to block until Ctrl-C, or drive it from code
    (:meth:`set_frame`, :meth:`play`, :meth:`pause`) and :meth:`stop` it. It is also a context
    manager that stops on exit.

    motions: a Motion or a sequence of them.
    labels: one name per motion (default: each motion's name, else "motion i").
    host, port: where to listen; if the port is taken the next free one is used (see
        :attr:`url`), and port=0 lets the system choose.
    spacing: metres between neighbouring motions' origins along X; 0 overlays them. By default
        each motion is moved along X by its own width (its joints and surface over all frames)
        plus a margin of LAYOUT_MARGIN times the tallest skeleton's height, so neither bodies nor
        their labels overlap (:attr:`offsets`, :attr:`margin`); a single motion is not moved.
    colors: one RGB (0-255) bone colour per motion (default: :data:`PALETTE`).
    thickness: bone thickness in metres; joint_size: joint point size in metres.
    loop: start with looping playback on; autoplay: start playing at once.
    meshes: None, or per motion None or (vertices (T, V, 3) in metres, one row per frame of the
        motion; faces (faces, 3) vertex indices): a surface that follows the motion's frames.
    verbose: let viser print its start-up banner and connection messages (otherwise standard
        output is silenced while the server starts and stops).
    """

    def __init__(
        self,
        motions: Motion | Sequence[Motion],
        labels: Sequence[str] | None = None,
        *,
        host: str = "127.0.0.1",
        port: int = 8080,
        spacing: float | None = None,
        colors: Sequence[tuple[int, int, int]] | None = None,
        thickness: float = 0.02,
        joint_size: float = 0.04,
        loop: bool = True,
        autoplay: bool = False,
        verbose: bool = False,
        meshes: Sequence[tuple[np.ndarray, np.ndarray] | None] | None = None,
    ):
        import viser  # imported here so `import humotion` never pays for the web server

        self.motions: list[Motion] = [motions] if isinstance(motions, Motion) else list(motions)
        if not self.motions:
            raise ValueError("MotionViewer needs at least one Motion")
        if labels is None:
            labels = [m.name or f"motion {i}" for i, m in enumerate(self.motions)]
        self.labels: list[str] = [str(x) for x in labels]
        if len(self.labels) != len(self.motions):
            raise ValueError(f"{len(self.motions)} motions but {len(self.labels)} labels")
        colors = list(colors) if colors is not None else [PALETTE[i % len(PALETTE)] for i in range(len(self.motions))]
        if len(colors) < len(self.motions):
            raise ValueError(f"{len(self.motions)} motions but only {len(colors)} colours")
        self.colors: list[tuple[int, int, int]] = [tuple(int(c) for c in rgb) for rgb in colors[: len(self.motions)]]

        # -- timeline: frame k is at time k / fps, fps being the fastest motion's ----------
        self.fps: float = max(float(m.fps) for m in self.motions)
        last_time = max((m.num_frames - 1) / m.fps for m in self.motions)
        self.num_frames: int = int(math.floor(last_time * self.fps + 1e-6)) + 1
        times = np.arange(self.num_frames) / self.fps
        self._frame_of = [  # timeline frame -> frame of each motion
            np.minimum(np.floor(times * m.fps + 1e-6).astype(np.int64), m.num_frames - 1) for m in self.motions
        ]

        # -- geometry, computed once -----------------------------------------------------
        count = len(self.motions)
        placed = [bone_segments(motion) for motion in self.motions]
        self._meshes = _checked_meshes(meshes, self.motions)
        self.spacing: float | None = None if spacing is None else float(spacing)
        self.offsets = np.zeros((count, 3), np.float32)
        if self.spacing is None:  # each motion's own width (skeleton and surface, every frame) plus a margin
            tallest = max(m.skeleton.height() for m in self.motions)
            self.margin = LAYOUT_MARGIN * (tallest if tallest > 0 else 1.0)
            extents = np.array([[_extent(joints, mesh, axis) for axis in (0, 2)]
                                for (_, joints), mesh in zip(placed, self._meshes)])   # (M, X/Z, low/high)
            if count > 1:   # one motion stays where it is
                self.offsets[:, 0] = side_by_side(extents[:, 0], self.margin)
                # ... and each is centred on Z = 0: one row, none standing metres behind the others
                # (video capture puts its people where the camera saw them, metres in front of it)
                self.offsets[:, 2] = -extents[:, 1].mean(axis=1)
        else:
            self.margin = None
            self.offsets[:, 0] = (np.arange(count) - (count - 1) / 2) * self.spacing
        self._segments: list[np.ndarray] = [segments + offset for (segments, _), offset in zip(placed, self.offsets)]
        self._joints: list[np.ndarray] = [joints + offset for (_, joints), offset in zip(placed, self.offsets)]
        self._meshes = [None if mesh is None else (mesh[0] + offset, mesh[1])
                        for mesh, offset in zip(self._meshes, self.offsets)]

        # -- server ------------------------------------------------------------------------
        quiet = contextlib.nullcontext() if verbose else contextlib.redirect_stdout(io.StringIO())
        with quiet:
            self.server = viser.ViserServer(host=host, port=port, label="humotion", verbose=verbose)
        self.host = host
        self.verbose = verbose
        self._lock = threading.RLock()
        self._frame = -1
        self._time = 0.0
        self._playing = False
        self._stopped = threading.Event()
        self._wake = threading.Event()
        try:
            self._build_scene(thickness, joint_size)
            self._build_gui(loop)
            self.set_frame(0)
        except BaseException:
            self.server.stop()
            raise
        self._thread = threading.Thread(target=self._playback, name="humotion-viewer-playback", daemon=True)
        self._thread.start()
        if autoplay:
            self.play()

    # -- public ---------------------------------------------------------------------------
    @property
    def port(self) -> int:
        """The port actually listened on."""
        return self.server.get_port()

    @property
    def url(self) -> str:
        """Address to open in a browser."""
        host = "localhost" if self.host in ("0.0.0.0", "::", "") else self.host
        return f"http://{host}:{self.port}"

    @property
    def frame(self) -> int:
        """Timeline frame shown now."""
        return self._frame

    @property
    def duration(self) -> float:
        """Seconds covered by the timeline: num_frames / fps."""
        return self.num_frames / self.fps

    @property
    def playing(self) -> bool:
        return self._playing

    def motion_frames(self, frame: int) -> list[int]:
        """Frame of each motion shown at a timeline frame."""
        return [int(f[frame]) for f in self._frame_of]

    def set_frame(self, frame: int) -> None:
        """Show a timeline frame (clamped to the timeline) and move the slider there."""
        frame = int(min(max(int(frame), 0), self.num_frames - 1))
        with self._lock:
            self._time = frame / self.fps
            self._show(frame)

    def set_time(self, seconds: float) -> None:
        """Show the timeline frame at a time in seconds."""
        self.set_frame(int(math.floor(seconds * self.fps + 1e-6)))

    def play(self) -> None:
        """Start playback (in real time times the selected speed) from the current frame."""
        with self._lock:
            if self._frame >= self.num_frames - 1 and not self._loop.value:
                self.set_frame(0)
            self._playing = True
            self._play_button.label = "Pause"
            self._play_button.icon = viser_icon("PLAYER_PAUSE")
        self._wake.set()

    def pause(self) -> None:
        """Stop playback on the current frame."""
        with self._lock:
            self._playing = False
            self._play_button.label = "Play"
            self._play_button.icon = viser_icon("PLAYER_PLAY")

    def stop(self) -> None:
        """Stop playback and the server; frees the port. Safe to call more than once."""
        if self._stopped.is_set():
            return
        self._stopped.set()
        self._wake.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)
        helper = threading.Thread(target=_abort_idle_connections, args=(self.server,), daemon=True)
        helper.start()
        quiet = contextlib.nullcontext() if self.verbose else contextlib.redirect_stdout(io.StringIO())
        with quiet:
            self.server.stop()
        helper.join(timeout=1.0)

    def run(self) -> None:
        """Log the address (INFO; the commands print it) and serve until Ctrl-C (or :meth:`stop` from
        another thread)."""
        log.info("humotion viewer: open %s in a browser (Ctrl-C to stop)", self.url)
        try:
            while not self._stopped.wait(0.5):
                pass
        except KeyboardInterrupt:
            pass
        finally:
            self.stop()

    def __enter__(self) -> "MotionViewer":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def __repr__(self) -> str:
        state = "stopped" if self._stopped.is_set() else self.url
        return f"MotionViewer({len(self.motions)} motions, {self.num_frames} frames at {self.fps:g} fps, {state})"

    # -- scene --------------------------------------------------------------------------
    def _build_scene(self, thickness: float, joint_size: float) -> None:
        scene = self.server.scene
        scene.set_up_direction("+y")
        everything = np.concatenate([j.reshape(-1, 3) for j in self._joints]
                                    + [s.reshape(-1, 3) for s in self._segments])
        low, high = everything.min(axis=0), everything.max(axis=0)
        centre = (low + high) / 2
        size = float(max(high[0] - low[0], high[2] - low[2])) + 2.0
        size = float(math.ceil(size))
        scene.add_grid("/ground", width=size, height=size, plane="xz", cell_size=0.5, section_size=1.0,
                       position=(float(centre[0]), 0.0, float(centre[2])))

        # Frame the first frame of every motion with its label, seen from the front (characters
        # face +Z) and a little above, filling about 60% of the view's height (75 degree vertical
        # field of view) or of its width for a view about 1.1 times wider than tall; in the lower
        # part of the view (the top 30% left free, the labels included), so that nothing hides
        # behind the notices the client shows in the top left corner (e.g. Chromium's "software
        # WebGL rendering").
        first = np.concatenate([j[0] for j in self._joints])
        f_low, f_high = first.min(axis=0), first.max(axis=0)
        f_high[1] += LABEL_HEIGHT
        look = (f_low + f_high) / 2
        width, height = float(f_high[0] - f_low[0]), float(f_high[1] - f_low[1])
        half_view = math.tan(math.radians(75.0) / 2)
        distance = max(height / (1.2 * half_view), width / (1.2 * half_view * 1.1), 1.0)
        look[1] += 0.2 * distance * half_view   # the view's centre 10% of its height above the content's
        self.server.initial_camera.look_at = tuple(float(x) for x in look)
        self.server.initial_camera.position = (float(look[0]), float(look[1]) + 0.3 * distance,
                                               float(f_high[2]) + distance)

        self._bones = []
        self._points = []
        self._tags = []
        for i, (label, rgb) in enumerate(zip(self.labels, self.colors)):
            dark = tuple(int(c * 0.55) for c in rgb)
            self._bones.append(scene.add_line_segments(
                f"/motions/{i}/bones", self._segments[i][0], rgb, thickness=thickness))
            self._points.append(scene.add_point_cloud(
                f"/motions/{i}/joints", self._joints[i][0], dark, point_size=joint_size,
                point_shape="circle", precision="float32", point_shading="flat"))
            self._tags.append(scene.add_label(f"/motions/{i}/label", label, position=self._label_position(i, 0),
                                             anchor="bottom-center"))
        self._mesh_handles = [None if mesh is None else scene.add_mesh_simple(
            f"/motions/{i}/mesh", mesh[0][0], mesh[1], color=MESH_COLOR) for i, mesh in enumerate(self._meshes)]
        for i, handle in enumerate(self._mesh_handles):  # a surface replaces its skeleton's bones and joints
            if handle is not None:
                self._bones[i].visible = self._points[i].visible = False

    def _label_position(self, i: int, motion_frame: int) -> tuple[float, float, float]:
        joints = self._joints[i][motion_frame]
        top = joints[int(np.argmax(joints[:, 1]))]
        return (float(joints[0, 0]), float(top[1]) + LABEL_GAP, float(joints[0, 2]))

    def _show(self, frame: int) -> None:
        """Send timeline frame `frame` to the browsers (call with the lock held)."""
        if frame == self._frame:
            return
        self._frame = frame
        with self.server.atomic():
            for i, frame_of in enumerate(self._frame_of):
                k = int(frame_of[frame])
                self._bones[i].points = self._segments[i][k]
                self._points[i].points = self._joints[i][k]
                self._tags[i].position = self._label_position(i, k)
                if self._mesh_handles[i] is not None:
                    self._mesh_handles[i].vertices = self._meshes[i][0][k]
            self._slider.value = frame
            self._readout.content = self._readout_text(frame)

    def _readout_text(self, frame: int) -> str:
        text = (f"**Frame** {frame} / {self.num_frames - 1}  \n"
                f"**Time** {frame / self.fps:.2f} / {(self.num_frames - 1) / self.fps:.2f} s at {self.fps:g} fps")
        if len(self.motions) > 1:
            own = self.motion_frames(frame)
            text += "  \n" + "  \n".join(f"{label}: frame {k}" for label, k in zip(self.labels, own))
        return text

    # -- GUI ----------------------------------------------------------------------------
    def _build_gui(self, loop: bool) -> None:
        gui = self.server.gui
        # No share button (it needs the internet); the panel docked right so that the 3D view
        # beside it is centred on the skeletons.
        gui.configure_theme(show_share_button=False)
        gui.main_panel.dock_right()
        gui.add_markdown(legend(self.labels, self.colors, self.motions, self._meshes))
        with gui.add_folder("Timeline"):
            self._slider = gui.add_slider("Frame", min=0, max=max(self.num_frames - 1, 1), step=1, initial_value=0,
                                          disabled=self.num_frames < 2)
            self._play_button = gui.add_button("Play", icon=viser_icon("PLAYER_PLAY"))
            self._step = gui.add_button_group("Step", ("|<", "<", ">", ">|"))
            self._speed = gui.add_dropdown("Speed", SPEEDS, initial_value="1x")
            self._loop = gui.add_checkbox("Loop", loop)
            self._readout = gui.add_markdown(self._readout_text(0))

        @self._slider.on_update
        def _(_event) -> None:
            with self._lock:
                if int(self._slider.value) != self._frame:
                    self.set_frame(int(self._slider.value))

        @self._play_button.on_click
        def _(_event) -> None:
            if self._playing:
                self.pause()
            else:
                self.play()

        @self._step.on_click
        def _(_event) -> None:
            choice = self._step.value
            self.pause()
            target = {"|<": 0, "<": self._frame - 1, ">": self._frame + 1, ">|": self.num_frames - 1}[choice]
            self.set_frame(target)

    @property
    def speed(self) -> float:
        """Playback speed factor chosen in the GUI."""
        return float(self._speed.value.rstrip("x"))

    # -- playback -----------------------------------------------------------------------
    def _playback(self) -> None:
        last = time.perf_counter()
        while not self._stopped.is_set():
            if not self._playing:
                self._wake.wait(0.2)
                self._wake.clear()
                last = time.perf_counter()
                continue
            now = time.perf_counter()
            with self._lock:
                if not self._playing:
                    continue
                self._time += (now - last) * self.speed
                frame = int(math.floor(self._time * self.fps + 1e-6))
                if frame >= self.num_frames:
                    if self._loop.value:
                        self._time %= self.duration
                        frame = int(math.floor(self._time * self.fps + 1e-6)) % self.num_frames
                    else:
                        frame = self.num_frames - 1
                        self._time = frame / self.fps
                        self.pause()
                self._show(frame)
                wait = ((frame + 1) / self.fps - self._time) / self.speed
            last = now
            self._stopped.wait(min(max(wait, 0.002), 0.1))


def side_by_side(extents: np.ndarray, margin: float) -> np.ndarray:
    """X offsets (M,) that line up M things left to right, `margin` apart, centred on X = 0.

    Args:
        extents (M x 2 array, metres): each thing's lowest and highest X before moving.
        margin: the gap in metres between one thing's highest X and the next one's lowest.
    Returns:
        offsets (M array, metres) to add to each thing's X.
    """
    extents = np.asarray(extents, dtype=np.float64).reshape(-1, 2)
    widths = extents[:, 1] - extents[:, 0]
    lows = np.concatenate([[0.0], np.cumsum(widths + margin)[:-1]])  # where each thing's lowest X goes
    total = widths.sum() + margin * (len(widths) - 1)
    return lows - total / 2 - extents[:, 0]


def _extent(joints: np.ndarray, mesh: tuple[np.ndarray, np.ndarray] | None, axis: int) -> tuple[float, float]:
    """(lowest, highest) coordinate `axis` (0: X, 2: Z) of joints (T, J, 3) and a surface's
    vertices (T, V, 3) over all frames, metres."""
    values = [joints[..., axis].min(), joints[..., axis].max()]
    if mesh is not None:
        values += [mesh[0][..., axis].min(), mesh[0][..., axis].max()]
    return float(min(values)), float(max(values))


def _checked_meshes(meshes, motions: list[Motion]) -> list[tuple[np.ndarray, np.ndarray] | None]:
    """MotionViewer's meshes checked against the motions: per motion None or (vertices (T, V, 3)
    float32, faces (faces, 3) uint32)."""
    if meshes is None:
        return [None] * len(motions)
    if len(meshes) != len(motions):
        raise ValueError(f"{len(motions)} motions but {len(meshes)} meshes (use None for a motion without one)")
    placed = []
    for i, (mesh, motion) in enumerate(zip(meshes, motions)):
        if mesh is None:
            placed.append(None)
            continue
        vertices, faces = np.asarray(mesh[0], dtype=np.float32), np.asarray(mesh[1], dtype=np.uint32)
        if vertices.ndim != 3 or vertices.shape[0] != motion.num_frames or vertices.shape[2] != 3 or faces.shape[1:] != (3,):
            raise ValueError(f"mesh {i} must be vertices ({motion.num_frames}, V, 3) and faces (T, 3), "
                             f"got {vertices.shape} and {faces.shape}")
        placed.append((vertices, faces))
    return placed


def _abort_idle_connections(server, period: float = 0.05, limit: float = 6.0) -> None:
    """While `server` shuts down, cancel connections that never sent a request.

    Browsers open spare ("preconnect") sockets that stay silent; the websockets server waits
    for each to time out (10 s) before its thread ends, which made stop() take seconds.
    Best effort: does nothing if the internals it looks at change.
    """
    import asyncio

    from websockets.protocol import State

    def abort() -> None:
        for task in asyncio.all_tasks():
            coro = task.get_coro()
            if getattr(coro, "__qualname__", "") != "Server.conn_handler" or getattr(coro, "cr_frame", None) is None:
                continue
            protocol = getattr(coro.cr_frame.f_locals.get("connection"), "protocol", None)
            if getattr(protocol, "state", None) is State.CONNECTING:
                task.cancel()

    try:
        loop = server.get_event_loop()
    except Exception:
        return
    deadline = time.monotonic() + limit
    while time.monotonic() < deadline and not loop.is_closed():
        try:
            loop.call_soon_threadsafe(abort)
        except RuntimeError:  # loop closed meanwhile
            return
        time.sleep(period)


def viser_icon(name: str):
    """A viser Icon by name, or None when this viser lacks it (icons are cosmetic)."""
    import viser

    return getattr(viser.Icon, name, None)


def serve(
    motions: Motion | Sequence[Motion],
    labels: Sequence[str] | None = None,
    host: str = "127.0.0.1",
    port: int = 8080,
    open_browser: bool = False,
    **options,
) -> None:
    """Show motions in a browser and block until Ctrl-C: the one way the commands start the viewer.
    open_browser opens a tab at its address; other options as for :class:`MotionViewer`."""
    viewer = MotionViewer(motions, labels, host=host, port=port, **options)   # run() logs its address
    if open_browser:
        import webbrowser

        webbrowser.open(viewer.url)
    viewer.run()


def legend(labels: Sequence[str], colors: Sequence[tuple[int, int, int]], motions: Sequence[Motion],
           meshes: Sequence[object | None]) -> str:
    """The panel's markdown legend, a line per motion: a square in the colour it is drawn in (its
    own, or MESH_COLOR when a surface replaces its skeleton), its label, frames, rate and joints."""
    def count(n: int, noun: str) -> str:
        return f"{n} {noun}" if n == 1 else f"{n} {noun}s"
    return "  \n".join(
        f"<span style='color:rgb{MESH_COLOR if mesh is not None else rgb}'>&#9632;</span> **{label}**: "
        f"{count(m.num_frames, 'frame')}, {m.fps:g} fps, {count(m.skeleton.num_joints, 'joint')}"
        for label, rgb, m, mesh in zip(labels, colors, motions, meshes))

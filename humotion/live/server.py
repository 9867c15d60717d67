"""The ``humotion serve`` WebSocket server: headset frames in, body poses out, one SparseTracker
per connection (asyncio, the ``websockets`` library). Messages: humotion.live.protocol.

Bounds, so that one client never affects the others:

- size: a message over ``max_message`` bytes closes its connection (websockets' max_size);
- queue: at most ``max_queue`` received messages wait per connection (websockets' max_queue:
  beyond it the server stops reading that socket and TCP holds the client back);
- time: the opening handshake, the hello, each later message and each reply have timeouts
  (``open_timeout``, ``idle_timeout``, ``send_timeout``); keepalive pings find vanished peers;
- count: at most ``max_clients`` connections (more are refused at the handshake, HTTP 503), and a
  connection is closed after ``max_errors`` bad messages;
- fairness: the server yields to the other connections after every frame;
- lateness: a binary frame that is late (it waited over ``late_after`` seconds in the inbox, or
  more than ``max_backlog`` messages wait behind it) and has another binary frame waiting behind it
  is skipped (no pose for it), so a client the server cannot keep up with gets fewer poses, not
  older ones, while a client whose frames arrive in small bunches (its own jitter) loses none;
- no compression: frames and poses are small and binary; deflating them costs more CPU than
  the bytes it saves on loopback or a LAN;
- nothing from the wire is unpickled or evaluated: JSON (json.loads) and fixed struct layouts.

Every connection tracks in its server's one event-loop thread. To use more cores, several server
processes listen on one port (``workers``: SO_REUSEPORT, Linux and the BSDs), and the kernel
spreads new connections among them; each process has its own model, trackers and bounds
(``max_clients`` is per process).
"""

from __future__ import annotations

import asyncio
import collections
import functools
import hmac
import json
import logging
import warnings
from dataclasses import dataclass, field
from http import HTTPStatus
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np
from websockets.asyncio.server import ServerConnection, serve
from websockets.exceptions import ConnectionClosed

from humotion.live import protocol as pr

log = logging.getLogger("humotion.live")


@dataclass
class ServeSettings:
    """How ``humotion serve`` runs.

    host, port: where to listen (port 0: any free one). token: a shared secret clients must
    send (query string or hello), None: none. weights: the tracker's network (a name or a .pt
    file; None: the default). height: the standing height in metres for clients that state
    none (None: from each stream's eye height). vmc: (host, port) to forward every body to as VMC.
    body: a body GLB written by ``humotion body`` for the live page's avatar (None: one made at
    ``height``, 1.7 m without one; humotion.live.avatar).
    """

    host: str = "127.0.0.1"
    port: int = 8765
    token: str | None = None
    weights: str | None = None
    height: float | None = None
    vmc: tuple[str, int] | None = None
    body: str | None = None
    tls: tuple[str, str] | None = None
    max_clients: int = 32
    """Most connections at once, per worker."""
    workers: int = 1                 # run_worker starts the others
    """Server processes sharing the port, connections spread among them (one per free core)."""
    max_message: int = 4096          # bytes: a JSON frame is about 300, a binary one 96
    max_queue: int = 32              # received messages waiting per connection
    max_backlog: int = 4             # messages that may wait behind a binary frame before it is late
    late_after: float = 0.05         # seconds a binary frame may wait in the inbox before it is late
    max_errors: int = 20             # bad messages before a connection is closed
    open_timeout: float = 5.0        # seconds for the WebSocket handshake
    idle_timeout: float = 30.0       # seconds without a message before a connection is closed
    send_timeout: float = 5.0        # seconds a reply may wait for a client that does not read
    ping_interval: float = 10.0
    ping_timeout: float = 10.0


@dataclass
class Stats:
    """Counts over the server's life (read by tests and the bench)."""

    connections: int = 0
    refused: int = 0
    frames: int = 0
    skipped: int = 0
    errors: int = 0
    closed_for: dict = field(default_factory=dict)

    def close(self, reason: str) -> None:
        self.closed_for[reason] = self.closed_for.get(reason, 0) + 1


class LiveServer:
    """``async with LiveServer(settings) as server:`` serves until the block ends; server.port is
    the port it listens on."""

    def __init__(self, settings: ServeSettings):
        from humotion.sparse.tracker import load_weights

        self.settings = settings
        self.model = load_weights(settings.weights)        # once, shared by every connection's tracker
        self.stats = Stats()
        self._open = 0
        self._server = None
        self._avatar = None
        self.port = settings.port

    def _avatar_task(self) -> asyncio.Future:
        from humotion.live.avatar import make_avatar

        if self._avatar is None:
            self._avatar = asyncio.ensure_future(asyncio.to_thread(make_avatar, self.settings.height, self.settings.body))
        return self._avatar

    async def avatar(self):
        """The live page's avatar (humotion.live.avatar.Avatar): made once, in a worker thread
        (seconds), on the first call or the first request for the page; the command makes it
        before it listens."""
        return await asyncio.shield(self._avatar_task())

    async def __aenter__(self) -> "LiveServer":
        s = self.settings
        await asyncio.to_thread(self._warm_up)
        context = None
        if s.tls is not None:
            import ssl

            context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
            context.load_cert_chain(*s.tls)
        self._server = await serve(self._handle, s.host, s.port, ssl=context, max_size=s.max_message, max_queue=s.max_queue,
                                   open_timeout=s.open_timeout, compression=None, reuse_port=s.workers > 1, ping_interval=s.ping_interval,
                                   ping_timeout=s.ping_timeout, close_timeout=2.0, process_request=self._admit)
        self.port = self._server.sockets[0].getsockname()[1]
        return self

    def _warm_up(self) -> None:
        """Track two frames once before listening: a process's first update compiles and loads
        what the tracker needs (seconds; tens of seconds on a busy machine), which would
        otherwise stall the first client's first frame and, with it, every connection."""
        from humotion.sparse.recording import HeadsetFrame
        from humotion.sparse.tracker import SparseTracker

        tracker = SparseTracker(self.model, height=1.7)
        head, hand = (np.eye(3), np.array([0.0, 1.6, 0.0])), (np.eye(3), np.array([0.3, 1.2, 0.3]))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for t in (0.0, 0.05):
                tracker.update(HeadsetFrame(t, head, left=hand))

    async def __aexit__(self, *exc) -> None:
        self._server.close()
        await self._server.wait_closed()

    async def serve_forever(self) -> None:
        await self._server.serve_forever()

    def _admit(self, connection: ServerConnection, request):
        """Plain HTTP requests get the live page (web_response); a WebSocket beyond max_clients
        is refused (HTTP 503), as is one with a bad query string (400)."""
        if request.headers.get("Upgrade", "").lower() != "websocket":
            path = urlsplit(request.path).path
            if path in ("/", "/body.glb", "/body.json"):
                made = self._avatar_task()          # the page will ask for it: begin now (once)
                if path != "/":
                    return self._avatar_response(connection, made, path)
            return web_response(connection, path)
        if self._open >= self.settings.max_clients:
            self.stats.refused += 1
            return connection.respond(HTTPStatus.SERVICE_UNAVAILABLE, "too many connections\n")
        try:
            pr.hello_from_query(urlsplit(request.path).query)
        except pr.ProtocolError as error:
            self.stats.refused += 1
            return connection.respond(HTTPStatus.BAD_REQUEST, f"{error}\n")
        return None

    def _avatar_response(self, connection: ServerConnection, made: asyncio.Future, path: str):
        """/body.glb or /body.json; 503 with Retry-After while the body is being made (longer
        than a handshake may wait), 500 naming the problem when it could not be made."""
        if not made.done():
            response = connection.respond(HTTPStatus.SERVICE_UNAVAILABLE, "the body is being made: ask again in a second\n")
            response.headers["Retry-After"] = "1"
            return response
        if made.exception() is not None:
            return connection.respond(HTTPStatus.INTERNAL_SERVER_ERROR, f"no body: {made.exception()}\n")
        avatar = made.result()
        if path == "/body.glb":
            return file_response(connection, avatar.glb, "model/gltf-binary")
        return file_response(connection, json.dumps(avatar.table).encode(), "application/json")

    async def _handle(self, ws: ServerConnection) -> None:
        self._open += 1
        self.stats.connections += 1
        try:
            await Session(self, ws).run()
        finally:
            self._open -= 1

    def authorised(self, token: str | None) -> bool:
        """The client's token against the server's, compared in constant time."""
        if self.settings.token is None:
            return True
        return token is not None and hmac.compare_digest(token.encode(), self.settings.token.encode())


class Session:
    """One connection: its settings, its tracker, its VMC forward."""

    def __init__(self, server: LiveServer, ws: ServerConnection):
        self.server, self.ws, self.s = server, ws, server.settings
        self.hello = pr.hello_from_query(urlsplit(ws.request.path).query)
        self.axes = pr.Axes(self.hello.convention, self.hello.hand_frame)
        self.tracker = None
        self.vmc = None
        self.errors = 0
        self._skeleton = None

    async def run(self) -> None:
        try:
            await self._loop()
        except ConnectionClosed:
            self.server.stats.close("gone")
        except TimeoutError:
            self.server.stats.close("timeout")
            await self.ws.close(1008, "timed out")
        finally:
            if self.vmc is not None:
                self.vmc.close()

    async def _loop(self) -> None:
        inbox: collections.deque = collections.deque()         # messages read, not yet handled
        arrived, room = asyncio.Event(), asyncio.Event()
        reader = asyncio.create_task(self._read(inbox, arrived, room))
        try:
            await self._handle_all(inbox, arrived, room)
        finally:
            reader.cancel()

    async def _read(self, inbox: collections.deque, arrived: asyncio.Event, room: asyncio.Event) -> None:
        """Read messages into the inbox, at most max_queue waiting (then TCP holds the client
        back), each with the loop time it arrived at; the connection's end or silence is put in
        the inbox for the loop to raise."""
        loop = asyncio.get_running_loop()
        try:
            while True:
                while len(inbox) >= self.s.max_queue:
                    room.clear()
                    await room.wait()
                async with asyncio.timeout(self.s.idle_timeout):
                    message = await self.ws.recv()
                inbox.append((loop.time(), message))
                arrived.set()
        except (ConnectionClosed, TimeoutError) as error:
            inbox.append((loop.time(), error))
            arrived.set()

    async def _handle_all(self, inbox: collections.deque, arrived: asyncio.Event, room: asyncio.Event) -> None:
        started = False
        loop = asyncio.get_running_loop()
        while True:
            while not inbox:
                arrived.clear()
                await arrived.wait()
            at, raw = inbox.popleft()
            room.set()
            if isinstance(raw, BaseException):
                raise raw
            if started and isinstance(raw, bytes) and inbox and isinstance(inbox[0][1], bytes) and (
                    len(inbox) > self.s.max_backlog or loop.time() - at > self.s.late_after):
                self.server.stats.skipped += 1          # late, and a newer binary frame waits behind it: skipped
                continue
            try:
                message = pr.read_message(raw)
                if isinstance(message, dict) and message.get("type") == "hello":
                    if started:
                        raise pr.ProtocolError("hello: only as the first message")
                    self.hello = self.hello.updated(message, "hello")
                    self.axes = pr.Axes(self.hello.convention, self.hello.hand_frame)
                if not started:
                    started = True
                    if not self.server.authorised(self.hello.token):
                        self.server.stats.close("unauthorised")
                        await self.ws.close(1008, "a valid token is needed (query string or hello)")
                        return
                    await self._start()
                    if isinstance(message, dict) and message.get("type") == "hello":
                        await self._send(self._welcome())
                        continue
                await self._message(message)
            except pr.ProtocolError as error:
                self.errors += 1
                self.server.stats.errors += 1
                await self._send(f'{{"type": "error", "message": {_json_string(str(error))}}}')
                if self.errors >= self.s.max_errors:
                    self.server.stats.close("errors")
                    await self.ws.close(1008, f"{self.errors} bad messages")
                    return
            await asyncio.sleep(0)              # the other connections' turn

    async def _start(self) -> None:
        from humotion.sparse.tracker import SparseTracker

        height = self.hello.height if self.hello.height is not None else self.s.height
        self.tracker = await asyncio.to_thread(SparseTracker, self.server.model, height=height)
        if self.s.vmc is not None:
            from humotion.live.vmc import VmcSender

            self.vmc = VmcSender(self.s.vmc)

    def _welcome(self) -> str:
        import json

        from humotion.canonical import JOINTS, PARENTS

        return json.dumps({"type": "welcome", "version": pr.VERSION, "convention": self.hello.convention,
                           "hand_frame": self.hello.hand_frame, "joints": list(JOINTS), "parents": list(PARENTS),
                           "fps": self.tracker.fps})

    async def _message(self, message) -> None:
        kind = "frame" if isinstance(message, bytes) else message.get("type", "frame")
        if kind == "frame":
            binary = isinstance(message, bytes)
            frame = pr.frame_from_binary(message, self.axes) if binary else pr.frame_from_json(message, self.axes)
            await self._frame(frame, binary)
        elif kind == "calibrate":
            frame = pr.frame_from_json({k: v for k, v in message.items() if k != "type"} | {"t": 0.0}, self.axes)
            try:
                self.tracker.calibrate(frame)
            except ValueError as error:
                raise pr.ProtocolError(str(error)) from None
            await self._send_skeleton()
        elif kind == "reset":
            self.tracker.reset()
        else:
            raise pr.ProtocolError(f"unknown message type {kind!r}; expected hello, frame, calibrate or reset")

    async def _frame(self, frame: pr.HeadsetFrame, binary: bool) -> None:
        """Track one frame and answer with its pose, in binary when the frame came in binary."""
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")         # the gate's per-sample warnings; counted in tracker.rejected
                pose = self.tracker.update(frame)
        except ValueError as error:
            raise pr.ProtocolError(f"frame at t={frame.timestamp}: {error}") from None
        self.server.stats.frames += 1
        rotations, root, positions = pose.rotations.numpy(), pose.root_position.numpy(), pose.positions.numpy()
        if self.tracker.skeleton is not self._skeleton:
            await self._send_skeleton()
        reply = (pr.pose_binary if binary else pr.pose_json)(frame.timestamp, rotations, root, positions, self.axes)
        await self._send(reply)
        if self.vmc is not None:
            self.vmc.send(rotations, root, frame.timestamp, np.asarray(self.tracker.skeleton.offsets))

    async def _send_skeleton(self) -> None:
        self._skeleton = self.tracker.skeleton
        if self._skeleton is not None:
            await self._send(pr.skeleton_json(self._skeleton, self.axes))

    async def _send(self, message) -> None:
        async with asyncio.timeout(self.s.send_timeout):
            await self.ws.send(message)


WEB = Path(__file__).with_name("web")
WEB_FILES = {"/": ("index.html", "text/html; charset=utf-8"), "/live.js": ("live.js", "text/javascript")} | {
    f"/{name}": (name, "text/javascript") for name in (
        "vendor/three.module.js", "vendor/three.core.js", "vendor/addons/loaders/GLTFLoader.js",
        "vendor/addons/utils/BufferGeometryUtils.js", "vendor/addons/utils/SkeletonUtils.js")}


def web_response(connection: ServerConnection, path: str):
    """The live page's files (a fixed list: nothing else on disk is reachable), and /demo.json:
    the bundled demo clip's headset frames (OpenXR axes, forward hand frame) for its replay mode.
    (The avatar, /body.glb and /body.json, is LiveServer's.)"""
    if path == "/demo.json":
        body, kind = _demo_frames(), "application/json"
    elif path in WEB_FILES:
        name, kind = WEB_FILES[path]
        body = (WEB / name).read_bytes()
    else:
        return connection.respond(HTTPStatus.NOT_FOUND, "not found: this server has / (the live page) and "
                                  "WebSocket connections (docs/live.md)\n")
    return file_response(connection, body, kind)


def file_response(connection: ServerConnection, body: bytes, kind: str):
    """An HTTP 200 answer holding body, of MIME type kind, not to be cached."""
    response = connection.respond(HTTPStatus.OK, "")
    response.body = body
    del response.headers["Content-Type"], response.headers["Content-Length"]
    response.headers["Content-Type"] = kind
    response.headers["Content-Length"] = str(len(body))
    response.headers["Cache-Control"] = "no-cache"
    return response


@functools.cache
def _demo_frames() -> bytes:
    import torch

    from humotion.assets import demo_clip_path
    from humotion.canonical import to_canonical
    from humotion.io import load_motion
    from humotion.sparse.recording import stream_from_motion

    truth = to_canonical(load_motion(demo_clip_path())).resample(90.0)
    stream = stream_from_motion(truth, "HT", generator=torch.Generator().manual_seed(0))
    frames = pr.stream_frames(stream, "openxr", "forward")
    rounded = [[round(t, 6), *[None if d is None else [round(v, 6) for v in d] for d in devices]] for t, *devices in frames]
    return json.dumps({"convention": "openxr", "hand_frame": "forward", "frames": rounded}).encode()


def _json_string(text: str) -> str:
    import json

    return json.dumps(text)


def run_worker(settings: ServeSettings, ready=None) -> None:
    """One more server process on settings.port, beside the first (``humotion serve --workers``;
    the target of a multiprocessing Process): serves until terminated or interrupted; sets the
    multiprocessing Event ready once it listens."""
    async def run():
        async with LiveServer(settings) as server:
            await server.avatar()
            if ready is not None:
                ready.set()
            await server.serve_forever()
    try:
        asyncio.run(run())
    except KeyboardInterrupt:
        pass


def is_loopback(host: str) -> bool:
    """Whether an address to listen on reaches only this machine."""
    import ipaddress

    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False

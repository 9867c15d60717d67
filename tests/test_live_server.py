"""humotion serve on 127.0.0.1: poses per frame as a tracker gives them, tokens, and faults
(garbage, oversized messages, vanished and stalled clients) that never reach the other clients."""

import asyncio
import json
import socket
import warnings

import numpy as np
import pytest
import torch

from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed, InvalidStatus

from humotion.live import protocol as pr
from humotion.live.server import LiveServer, ServeSettings, is_loopback
from processes import interruptible

TIMEOUT = 90.0


@pytest.fixture(scope="module")
def stream():
    from humotion.assets import demo_clip_path
    from humotion.canonical import to_canonical
    from humotion.io import load_motion
    from humotion.sparse.recording import stream_from_motion

    truth = to_canonical(load_motion(demo_clip_path())).resample(90.0)
    s = stream_from_motion(truth, "HT", generator=torch.Generator().manual_seed(0))
    return s


def serving(scenario, **settings):
    """Run scenario(server, url) against a fresh server on 127.0.0.1 (any free port), bounded in time."""
    async def main():
        async with LiveServer(ServeSettings(port=0, **settings)) as server:
            return await asyncio.wait_for(scenario(server, f"ws://127.0.0.1:{server.port}/"), TIMEOUT)
    return asyncio.run(main())


async def recv_json(ws, kind: str):
    """The next JSON message of a kind (skipping skeleton messages unless asked for)."""
    for _ in range(10):
        message = json.loads(await asyncio.wait_for(ws.recv(), 20))
        if message["type"] == kind:
            return message
        if message["type"] == "error":
            raise AssertionError(message["message"])
    raise AssertionError(f"no {kind} message")


async def replay(url, frames, binary: bool, hello: dict | None = None) -> list:
    """Send frames one by one, each answered before the next; the poses received."""
    poses = []
    async with connect(url, open_timeout=20) as ws:
        if hello is not None:
            await ws.send(json.dumps({"type": "hello", **hello}))
            await recv_json(ws, "welcome")
        for t, head, left, right in frames:
            if binary:
                await ws.send(pr.frame_binary(t, head, left, right))
            else:
                await ws.send(json.dumps({"type": "frame", "t": t, "head": head, "left": left, "right": right}))
            while True:
                reply = await asyncio.wait_for(ws.recv(), 20)
                if isinstance(reply, bytes):
                    poses.append(pr.read_pose_binary(reply))
                    break
                message = json.loads(reply)
                assert message["type"] != "error", message
                if message["type"] == "pose":
                    poses.append({k: np.asarray(v) if k != "t" else v for k, v in message.items()})
                    break
    return poses


def direct(stream, n):
    """The same frames through a SparseTracker in humotion's axes."""
    from humotion.sparse.tracker import SparseTracker

    tracker = SparseTracker()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return [tracker.update(stream.frame(i)) for i in range(n)]


@pytest.mark.parametrize("binary", [False, True])
def test_each_frame_gets_the_trackers_pose_in_the_connections_axes(stream, binary):
    n = 40
    frames = pr.stream_frames(stream, "unity")[:n]
    poses = serving(lambda server, url: replay(url, frames, binary, {"convention": "unity", "version": 1}))
    expected = direct(stream, n)
    assert len(poses) == n
    c = np.array([-1.0, 1.0, 1.0])
    for got, want, frame in zip(poses, expected, frames):
        assert got["t"] == pytest.approx(frame[0])
        assert np.allclose(got["positions"], want.positions.numpy() * c, atol=2e-3)
        assert np.allclose(got["root"], want.root_position.numpy() * c, atol=2e-3)


def test_welcome_and_skeleton_describe_the_body(stream):
    async def scenario(server, url):
        async with connect(url + "?convention=humotion&height=1.8") as ws:
            await ws.send(json.dumps({"type": "hello"}))
            welcome = await recv_json(ws, "welcome")
            t, head, left, right = pr.stream_frames(stream, "humotion")[0]
            await ws.send(pr.frame_binary(t, head, left, right))
            skeleton = await recv_json(ws, "skeleton")
            pose = pr.read_pose_binary(await ws.recv())
            return welcome, skeleton, pose
    welcome, skeleton, pose = serving(scenario)
    assert welcome["convention"] == "humotion" and len(welcome["joints"]) == 22 and welcome["joints"][0] == "pelvis"
    assert skeleton["height"] == pytest.approx(1.8, abs=0.02) and len(skeleton["offsets"]) == 22
    assert np.isfinite(pose["positions"]).all()


def test_calibration_sizes_the_body():
    async def scenario(server, url):
        async with connect(url + "?convention=humotion") as ws:
            await ws.send(json.dumps({"type": "calibrate", "head": [0, 1.6, 0, 1, 0, 0, 0],
                                      "left": [0.8, 1.4, 0, 1, 0, 0, 0], "right": [-0.8, 1.4, 0, 1, 0, 0, 0]}))
            return await recv_json(ws, "skeleton")
    assert 1.6 < serving(scenario)["height"] < 1.9


@pytest.mark.parametrize("sent, ok", [(None, False), ("wrong-token", False), ("right-token", True)])
def test_a_token_is_needed_when_the_server_has_one(stream, sent, ok):
    async def scenario(server, url):
        query = "" if sent is None else f"?token={sent}"
        async with connect(url + query) as ws:
            await ws.send(json.dumps({"type": "hello"}))
            try:
                await recv_json(ws, "welcome")
                return True
            except ConnectionClosed as closed:
                assert closed.rcvd.code == 1008
                return False
    assert serving(scenario, token="right-token") is ok


def test_loopback_addresses():
    assert is_loopback("127.0.0.1") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("0.0.0.0") and not is_loopback("192.168.1.5") and not is_loopback("example.org")


# -- faults: each one meets a well-behaved client that must keep its poses ------------------------

async def steady(url, frames, started: asyncio.Event | None = None) -> int:
    """A well-behaved binary client at about 90 Hz: the poses it got (all of them, or it fails)."""
    got = 0
    async with connect(url) as ws:
        for i, (t, head, left, right) in enumerate(frames):
            await ws.send(pr.frame_binary(t, head, left, right))
            while isinstance(reply := await asyncio.wait_for(ws.recv(), 20), str):
                pass
            got += len(reply) == pr.POSE.size
            if started is not None and i == 5:
                started.set()
            await asyncio.sleep(1 / 90)
    return got


def with_neighbour(stream, fault, **settings):
    """Run fault(url, started) beside a steady client; both results."""
    frames = pr.stream_frames(stream, "openxr")[:90]

    async def scenario(server, url):
        started = asyncio.Event()
        good = asyncio.create_task(steady(url, frames, started))
        await asyncio.wait_for(started.wait(), 30)
        result = await fault(url)
        return await good, result, server.stats
    good, result, stats = serving(scenario, **settings)
    assert good == len(frames)
    return result, stats


def test_garbage_is_answered_with_errors_then_closed(stream):
    async def fault(url):
        errors = 0
        async with connect(url) as ws:
            try:
                for garbage in [b"\x01" * 96, "not json", '{"type": "dance"}', b"\x00\xff" * 3] * 10:
                    await ws.send(garbage)
                    message = json.loads(await asyncio.wait_for(ws.recv(), 10))
                    errors += message["type"] == "error"
            except ConnectionClosed as closed:
                return errors, closed.rcvd.code
        return errors, None
    (errors, code), stats = with_neighbour(stream, fault, max_errors=20)
    assert errors == 20 and code == 1008 and stats.closed_for.get("errors") == 1   # the 20th error, then closed


def test_an_oversized_message_closes_only_its_connection(stream):
    async def fault(url):
        async with connect(url, max_size=None) as ws:
            await ws.send(b"\x00" * 100_000)
            try:
                await asyncio.wait_for(ws.recv(), 10)
            except ConnectionClosed as closed:
                return closed.rcvd.code
    code, _ = with_neighbour(stream, fault)
    assert code == 1009                                              # message too big


def test_a_vanished_client_is_forgotten(stream):
    frames = pr.stream_frames(stream, "openxr")[:5]

    async def fault(url):
        ws = await connect(url)
        for t, head, left, right in frames:
            await ws.send(pr.frame_binary(t, head, left, right))
        ws.transport.abort()                                         # no closing handshake: the peer just goes
        await asyncio.sleep(0.5)
    _, stats = with_neighbour(stream, fault)
    assert stats.closed_for.get("gone", 0) >= 1


def test_a_silent_client_times_out(stream):
    async def fault(url):
        async with connect(url) as ws:
            try:
                await asyncio.wait_for(ws.recv(), 10)
            except ConnectionClosed as closed:
                return closed.rcvd.code
    code, stats = with_neighbour(stream, fault, idle_timeout=0.5)
    assert code == 1008 and stats.closed_for.get("timeout") == 1


async def raw_client(url):
    """A WebSocket client by hand (asyncio streams) that can write without ever reading: its
    receive buffer kept small, so the server's replies back up fast."""
    port = int(url.rsplit(":", 1)[1].strip("/"))
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)        # before connecting, so the window stays small
    sock.setblocking(False)
    await asyncio.get_running_loop().sock_connect(sock, ("127.0.0.1", port))
    reader, writer = await asyncio.open_connection(sock=sock)
    writer.write(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                 b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n")
    response = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), 10)
    assert response.startswith(b"HTTP/1.1 101")
    return reader, writer


def masked(payload: bytes, opcode: int = 0x1) -> bytes:
    """A client's WebSocket frame (text by default; mask key 0: the payload as it is)."""
    assert len(payload) < 65536
    size = bytes([0x80 | len(payload)]) if len(payload) < 126 else bytes([0x80 | 126]) + len(payload).to_bytes(2, "big")
    return bytes([0x80 | opcode]) + size + b"\0\0\0\0" + payload


def test_a_client_that_never_reads_is_dropped(stream):
    t0, head, left, right = pr.stream_frames(stream, "openxr")[0]

    async def fault(url):
        reader, writer = await raw_client(url)
        sent = 0
        try:
            for i in range(200_000):                 # JSON frames (each answered), 0.1 ms apart: from the held pose, fast
                frame = {"t": t0 + i * 1e-4, "head": head, "left": left, "right": right}
                writer.write(masked(json.dumps(frame).encode()))
                await asyncio.wait_for(writer.drain(), 3)
                sent += 1
        except (TimeoutError, ConnectionError):
            pass
        writer.transport.abort()
        return sent
    sent, stats = with_neighbour(stream, fault, send_timeout=0.5)
    assert sent < 200_000 and stats.closed_for.get("timeout") == 1


def test_a_burst_of_binary_frames_is_answered_up_to_its_newest(stream):
    frames = pr.stream_frames(stream, "openxr")[:200]

    async def scenario(server, url):
        async with connect(url) as ws:
            for t, head, left, right in frames:                  # all at once, nothing read meanwhile
                await ws.send(pr.frame_binary(t, head, left, right))
            answered = []
            while not answered or answered[-1] < frames[-1][0]:
                reply = await asyncio.wait_for(ws.recv(), 20)
                if isinstance(reply, bytes):
                    answered.append(pr.read_pose_binary(reply)["t"])
            return answered, server.stats
    answered, stats = serving(scenario)
    assert answered == sorted(answered) and answered[-1] == frames[-1][0]
    assert len(answered) + stats.skipped == len(frames) and stats.skipped > 0


def test_connections_beyond_the_limit_are_refused():
    async def scenario(server, url):
        async with connect(url):
            with pytest.raises(InvalidStatus) as refused:
                async with connect(url):
                    pass
            return refused.value.response.status_code, server.stats.refused
    assert serving(scenario, max_clients=1) == (503, 1)


# -- the command and its VMC forward ---------------------------------------------------------

def test_every_pose_is_forwarded_as_vmc(stream):
    from test_live_vmc import Receiver

    from humotion.live.vmc import BONE_NAMES

    receiver = Receiver()
    try:
        frames = pr.stream_frames(stream, "openxr")[:12]
        poses = serving(lambda server, url: replay(url, frames, True), vmc=("127.0.0.1", receiver.port))
        receiver.wait_for(len(frames))
        heard = receiver.frames()
    finally:
        receiver.close()
    assert len(poses) == len(heard) == len(frames)
    for pose, frame in zip(poses, heard):
        bones = {args[0]: args[1:] for address, args in frame if address == "/VMC/Ext/Bone/Pos"}
        assert set(bones) == set(BONE_NAMES)
        # the Hips' position is the pelvis's: openxr (-x, y, -z) to the client, unity (-x, y, z) over VMC
        assert np.allclose(bones["Hips"][:3], pose["root"] * np.array([1.0, 1.0, -1.0]), atol=1e-4)


def run_command(*args):
    from click.testing import CliRunner

    from humotion.cli import main

    return CliRunner().invoke(main, ["serve", *args])


@pytest.mark.parametrize("host", ["0.0.0.0", "192.168.1.5", "::"])
def test_other_interfaces_need_allow_remote(host):
    result = run_command("--host", host)
    assert result.exit_code == 2 and "--allow-remote" in result.output


def test_serving_remotely_warns(monkeypatch):
    started = []
    monkeypatch.setattr(asyncio, "run", lambda coroutine: started.append(coroutine.close()))
    result = run_command("--host", "0.0.0.0", "--allow-remote", "--port", "0")
    assert result.exit_code == 0 and started
    assert "warning: serving on 0.0.0.0" in result.output and "no --token" in result.output


def test_short_tokens_are_refused():
    result = run_command("--token", "abc")
    assert result.exit_code == 2 and "8 characters" in result.output


def test_a_flooding_client_does_not_starve_the_others(stream):
    frames = pr.stream_frames(stream, "openxr")

    async def fault(url):
        reader, writer = await raw_client(url)
        sent = 0
        try:
            for i in range(5000):                    # binary frames as fast as TCP takes them, replies never read
                t, head, left, right = frames[i % len(frames)]
                writer.write(masked(pr.frame_binary(i / 90, head, left, right), opcode=0x2))
                await asyncio.wait_for(writer.drain(), 3)
                sent += 1
        except (TimeoutError, ConnectionError):
            pass
        writer.transport.abort()
        return sent
    sent, stats = with_neighbour(stream, fault)                 # the steady client still gets every pose
    assert sent > 0 and stats.frames + stats.skipped >= 90


def test_frames_arriving_in_small_bunches_are_all_answered(stream):
    frames = pr.stream_frames(stream, "openxr")[:60]

    async def scenario(server, url):
        async with connect(url) as ws:
            answered = []
            for start in range(0, len(frames), 3):              # three at once, as a client's jitter sends them
                for t, head, left, right in frames[start:start + 3]:
                    await ws.send(pr.frame_binary(t, head, left, right))
                while len(answered) < start + 3:
                    reply = await asyncio.wait_for(ws.recv(), 20)
                    if isinstance(reply, bytes):
                        answered.append(pr.read_pose_binary(reply)["t"])
            return answered, server.stats
    answered, stats = serving(scenario, late_after=10.0)       # only the backlog (max_backlog 4) can make one late
    assert answered == [f[0] for f in frames] and stats.skipped == 0


def listening_sockets(port: int) -> int:
    """How many sockets listen on 127.0.0.1:port (Linux /proc/net/tcp; state 0A: LISTEN)."""
    rows = [line.split() for line in open("/proc/net/tcp").read().splitlines()[1:]]
    return sum(row[1] == f"0100007F:{port:04X}" and row[3] == "0A" for row in rows)


def test_workers_share_the_port_and_stop_together(stream, tmp_path):
    import os
    import signal
    import subprocess
    import sys

    from websockets.sync.client import connect as sync_connect

    if not os.path.exists("/proc/net/tcp"):
        pytest.skip("needs Linux /proc")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = subprocess.Popen([sys.executable, "-m", "humotion.cli", "serve", "--port", str(port), "--workers", "2"],
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, preexec_fn=interruptible)
    try:
        line = server.stdout.readline()
        assert "serving" in line and "2 processes" in line, line
        assert listening_sockets(port) == 2                        # two processes, one port
        frames = pr.stream_frames(stream, "openxr")[:3]
        for _ in range(4):                                          # every connection served, wherever it lands
            with sync_connect(f"ws://127.0.0.1:{port}/", open_timeout=30) as ws:
                for t, head, left, right in frames:
                    ws.send(pr.frame_binary(t, head, left, right))
                    while not isinstance(reply := ws.recv(timeout=30), bytes):
                        pass
                    assert pr.read_pose_binary(reply)["t"] == t
    finally:
        server.send_signal(signal.SIGINT)
        server.wait(30)
    assert listening_sockets(port) == 0                            # the worker stopped with the first


def test_a_body_file_not_made_by_humotion_body_is_refused(tmp_path):
    foreign = tmp_path / "robot.glb"
    foreign.write_bytes(b"glTF" + bytes(40))
    result = run_command("--port", "0", "--body", str(foreign))
    assert result.exit_code == 2 and "--body" in result.output and "not a body written by `humotion body`" in result.output

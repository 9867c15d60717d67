"""humotion serve under load on loopback: N concurrent headset streams at 90 Hz.

    .venv/bin/python bench/serve_load.py [--streams 1,4,8,16,32,64] [--seconds 10] [--rate 90]
        [--workers 1,2] [--baseline] [--json] [--keep-going]

Starts ``humotion serve`` in its own process on 127.0.0.1 (a free port), then for each stream
count N opens N WebSocket connections from this process; each sends binary frames (the bundled
demo clip's headset stream, looped) on a 90 Hz clock without waiting for replies, and its reader
times each pose from the moment its frame was sent. Per N it prints poses received per second
against the rate asked for, latency p50 / p99 (ms, frame sent -> pose received), the server's CPU
use (% of one core, from /proc: its processes together, --workers of them) and this process's,
and the load average (the machine is shared). Each --workers value is a server of its own,
measured in turn over the same stream counts. --baseline first runs the same levels against a
bare websockets server in its own process that answers each frame with a zeroed pose at once (no
tracker, no checks): the floor that the WebSocket traffic alone sets. N "holds" when at least 98% of the frames are answered within the run plus
one second and p99 stays under 100 ms; the bench stops at the first N that does not hold
(--keep-going: runs them all). Linux only (/proc).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of a process and its child processes (Linux /proc/PID/stat)."""
    total = 0.0
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:                 # a process that ended meanwhile
            continue
        if stat.parent.name == str(pid) or fields[1] == str(pid):
            total += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return total


def demo_frames() -> list[tuple]:
    import torch

    from humotion.assets import demo_clip_path
    from humotion.canonical import to_canonical
    from humotion.io import load_motion
    from humotion.live.protocol import stream_frames
    from humotion.sparse.recording import stream_from_motion

    truth = to_canonical(load_motion(demo_clip_path())).resample(90.0)
    return stream_frames(stream_from_motion(truth, "HT", generator=torch.Generator().manual_seed(0)), "openxr")


async def one_stream(url: str, frames: list[tuple], rate: float, seconds: float, latencies: list, counts: dict,
                     ready: list, go: asyncio.Event):
    from websockets.asyncio.client import connect

    from humotion.live.protocol import POSE, frame_binary

    sent_at: dict[float, float] = {}
    period, span = 1.0 / rate, frames[-1][0] + 1.0 / rate
    async with connect(url, open_timeout=60, max_queue=None, compression=None) as ws:
        await ws.send(json.dumps({"type": "hello", "version": 1}))
        while json.loads(await asyncio.wait_for(ws.recv(), 60))["type"] != "welcome":   # its tracker is built
            pass
        _, head, left, right = frames[0]                       # a first frame warms the server's code paths,
        await ws.send(frame_binary(0.0, head, left, right))   # then the tracker forgets it
        while not isinstance(await asyncio.wait_for(ws.recv(), 60), bytes):
            pass
        await ws.send(json.dumps({"type": "reset"}))
        ready.append(ws)
        if len(ready) == ready[0] + 1:
            go.set()
        await asyncio.wait_for(go.wait(), 120)

        async def reader():
            async for message in ws:
                if isinstance(message, bytes) and len(message) == POSE.size:
                    t = POSE.unpack_from(message)[4]
                    start = sent_at.pop(t, None)
                    if start is not None:
                        latencies.append(time.perf_counter() - start)
                        counts["received"] += 1
        task = asyncio.create_task(reader())
        begin, n = time.perf_counter(), int(seconds * rate)
        for i in range(n):
            wait = begin + i * period - time.perf_counter()
            if wait > 0:
                await asyncio.sleep(wait)
            _, head, left, right = frames[i % len(frames)]
            t = (i // len(frames)) * span + frames[i % len(frames)][0]
            sent_at[t] = time.perf_counter()
            await ws.send(frame_binary(t, head, left, right))
            counts["sent"] += 1
        deadline = time.perf_counter() + 1.0
        while sent_at and time.perf_counter() < deadline:
            await asyncio.sleep(0.02)
        task.cancel()


async def load(url: str, streams: int, frames, rate: float, seconds: float, marks: dict, server_pid: int) -> dict:
    latencies, counts = [], {"sent": 0, "received": 0}
    # connections open first (each builds a tracker on the server), then all streams start together
    ready, go = [streams], asyncio.Event()

    async def mark():
        await go.wait()
        marks.update(server_cpu=cpu_seconds(server_pid), own_cpu=time.process_time(), wall=time.perf_counter())
    marker = asyncio.create_task(mark())
    await asyncio.gather(*(one_stream(url, frames, rate, seconds, latencies, counts, ready, go) for _ in range(streams)))
    marker.cancel()
    return {"latencies": latencies, **counts}


def run_level(url: str, server_pid: int, streams: int, frames, rate: float, seconds: float) -> dict:
    marks = {}                 # CPU and wall clock from when every stream is ready (trackers built)
    result = asyncio.run(asyncio.wait_for(load(url, streams, frames, rate, seconds, marks, server_pid), seconds * 3 + 180))
    server_cpu, own_cpu, wall = marks["server_cpu"], marks["own_cpu"], marks["wall"]
    wall = time.perf_counter() - wall
    lat = sorted(result["latencies"])
    p = (lambda q: 1e3 * lat[min(len(lat) - 1, int(q * len(lat)))]) if lat else (lambda q: float("nan"))
    answered = result["received"] / max(result["sent"], 1)
    return {"streams": streams, "rate_hz": rate, "asked_per_s": streams * rate, "sent": result["sent"],
            "received": result["received"], "answered": round(answered, 4),
            "p50_ms": round(p(0.5), 2), "p99_ms": round(p(0.99), 2),
            "server_cpu_pct": round(100 * (cpu_seconds(server_pid) - server_cpu) / wall, 1),
            "client_cpu_pct": round(100 * (time.process_time() - own_cpu) / wall, 1),
            "loadavg_1m": round(os.getloadavg()[0], 2), "wall_s": round(wall, 1),
            "holds": answered >= 0.98 and bool(lat) and p(0.99) < 100.0}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--streams", default="8,16,32,64", help="stream counts, comma separated")
    parser.add_argument("--seconds", type=float, default=10.0, help="each level's sending time")
    parser.add_argument("--rate", type=float, default=90.0, help="frames per second per stream")
    parser.add_argument("--keep-going", action="store_true", help="run every level, held or not")
    parser.add_argument("--workers", default="1", help="server processes (humotion serve --workers), comma "
                        "separated: each a server of its own, run over every stream count in turn")
    parser.add_argument("--baseline", action="store_true", help="first the same levels against a bare echo server")
    parser.add_argument("--json", action="store_true", help="one JSON object per level")
    parser.add_argument("--echo-server", type=int, metavar="PORT", help=argparse.SUPPRESS)   # --baseline's server
    args = parser.parse_args()
    if args.echo_server:
        asyncio.run(echo_server(args.echo_server))
        return
    levels = [int(n) for n in args.streams.split(",")]
    frames = demo_frames()
    if args.baseline:
        run_server(args, levels, frames, 0)
    for workers in [int(n) for n in args.workers.split(",")]:
        run_server(args, levels, frames, workers)


async def echo_server(port: int) -> None:
    """The baseline: a welcome for a hello, a zeroed binary pose echoing each binary frame's time."""
    from websockets.asyncio.server import serve

    from humotion.live.protocol import POSE

    zeros = [0.0] * (3 + 22 * 4 + 22 * 3)

    async def handle(ws):
        async for message in ws:
            if isinstance(message, bytes):
                await ws.send(POSE.pack(1, 2, 0, 0, struct.unpack_from("<d", message, 4)[0], *zeros))
            elif json.loads(message).get("type") == "hello":
                await ws.send(json.dumps({"type": "welcome"}))
    async with serve(handle, "127.0.0.1", port, compression=None, max_size=4096):
        print(f"serving ws://127.0.0.1:{port}/ (echo)", flush=True)
        await asyncio.Future()


def run_server(args, levels: list[int], frames, workers: int) -> None:
    """The levels against humotion serve --workers workers, or (workers 0) the echo server."""
    port = free_port()
    command = ([sys.executable, str(Path(__file__).resolve()), "--echo-server", str(port)] if workers == 0 else
               [sys.executable, "-m", "humotion.cli", "serve", "--port", str(port), "--workers", str(workers),
                "--max-clients", str(max(levels) + 8)])
    server = subprocess.Popen(command, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        line = server.stdout.readline()          # "serving ws://..." once it listens (every worker)
        if "serving" not in line:
            sys.exit(f"humotion serve did not start: {line.strip()}")
        import collections
        import threading

        said = collections.deque(maxlen=5)           # the server's last lines, read so its pipe never fills
        threading.Thread(target=lambda: [said.append(l) for l in server.stdout], daemon=True).start()
        what = ("baseline: a bare websockets server answering each frame with a zeroed pose" if workers == 0
                else f"humotion serve --workers {workers}")
        print(f"# {os.cpu_count()} CPUs, load average {os.getloadavg()}; {what} "
              f"(pid {server.pid}), {args.rate:g} Hz per stream, {args.seconds:g} s per level", flush=True)
        first_not_held = None
        for n in levels:
            row = run_level(f"ws://127.0.0.1:{port}/", server.pid, n, frames, args.rate, args.seconds)
            print(json.dumps(row) if args.json else
                  f"{n:3d} streams: {row['received'] / args.seconds:7.0f} poses/s of {row['asked_per_s']:.0f} asked, "
                  f"answered {100 * row['answered']:.1f}%, p50 {row['p50_ms']:.1f} ms, p99 {row['p99_ms']:.1f} ms, "
                  f"server CPU {row['server_cpu_pct']:.0f}%, client CPU {row['client_cpu_pct']:.0f}%, "
                  f"load {row['loadavg_1m']:.2f} -> {'holds' if row['holds'] else 'does NOT hold'}", flush=True)
            if not row["holds"] and first_not_held is None:
                first_not_held = n
                print(f"# {n} streams at {args.rate:g} Hz is more than this machine holds (load average "
                      f"{row['loadavg_1m']:.2f} on {os.cpu_count()} CPUs)" + ("" if args.keep_going else ": stopped"),
                      flush=True)
                if not args.keep_going:
                    break
        if first_not_held is None:
            print(f"# every level held, up to {levels[-1]} streams at {args.rate:g} Hz", flush=True)
    finally:
        if 'said' in locals() and said:
            print("# the server's last lines:", *("#   " + l.rstrip() for l in said), sep="\n")
        server.send_signal(signal.SIGINT)           # Ctrl-C: it stops its worker processes too
        try:
            server.wait(10)
        except subprocess.TimeoutExpired:
            server.kill()


if __name__ == "__main__":
    main()

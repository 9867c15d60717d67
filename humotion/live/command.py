"""The live commands: ``humotion serve`` and the VMC output of ``humotion track --vmc``."""

from __future__ import annotations

import math

import click

from humotion.live.server import LiveServer, ServeSettings, is_loopback, run_worker
from humotion.options import config_options, host_option, port_option, reported, sparse_weights_option


def vmc_address(ctx, param, value):
    """click callback: 'HOST:PORT' -> (host, port), a usage error naming the option otherwise."""
    if value is None:
        return None
    from humotion.live.vmc import parse_address

    try:
        return parse_address(value)
    except ValueError as error:
        raise click.BadParameter(str(error)) from None


def send_vmc(body, address: tuple[str, int], fps: float, rate: float | None) -> None:
    """Stream a tracked body (canonical Motion) as VMC to address in real time at ``fps`` (the
    recording's rate), or at ``rate`` frames per second (0: as fast as possible)."""
    from humotion.live.vmc import VmcSender, stream_motion

    if fps > 0 and abs(body.fps - fps) > 1e-6:
        body = body.resample(fps)
    rate = body.fps if rate is None else (math.inf if rate == 0 else rate)
    if rate < 0:
        raise click.BadParameter("must be 0 (as fast as possible) or a positive rate", param_hint="--vmc-rate")
    with reported(ValueError):
        sender = VmcSender(address)
    pace = "as fast as possible" if math.isinf(rate) else f"{rate:g} frames/s"
    click.echo(f"VMC: {len(body)} frames to {address[0]}:{address[1]} ({pace}, {len(body) / rate:.1f} s)"
               if math.isfinite(rate) else f"VMC: {len(body)} frames to {address[0]}:{address[1]} ({pace})")
    with sender:
        try:
            stream_motion(body, sender, rate)
        except KeyboardInterrupt:
            click.echo("VMC: stopped", err=True)
    if sender.dropped:
        click.echo(f"warning: VMC: {sender.dropped} datagrams dropped (the network could not take them)", err=True)


SERVE_EPILOG = """\b
Examples:
  humotion serve                                   # ws://127.0.0.1:8765, this machine only
  humotion serve --vmc 127.0.0.1:39539             # also each body as VMC (VSeeFace, Warudo, EVMC4U)
  humotion serve --host 0.0.0.0 --allow-remote --token SECRET   # a headset on the LAN
  humotion serve --body alice.glb --workers 4      # the page shows alice (humotion body); 4 processes

Messages (JSON or 96-byte binary frames in, poses out): docs/live.md.
"""


@click.command("serve", epilog=SERVE_EPILOG)
@host_option()
@port_option(ServeSettings.port, help="Port (0: any free one).")
@click.option("--allow-remote", is_flag=True, help="Needed to listen on an address other machines can reach.")
@click.option("--token", envvar="HUMOTION_SERVE_TOKEN", metavar="SECRET",
              help="Shared secret clients must send (query string ?token= or hello); also $HUMOTION_SERVE_TOKEN.")
@sparse_weights_option
@click.option("--height", type=click.FloatRange(0.5, 2.5), help="Standing height in metres for clients that state none.")
@click.option("--vmc", metavar="HOST:PORT", callback=vmc_address, help="Also send every connection's body as VMC (OSC/UDP).")
@click.option("--body", type=click.Path(exists=True, dir_okay=False), metavar="BODY.glb",
              help="The live page's avatar: a body written by `humotion body` (default: one made at --height, "
                   "else 1.7 m, when the server starts).")
@click.option("--tls", nargs=2, type=click.Path(exists=True, dir_okay=False), metavar="CERT.pem KEY.pem",
              help="Serve https/wss with this certificate and key (a headset's browser gives WebXR only to secure pages).")
@config_options(ServeSettings, "max_clients", "workers", max_clients={"type": click.IntRange(1, 1024)},
                workers={"type": click.IntRange(1, 64)})
def serve_command(host, port, allow_remote, token, weights, height, vmc, body, tls, max_clients, workers):
    """Live full-body tracking over WebSocket: headset frames in, one body pose per frame out,
    one tracker per connection."""
    import asyncio
    import dataclasses
    import multiprocessing

    if not is_loopback(host):
        if not allow_remote:
            raise click.UsageError(f"--host {host} lets other machines connect: add --allow-remote to mean it "
                                   "(and --token SECRET to let only your devices in)")
        click.echo(f"warning: serving on {host}: any machine that reaches this one can connect"
                   + ("" if token else " (no --token: anyone)")
                   + ("" if tls else "; frames and poses travel unencrypted (ws://; --tls encrypts)"), err=True)
    if token is not None and len(token) < 8:
        raise click.BadParameter("use 8 characters or more", param_hint="--token")
    settings = ServeSettings(host=host, port=port, token=token, weights=weights, height=height, vmc=vmc, body=body,
                             tls=tuple(tls) if tls else None, max_clients=max_clients, workers=workers)
    with reported(FileNotFoundError):
        server = LiveServer(settings)

    async def run():
        async with server:
            try:
                await server.avatar()                             # the page's body, made once
            except ValueError as error:
                raise click.BadParameter(str(error), param_hint="--body") from None
            spawn = multiprocessing.get_context("spawn")         # after the first has bound: port 0 is known
            ready = [spawn.Event() for _ in range(workers - 1)]
            others = [spawn.Process(target=run_worker, args=(dataclasses.replace(settings, port=server.port), event),
                                    daemon=True) for event in ready]
            for process in others:
                process.start()
            for process, event in zip(others, ready):         # each has loaded its model and listens
                while not await asyncio.to_thread(event.wait, 1.0):
                    if not process.is_alive():
                        raise click.ClickException(f"a worker process stopped (exit code {process.exitcode})")
            web, ws = ("https", "wss") if tls else ("http", "ws")
            shown = f"[{host}]" if ":" in host else host
            click.echo(f"serving {ws}://{shown}:{server.port}/ (live page: {web}://{shown}:{server.port}/)"
                       + (f", VMC to {vmc[0]}:{vmc[1]}" if vmc else "")
                       + (f", {workers} processes" if workers > 1 else "") + " (Ctrl-C stops)")
            try:
                await server.serve_forever()
            finally:
                for process in others:
                    process.terminate()
                    process.join(5)

    try:
        asyncio.run(run())
    except KeyboardInterrupt:
        click.echo("stopped")
    except OSError as error:          # the port taken, an address not of this machine, an unreadable certificate
        raise click.ClickException(f"cannot serve on {host}:{port}: {error.strerror or error}") from None

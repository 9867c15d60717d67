"""The live commands: ``humotion serve`` and the VMC output of ``humotion track --vmc``."""

from __future__ import annotations

import math

import click


def _needs_live_extra(module: str):
    """Import a module of the live extra, or a one-line error saying how to install it."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as error:
        raise click.ClickException(f"{error.name} is missing: install humotion's live extra "
                                   "(pip install 'humotion[live]')") from None


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
    _needs_live_extra("pythonosc")
    from humotion.live.vmc import VmcSender, stream_motion

    if fps > 0 and abs(body.fps - fps) > 1e-6:
        body = body.resample(fps)
    rate = body.fps if rate is None else (math.inf if rate == 0 else rate)
    if rate < 0:
        raise click.BadParameter("must be 0 (as fast as possible) or a positive rate", param_hint="--vmc-rate")
    try:
        sender = VmcSender(address)
    except ValueError as error:
        raise click.ClickException(str(error)) from None
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

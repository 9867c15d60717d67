"""The commands agree with each other (issue 24 item 5): every command with a viewer takes both
--view and --no-view."""

from __future__ import annotations

import click

from humotion.cli import main


def commands(group: click.Group, prefix: str = "humotion"):
    """(name, command) of every command under group, subcommands included."""
    for name, command in group.commands.items():
        if isinstance(command, click.Group):
            yield from commands(command, f"{prefix} {name}")
        else:
            yield f"{prefix} {name}", command


def test_every_viewer_can_be_switched_off():
    with_view = {}
    for name, command in commands(main):
        for param in command.params:
            if "--view" in param.opts:
                with_view[name] = param.secondary_opts
    assert {"humotion track", "humotion capture", "humotion demo", "humotion body", "humotion retarget"} <= set(with_view)
    assert all(off == ["--no-view"] for off in with_view.values()), with_view

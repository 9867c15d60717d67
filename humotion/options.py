"""Command-line options shared by humotion's commands (the command side: libraries never import this).

Each setting is written once, as a config dataclass field with its docstring; :func:`config_options`
makes the click options from the fields (name, type, default, help). The `humotion train`
commands take :func:`run_options` (RunConfig's fields, with the command's config's defaults),
turn them into config fields with :func:`run_settings` and print the run's summary with
:func:`echo_summary`.

Options several commands take are declared here once: :func:`input_options` (how to read a motion
file), :func:`view_options` (--view/--no-view and --port), :func:`host_option`,
:func:`port_option`, :func:`sparse_weights_option`; one way to report the user's mistakes,
:func:`reported` (click's one-line error, no traceback); and one way to print what a library logs
for the person at the terminal, :func:`show_log` (the viewer's address). Different things get different names:
--weights is the sparse-tracking network; capture's lifter is --lifter and retarget's network
--retargeter (their earlier --weights still accepted, unlisted: :class:`RenamedOption`).
"""

from __future__ import annotations

import ast
import contextlib
import dataclasses
import inspect
import json
import logging
import os
import textwrap
import types
import typing
from functools import cache

import click

from humotion.training import EVALUATION_ONLY, RunConfig


@cache
def field_help(cls: type) -> dict[str, str]:
    """Field name -> the docstring written under the field (the string literal after it), over
    the dataclass and its bases (a subclass's docstring wins)."""
    helps: dict[str, str] = {}
    for base in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(base):
            continue
        body = ast.parse(textwrap.dedent(inspect.getsource(base))).body[0].body
        for node, after in zip(body, body[1:]):
            if (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and isinstance(after, ast.Expr)
                    and isinstance(after.value, ast.Constant) and isinstance(after.value.value, str)):
                helps[node.target.id] = " ".join(after.value.value.split())
    return helps


def _click_type(annotation) -> dict:
    """click.option keywords for a field's type: X | None -> X; tuple[X, ...] -> multiple;
    tuple[X, X] -> nargs; bool -> a --name/--no-name flag (set by config_options)."""
    args = [a for a in typing.get_args(annotation) if a is not type(None)]
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        return _click_type(args[0])
    if typing.get_origin(annotation) is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return {"type": args[0], "multiple": True}
        return {"type": args[0], "nargs": len(args)}
    return {"type": annotation}


def config_options(cls: type, *names: str, **custom: dict):
    """Decorator adding a click option per named field of the dataclass `cls`: `--field-name`,
    the field's type (:func:`_click_type`), default (a default_factory's value) and help (the
    field's docstring, :func:`field_help`). custom[name]: click.option keywords replacing those
    (e.g. `decls=("--fov", "fov_deg")` for another spelling, `type=click.Choice(...)`)."""
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    helps = field_help(cls)
    options = []
    for name in names:
        f = fields[name]
        default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
        keywords = {"default": default, "show_default": default is not None, "help": helps.get(name), **_click_type(hints[name])}
        dashed = name.replace("_", "-")
        decls = (f"--{dashed}/--no-{dashed}", name) if keywords["type"] is bool else (f"--{dashed}", name)
        if keywords.get("multiple") and default is None:
            keywords["default"] = ()
        keywords.update(custom.get(name, {}))
        options.append(click.option(*keywords.pop("decls", decls), **keywords))
    return stacked(*options)


def run_options(config: type[RunConfig]):
    """Decorator adding the options every `humotion train` command takes (data, output folder,
    length of the run, seed, device, resume), with `config`'s defaults; turn them into config
    fields with run_settings."""
    return config_options(
        config, "data_root", "out_dir", "epochs", "steps", "batch_size", "lr", "sources", "exclude", "seed", "device",
        "threads", "checkpoint_every", "max_clips", "resume",
        data_root={"decls": ("--data", "data_root")}, out_dir={"decls": ("--out", "out_dir")},
        sources={"decls": ("--source", "sources")})


def run_settings(options: dict) -> dict:
    """Config fields from the options of run_options (popped from `options`): sources, and
    exclude, which always keeps the evaluation-only sources out."""
    return {"sources": options.pop("sources") or None,
            "exclude": tuple(dict.fromkeys((*options.pop("exclude"), *EVALUATION_ONLY)))}


def echo_summary(summary: dict) -> None:
    """Print a run's summary as JSON (rank 0 only; the validation metrics are in log.jsonl)."""
    if int(os.environ.get("RANK", "0")) == 0:
        click.echo(json.dumps({k: v for k, v in summary.items() if k != "val"}, indent=1))


# -- options several commands share -------------------------------------------------------

def stacked(*options):
    """One decorator applying several click options, listed in --help in this order."""
    def decorate(command):
        for option in reversed(options):
            command = option(command)
        return command

    return decorate


_input_options = [
    click.option("--asf", type=click.Path(exists=True, dir_okay=False), help="ASF skeleton for an AMC file (default: found beside it or in ../asf/)."),
    click.option("--source-fps", type=float, help="Frame rate of formats that store none (AMC, exp-map). Default 120, CMU's rate."),
    click.option("--units", default="auto", show_default=True, callback=lambda ctx, param, value: _units(value),
                 help="BVH length unit: auto, m, cm, mm, inch, cmu, or metres per unit."),
]


def _units(value: str) -> str | float:
    """--units as the readers take it: "auto", a unit's name, or metres per file unit (a number)."""
    from humotion.io.bvh import UNITS

    if value == "auto" or value in UNITS:
        return value
    try:
        factor = float(value)
    except ValueError:
        factor = float("nan")
    if not (factor > 0 and factor != float("inf")):
        raise click.BadParameter(f"expected auto, one of {', '.join(UNITS)}, or a positive number of metres per "
                                 f"file unit; got {value!r}", param_hint="--units")
    return factor


def input_options(command):
    """--asf, --source-fps and --units: how to read a motion file (humotion.io.load_motion)."""
    return stacked(*_input_options)(command)


def port_option(default: int = 8080, help: str = "Port of the browser viewer."):
    """--port: a TCP port (0: any free one)."""
    return click.option("--port", default=default, show_default=True, type=click.IntRange(0, 65535), help=help)


def host_option(help: str = "Address to serve on (this machine only by default)."):
    """--host: the address a server listens on."""
    return click.option("--host", default="127.0.0.1", show_default=True, help=help)


def view_options(default: bool | None = False, help: str = "Open the result in the browser viewer."):
    """--view/--no-view (open the browser viewer when the command is done) and its --port."""
    return stacked(click.option("--view/--no-view", default=default, show_default=default is not None, help=help),
                   port_option())


SPARSE_WEIGHTS_HELP = ("Sparse-tracking weights: a .pt file, or a shipped network: default (64 wide, about half a "
                       "millisecond per frame) or accurate (128 wide, 0.1-1.0 cm more accurate, 1.3-1.7x the time).")


def sparse_weights_option(command):
    """--weights: the sparse-tracking network (a .pt file or a shipped network's name)."""
    return click.option("--weights", metavar="PATH|NAME", help=SPARSE_WEIGHTS_HELP)(command)


class RenamedOption(click.Option):
    """An option whose earlier spelling (`old`, one of its declarations) still works but is not
    shown in --help."""

    def __init__(self, *args, old: str, **kwargs):
        super().__init__(*args, **kwargs)
        self.old = old

    def get_help_record(self, ctx):
        shown, self.opts = self.opts, [o for o in self.opts if o != self.old]
        try:
            return super().get_help_record(ctx)
        finally:
            self.opts = shown


@contextlib.contextmanager
def reported(*errors: type[Exception]):
    """Turn these exceptions into click's one-line error (message, exit code 1, no traceback):
    as a decorator on a command, or `with reported(ValueError): ...` around the lines that read
    the user's input."""
    try:
        yield
    except errors as error:
        raise click.ClickException(str(error)) from None


class EchoHandler(logging.Handler):
    """Log records printed as click prints them (the stream looked up for each record, so the
    terminal's and CliRunner's alike): the message alone; warnings and errors on stderr."""

    def emit(self, record: logging.LogRecord) -> None:
        click.echo(self.format(record), err=record.levelno >= logging.WARNING)


def show_log(name: str, level: int = logging.INFO) -> None:
    """Print what the library logger `name` (and those under it) logs at `level` and above; once,
    however often it is called."""
    logger = logging.getLogger(name)
    if not any(isinstance(handler, EchoHandler) for handler in logger.handlers):
        logger.addHandler(EchoHandler())
    logger.setLevel(level)

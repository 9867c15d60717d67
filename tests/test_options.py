"""Each setting is written once: the `humotion train` commands' options, and those of `humotion
capture` and `humotion serve` that are their settings, are made from the config dataclasses
(humotion.options.config_options), so a command run without options trains (or captures) with its
config's defaults, and an option changes the same setting the config field does."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import click
import pytest
import torch
from click.testing import CliRunner

import humotion.body.command as body_command
import humotion.capture.command as capture_command
import humotion.retarget.command as retarget_command
import humotion.sparse.command as sparse_command
from humotion.assets import demo_photo_path
from humotion.body.dataset import Settings
from humotion.capture import lifting, pipeline
from humotion.capture.filters import OneEuroConfig
from humotion.capture.pipeline import CaptureConfig, CaptureResult
from humotion.body.train import BodyTrainConfig
from humotion.capture.prior import PosePrior, PriorTrainConfig
from humotion.capture.train_lift import LiftTrainConfig
from humotion.live.server import ServeSettings
from humotion.retarget.train import RetargetTrainConfig
from humotion.sparse.train import TrainConfig
from humotion.options import RenamedOption, config_options, field_help, reported, show_log
from humotion.sparse.model import SparseConfig, SparsePoser
from humotion.training import RunConfig

PACKAGE = Path(__file__).resolve().parents[1] / "humotion"

COMMANDS = {
    "sparse": (sparse_command, sparse_command.train_sparse_command, TrainConfig),
    "lift": (capture_command, capture_command.train_lift_command, LiftTrainConfig),
    "retarget": (retarget_command, retarget_command.train_retarget_command, RetargetTrainConfig),
    "body": (body_command, body_command.train_body_command, BodyTrainConfig),
    "prior": (capture_command, capture_command.train_prior_command, PriorTrainConfig),
}

TRAINED = {"prior": ("train_prior", PosePrior(torch.zeros(63), torch.eye(63), 0))}
"""The library function a command calls with its config, and what a stand-in for it returns, where
these are not `train` and a summary dict."""


def config_of(name: str, args: list[str], monkeypatch) -> RunConfig:
    """The config `humotion train <name> ARGS` would train with (the training itself replaced)."""
    module, command, _ = COMMANDS[name]
    function, result = TRAINED.get(name, ("train", {}))
    seen = []
    monkeypatch.setattr(module, function, lambda config: seen.append(config) or result)
    result = CliRunner().invoke(command, args, catch_exceptions=False)
    assert result.exit_code == 0, result.output
    return seen[0]


@pytest.mark.parametrize("name", COMMANDS)
def test_a_command_without_options_trains_with_its_config_defaults(name, monkeypatch):
    assert config_of(name, [], monkeypatch) == COMMANDS[name][2]()


@pytest.mark.parametrize("name", COMMANDS)
def test_every_option_default_is_its_fields_default(name):
    """Each option named after a field of the config (or of its model's config) defaults to that
    field's default, as click parses it."""
    _, command, config = COMMANDS[name]
    defaults = {}
    for cls in (type(getattr(config(), "model", None)), config):
        if not dataclasses.is_dataclass(cls):
            continue
        defaults.update({f.name: getattr(cls(), f.name) if f.default is dataclasses.MISSING else f.default
                         for f in dataclasses.fields(cls)})
    checked = 0
    for param in command.params:
        if param.name in defaults and param.default is not None:
            value = param.type_cast_value(click.Context(command), param.default)
            expected = () if param.multiple and defaults[param.name] is None else defaults[param.name]
            assert value == (tuple(expected) if isinstance(expected, (list, tuple)) else expected), param.name
            checked += 1
    assert checked >= min(8, len(defaults) - 1)   # the prior's: all but progress


SETTINGS = {
    "capture": ((CaptureConfig, OneEuroConfig), {"hfov_deg", "focal_px", "camera_height", "pitch_deg", "max_people",
                                                "detector", "body", "height_reference", "min_cutoff", "beta"},
                ["video.mp4", "-o", "out"]),
    "serve": ((ServeSettings,), {"host", "port", "token", "weights", "height", "vmc", "body", "tls", "max_clients",
                                 "workers"}, []),
}
"""`humotion NAME`: the config dataclasses its options set, its options (by name) that are their
fields, and the arguments it cannot do without. capture's --height (heights and height_m),
--no-filter (filter.enabled) and --no-refine (refine) are its own options:
test_a_capture_without_options_runs_with_capture_configs_defaults holds them."""


def field_defaults(*classes: type) -> dict:
    """Field name -> its default (a default_factory's value) over the dataclasses, which share no names."""
    defaults = {}
    for cls in classes:
        fields = {f.name: f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
                  for f in dataclasses.fields(cls)}
        assert not fields.keys() & defaults.keys()
        defaults.update(fields)
    return defaults


@pytest.mark.parametrize("name", SETTINGS)
def test_every_option_of_a_setting_defaults_to_the_setting(name):
    """Each option named after a field of the command's settings gives that field's default when
    it is not used (None included): one written by hand with its own default fails."""
    from humotion.cli import main

    classes, names, required = SETTINGS[name]
    given = main.commands[name].make_context(name, list(required)).params
    assert names <= given.keys()
    defaults = field_defaults(*classes)
    assert {n: given[n] for n in sorted(names)} == {n: defaults[n] for n in sorted(names)}


def captured_config(args: list[str], tmp_path, monkeypatch) -> CaptureConfig:
    """The CaptureConfig `humotion capture PHOTO -o OUT ARGS` runs with (the capture itself replaced)."""
    from humotion.cli import main

    seen = []
    monkeypatch.setattr(lifting, "load_lifter", lambda weights: None)
    monkeypatch.setattr(pipeline, "capture", lambda source, out_dir, config, **kwargs:
                        seen.append(config) or CaptureResult([], [], []))
    result = CliRunner().invoke(main, ["capture", str(demo_photo_path()), "-o", str(tmp_path / "out"), *args],
                                catch_exceptions=False)
    assert result.exit_code == 0, result.output
    return seen[0]


def test_a_capture_without_options_runs_with_capture_configs_defaults(tmp_path, monkeypatch):
    assert captured_config([], tmp_path, monkeypatch) == CaptureConfig()
    args = ["--height", "1.7", "--height", "1=1.8", "--height-reference", "1", "--fov", "70", "--focal", "900",
            "--camera-height", "1.2", "--pitch", "10", "--max-people", "3", "--detector", "mediapipe", "--no-filter",
            "--filter-cutoff", "2", "--filter-beta", "0.5", "--no-refine", "--body", "low"]
    assert captured_config(args, tmp_path, monkeypatch) == CaptureConfig(
        height_m=1.7, heights={1: 1.8}, height_reference=1, hfov_deg=70.0, focal_px=900.0, camera_height=1.2,
        pitch_deg=10.0, max_people=3, detector="mediapipe", filter=OneEuroConfig(enabled=False, min_cutoff=2.0, beta=0.5),
        refine=None, body="low")


def test_sparse_widths_follow_hidden_on_the_command_line_and_in_the_config(monkeypatch):
    """`--hidden 64` and SparseConfig(hidden=64) build the same network: 128-wide feed-forward
    and decoder layers (2 x hidden), as the shipped default network was trained."""
    config = config_of("sparse", ["--hidden", "64", "--embed", "16"], monkeypatch)
    assert config.model == SparseConfig(hidden=64, embed=16)
    assert (config.model.feedforward, config.model.decoder) == (128, 128)
    network = SparsePoser(config.model)
    widths = {tuple(p.shape) for n, p in network.named_parameters() if "linear1.weight" in n or "decoder" in n}
    assert any(128 in shape for shape in widths) and not any(256 in shape for shape in widths)
    explicit = config_of("sparse", ["--hidden", "64", "--feedforward", "96"], monkeypatch)
    assert (explicit.model.feedforward, explicit.model.decoder) == (96, 128)


def test_the_prior_options_set_its_config(monkeypatch, tmp_path):
    args = ["--data", str(tmp_path), "-o", str(tmp_path / "p.npz"), "--fps", "2", "--exclude", "x", "--ridge", "0.01"]
    assert config_of("prior", args, monkeypatch) == PriorTrainConfig(
        data_root=str(tmp_path), out=str(tmp_path / "p.npz"), fps=2.0, exclude=("x",), ridge=0.01)


def test_old_flag_spellings_still_work(monkeypatch):
    assert config_of("sparse", ["--no-resume"], monkeypatch).resume is False
    assert config_of("lift", ["--causal"], monkeypatch).model.causal is True
    assert config_of("body", ["--no-correctives"], monkeypatch).model.correctives is False
    config = config_of("sparse", ["--source", "cmu", "--exclude", "x", "--speed", "0.8", "1.25"], monkeypatch)
    assert (config.sources, config.exclude, config.speed_range) == (("cmu",), ("x", "hdm05_jointlearning"), (0.8, 1.25))


def test_the_body_data_options_are_its_settings(monkeypatch, tmp_path):
    """`python -m humotion.body.command data --out X` generates with Settings(out=X)'s defaults;
    an option sets its field (the generation itself replaced)."""
    seen = []
    manifest = {"meshes": 0, "splits": {}, "bytes": 0, "lbs_vs_dqs_mean_mm": {"all": 0.0}}
    monkeypatch.setattr(body_command, "generate", lambda settings, command: seen.append(settings) or manifest)
    folder = ["--out", str(tmp_path / "data"), "--mocap", str(tmp_path)]
    for args in ([], ["--held-out-poses", "2", "--topology", "none", "--min-age", "18"]):
        result = CliRunner().invoke(body_command.body_data_commands, ["data"] + folder + args, catch_exceptions=False)
        assert result.exit_code == 0, result.output
    assert seen == [Settings(out=str(tmp_path / "data"), mocap=str(tmp_path)),
                    Settings(out=str(tmp_path / "data"), mocap=str(tmp_path), held_out_poses=2, topology="none",
                             min_age=18.0)]


def test_options_take_name_type_default_and_help_from_the_field():
    @dataclasses.dataclass
    class Settings:
        frames: int = 40
        """Window length, frames."""
        scale: tuple[float, float] = (0.5, 2.0)
        names: tuple[str, ...] | None = None
        """Names (repeatable)."""
        mirror: bool = True

    @click.command()
    @config_options(Settings, "frames", "scale", "names", "mirror", frames={"decls": ("--length", "frames")})
    def command(**options):
        click.echo(repr(Settings(**options)))

    assert field_help(Settings) == {"frames": "Window length, frames.", "names": "Names (repeatable)."}
    runner = CliRunner()
    assert runner.invoke(command, []).output.strip() == repr(Settings(names=()))
    out = runner.invoke(command, ["--length", "8", "--scale", "1", "3", "--names", "a", "--names", "b", "--no-mirror"])
    assert out.output.strip() == repr(Settings(8, (1.0, 3.0), ("a", "b"), False))
    help_text = runner.invoke(command, ["--help"]).output
    assert "Window length, frames.  [default: 40]" in help_text and "--mirror / --no-mirror" in help_text


def test_reported_errors_are_one_line_without_a_traceback():
    @click.command()
    @click.argument("value")
    def command(value):
        with reported(ValueError):
            raise ValueError(f"{value}: not a height")

    result = CliRunner().invoke(command, ["tall"])
    assert (result.exit_code, result.output) == (1, "Error: tall: not a height\n")
    assert isinstance(result.exception, SystemExit)


def test_show_log_prints_a_librarys_records_once_warnings_on_stderr():
    @click.command()
    def command():
        show_log("humotion.test_notes")
        show_log("humotion.test_notes")          # again: still one handler
        logging.getLogger("humotion.test_notes.inner").info("the address is %s", "here")
        logging.getLogger("humotion.test_notes").warning("a warning")
        logging.getLogger("humotion.test_notes").debug("not shown")

    result = CliRunner().invoke(command)
    assert (result.stdout, result.stderr) == ("the address is here\n", "a warning\n")


def test_a_renamed_option_keeps_its_old_spelling_out_of_help():
    @click.command()
    @click.option("--lifter", "--weights", "weights", cls=RenamedOption, old="--weights")
    def command(weights):
        click.echo(weights)

    runner = CliRunner()
    assert runner.invoke(command, ["--weights", "a.pt"]).output == "a.pt\n"
    assert runner.invoke(command, ["--lifter", "b.pt"]).output == "b.pt\n"
    help_text = runner.invoke(command, ["--help"]).output
    assert "--lifter" in help_text and "--weights" not in help_text


SHARED = ('click.option("--port"', 'click.option("--view', 'click.option("--host"', 'click.option("--asf"',
          'click.option("--units"', "ClickException(str(error)) from None")


@pytest.mark.parametrize("path", sorted({PACKAGE / "cli.py", *PACKAGE.glob("*/command.py"), *PACKAGE.glob("*/train*.py")}), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_shared_options_and_error_reporting_are_declared_once(path):
    """--port, --view, --host, the input options and the one-line error report come from humotion.options."""
    source = path.read_text()
    assert [s for s in SHARED if s in source] == []


@pytest.mark.parametrize("command_name, new", [("capture", "--lifter"), ("retarget", "--retargeter")])
def test_capture_and_retarget_weights_have_their_own_names_and_keep_the_old_one(command_name, new, tmp_path):
    from humotion.cli import main

    command = main.commands[command_name]
    weights, source = tmp_path / "w.pt", tmp_path / "walk.bvh"
    weights.write_bytes(b"")
    source.write_text("")
    extra = ["-o", str(tmp_path / "out")] + (["--to", "canonical"] if command_name == "retarget" else [])
    for spelling in (new, "--weights"):
        context = command.make_context(command_name, [str(source), *extra, spelling, str(weights)])
        assert context.params["weights"] == str(weights)
    help_text = CliRunner().invoke(main, [command_name, "--help"]).output
    assert new in help_text and "--weights" not in help_text

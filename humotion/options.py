"""Command-line options shared by humotion's commands (the command side: libraries never import this).

The `humotion train` commands take :func:`run_options`, turn them into
:class:`humotion.training.RunConfig` fields with :func:`run_settings` and print the run's summary
with :func:`echo_summary`.
"""

from __future__ import annotations

import json
import os

import click

from humotion.training import DEFAULT_DATA, EVALUATION_ONLY


def run_options(out_dir: str, epochs: int, batch_size: int, lr: float, checkpoint_every: int = 500):
    """Decorator adding the options every `humotion train` command takes (data, output folder,
    length of the run, seed, device, resume); turn them into config fields with run_settings."""
    options = [
        click.option("--data", "data_root", default=str(DEFAULT_DATA), show_default=True, help="Mocap folder tree."),
        click.option("--out", "out_dir", default=out_dir, show_default=True,
                     help="Output folder (checkpoints, log, weights)."),
        click.option("--epochs", default=epochs, show_default=True, help="Epochs over the training windows."),
        click.option("--steps", type=int, help="Stop after this many optimizer steps instead."),
        click.option("--batch-size", default=batch_size, show_default=True),
        click.option("--lr", default=lr, show_default=True, help="Adam learning rate."),
        click.option("--source", "sources", multiple=True, help="Train on these source folders only (repeatable)."),
        click.option("--exclude", multiple=True, default=EVALUATION_ONLY, show_default=True,
                     help="Leave these source folders out (repeatable; hdm05_jointlearning is evaluation-only)."),
        click.option("--seed", default=0, show_default=True),
        click.option("--device", default="cpu", show_default=True, help="cpu or cuda (torchrun for several GPUs)."),
        click.option("--threads", type=int, help="Torch CPU threads (1 is fastest on a busy shared machine)."),
        click.option("--checkpoint-every", default=checkpoint_every, show_default=True,
                     help="Steps between checkpoints."),
        click.option("--max-clips", type=int, help="Use only the first N clips of the split (quick runs)."),
        click.option("--no-resume", is_flag=True, help="Start afresh even if the output folder has checkpoints."),
    ]

    def decorate(command):
        for option in reversed(options):
            command = option(command)
        return command

    return decorate


def run_settings(options: dict) -> dict:
    """Config fields from the options of run_options (popped from `options`): resume, sources,
    and exclude, which always keeps the evaluation-only sources out."""
    return {"resume": not options.pop("no_resume"), "sources": options.pop("sources") or None,
            "exclude": tuple(dict.fromkeys((*options.pop("exclude"), *EVALUATION_ONLY)))}


def echo_summary(summary: dict) -> None:
    """Print a run's summary as JSON (rank 0 only; the validation metrics are in log.jsonl)."""
    if int(os.environ.get("RANK", "0")) == 0:
        click.echo(json.dumps({k: v for k, v in summary.items() if k != "val"}, indent=1))

"""`humotion train lift` and `humotion train prior`: the command lines of
humotion.capture.train_lift (also ``torchrun --nproc_per_node=4 -m humotion.capture.command ...``
for several GPUs, which runs the lifter's training) and humotion.capture.prior."""

from __future__ import annotations

import logging

import click

from humotion.capture.lifting import LiftingConfig
from humotion.capture.prior import PriorTrainConfig, train_prior
from humotion.capture.train_lift import LiftTrainConfig, train
from humotion.options import config_options, echo_summary, reported, run_options, run_settings


@click.command("lift", context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@run_options(LiftTrainConfig)
@config_options(LiftingConfig, "causal", "levels", "channels", "dropout")
@config_options(LiftTrainConfig, "fps", "targets", "stride", "lr_decay", "arm_raise")
def train_lift_command(causal, levels, channels, dropout, **options):
    """Train the 2D-to-3D lifting network on CMU mocap filmed by random virtual cameras.

    \b
    Examples:
      humotion train lift --out runs/lift --threads 1
      humotion train lift --causal --out runs/lift_causal
      humotion train lift --steps 100 --max-clips 10 --out /tmp/quick
      torchrun --nproc_per_node=4 -m humotion.capture.command --device cuda --batch-size 512
    """
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    config = LiftTrainConfig(model=LiftingConfig(channels=channels, levels=levels, dropout=dropout, causal=causal),
                             **run_settings(options), **options)
    echo_summary(train(config))


@click.command("prior", context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@config_options(PriorTrainConfig, "data_root", "out", "fps", "exclude", "ridge",
                data_root={"decls": ("--data", "data_root"), "type": click.Path(file_okay=False)},
                out={"decls": ("-o", "--out", "out")})
@reported(FileNotFoundError)
def train_prior_command(**options):
    """Fit the capture refinement's Gaussian pose prior on the training subjects' mocap."""
    config = PriorTrainConfig(**options)
    prior = train_prior(config)
    click.echo(f"pose prior from {prior.frames} poses -> {config.out}")


if __name__ == "__main__":
    train_lift_command()

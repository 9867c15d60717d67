"""`humotion train sparse`: the command line of humotion.sparse.train (also
``torchrun --nproc_per_node=4 -m humotion.sparse.command ...`` for several GPUs)."""

from __future__ import annotations

import logging

import click

from humotion.io.amass import load_body_model
from humotion.io.errors import MotionFileError
from humotion.options import config_options, echo_summary, reported, run_options, run_settings
from humotion.sparse.losses import TERMS, loss_weights
from humotion.sparse.model import MASK_TOKENS, TOKEN_GRADIENTS, SparseConfig
from humotion.sparse.train import SCENARIO_CHOICES, TrainConfig, initial_weights, train


@click.command("sparse", context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@run_options(TrainConfig)
@config_options(TrainConfig, "lr_final", "length", "fps", "stride", "scenario", "fov_deg", "tracking_loss_per_s",
                "speed_range", "position_weight", "init_weights", "workers", "smplh_model",
                scenario={"type": click.Choice(SCENARIO_CHOICES)}, fov_deg={"decls": ("--fov", "fov_deg")},
                tracking_loss_per_s={"decls": ("--tracking-loss", "tracking_loss_per_s")},
                speed_range={"decls": ("--speed", "speed_range")},
                init_weights={"decls": ("--init", "init_weights"), "type": click.Path(exists=True, dir_okay=False)},
                smplh_model={"type": click.Path(exists=True, dir_okay=False)})
@click.option("--ablate-loss", multiple=True, type=click.Choice(TERMS[1:]), help="Switch a loss term off (repeatable).")
@config_options(SparseConfig, "mask_token", "token_gradient", "hidden", "embed", "feedforward", "decoder",
                mask_token={"type": click.Choice(MASK_TOKENS)}, token_gradient={"type": click.Choice(TOKEN_GRADIENTS)})
def train_sparse_command(ablate_loss, mask_token, token_gradient, hidden, embed, feedforward, decoder, **options):
    """Train the headset-to-full-body model (SparsePoser) on the CMU mocap windows.

    \b
    Examples:
      humotion train sparse --out runs/sparse --epochs 20
      humotion train sparse --steps 200 --max-clips 20 --out /tmp/quick
      humotion train sparse --ablate-loss se3 --ablate-loss aux --out runs/no_se3_aux
      humotion train sparse --hidden 64 --embed 16 --out runs/narrow     # a smaller, faster network
      torchrun --nproc_per_node=4 -m humotion.sparse.command --device cuda --batch-size 256
      humotion train sparse --data ~/AMASS --smplh-model smplh/neutral/model.npz   # docs/amass.md
    """
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    config_model = SparseConfig(embed=embed, hidden=hidden, mask_token=mask_token, token_gradient=token_gradient,
                                feedforward=feedforward, decoder=decoder)
    if options.get("init_weights"):
        with reported(ValueError):
            initial_weights(TrainConfig(model=config_model, init_weights=options["init_weights"]))   # checked before any work
    if options.get("smplh_model"):
        with reported(MotionFileError):
            load_body_model(options["smplh_model"])      # checked once, before any work
    config = TrainConfig(weights=loss_weights(ablate=ablate_loss), **run_settings(options), model=config_model, **options)
    echo_summary(train(config))


if __name__ == "__main__":
    train_sparse_command()

"""Train the AvatarPoser-style peer (humotion.sparse.peers) with the shipped default network's
data and budget: the same training split and exclusions, 40-frame windows at 30 fps (stride 10),
the same augmentation and MC/HT mix, batch 64, Adam lr 1e-3, 1,700 steps (steps x batch matched).

    OMP_NUM_THREADS=1 nice -n 5 .venv/bin/python scripts/train_sparse_peer.py --out runs/peer-s0
    .venv/bin/python scripts/train_sparse_peer.py --steps 5 --max-clips 3 --out /tmp/peer-quick

Resumes from the newest checkpoint in --out. Weights: <out>/avatar_poser_best.pt (lowest
validation loss) and <out>/avatar_poser.pt (last step).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys

from humotion.sparse.peers import PeerConfig, train_peer
from humotion.sparse.train import TrainConfig

SHIPPED_EXCLUDE = ("hdm05_jointlearning", "cmu_iclone_ccskeleton")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="runs/peer")
    parser.add_argument("--steps", type=int, default=1700)
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--checkpoint-every", type=int, default=100)
    parser.add_argument("--max-clips", type=int)
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    config = TrainConfig(out_dir=args.out, steps=args.steps, batch_size=args.batch_size, seed=args.seed,
                         threads=args.threads, checkpoint_every=args.checkpoint_every, max_clips=args.max_clips,
                         exclude=SHIPPED_EXCLUDE, progress=not args.no_progress)
    summary = train_peer(config, PeerConfig(window=config.length))
    print(json.dumps({k: v for k, v in summary.items() if k != "val"}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

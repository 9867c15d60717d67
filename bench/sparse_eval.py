"""Sparse tracking accuracy on held-out subjects: one table, MC and HT, CMU test split and HDM05.

    .venv/bin/python bench/sparse_eval.py                       # shipped weights + baselines
    .venv/bin/python bench/sparse_eval.py --weights fixed=runs/fixed/sparse_poser.pt --json
    .venv/bin/python bench/sparse_eval.py $(bash scripts/train_sparse_ablations.sh --weights)

Rows (humotion.sparse.evaluation): the network (shipped weights unless --weights replaces them)
as SparseTracker runs it, its root anchored to the headset; "hold last hand" and "own
trajectory" baselines of that network; any further --weights LABEL=PATH (the fixed-token and
loss ablations trained by scripts/train_sparse_ablations.sh); then two peers (issue 27), unless
--no-peers: "kNN lookup (k=64)" (humotion.sparse.baselines: the 64 nearest training frames'
poses averaged) and "AvatarPoser-style peer" (humotion.sparse.peers, weights --peer-weights,
trained there by scripts/train_sparse_peer.py when missing: 1,700 steps, about 25 CPU minutes of
one thread, 66 minutes on the shared machine of the model card's run). Like the network, both
are solved after (humotion.sparse.solve), so the rows compare models, not post-processing.
Always: "network alone (no solve)" (the first network without the solve) and "truth" (the
motion capture's own penetration and skating). Columns beyond the usual accuracy: target (wrist
to the tracked hand while seen), pen / depth (feet below the floor), skate (foot speed in
contact); humotion.sparse.metrics and evaluation say how they are measured.
Test data: the CMU subjects of the collection's test split (never trained on; each take once)
and, across datasets, HDM05 (evaluation only); clips cut to --max-seconds.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

from humotion.sparse.baselines import KnnPoser
from humotion.sparse.batches import DEFAULT_DATA
from humotion.sparse.evaluation import evaluate_models, format_table, test_sets
from humotion.sparse.model import load_sparse_model
from humotion.sparse.peers import load_peer
from humotion.sparse.tracker import DEFAULT_WEIGHTS


PEER_WEIGHTS = Path("runs/peer-s0/avatar_poser_best.pt")
KNN, PEER = "kNN lookup (k=64)", "AvatarPoser-style peer"


def peer_models(peer_weights: Path) -> dict:
    """The two peers of the network: the kNN lookup over the training frames and the
    AvatarPoser-style network (trained into peer_weights' folder first when the file is missing)."""
    if not peer_weights.is_file():
        print(f"no peer weights at {peer_weights}: training them (scripts/train_sparse_peer.py)", file=sys.stderr)
        sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
        from train_sparse_peer import main as train_peer
        train_peer(["--out", str(peer_weights.parent), "--no-progress"])
    return {KNN: KnnPoser.from_training(k=64), PEER: load_peer(peer_weights)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--weights", action="append", default=[], metavar="LABEL=PATH",
                        help="a model to evaluate (repeatable; default: the shipped weights as 'network')")
    parser.add_argument("--with-shipped", action="store_true", help="evaluate the shipped weights first, then --weights")
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--max-clips", type=int, help="first N clips of each test set (quick runs)")
    parser.add_argument("--max-seconds", type=float, default=60.0, help="cut clips to this length")
    parser.add_argument("--set", dest="sets", action="append", choices=("CMU test", "HDM05"),
                        help="evaluate on this test set only (repeatable; default both)")
    parser.add_argument("--json", action="store_true", help="print the table as JSON")
    parser.add_argument("--no-peers", action="store_true", help="leave out the kNN and AvatarPoser-style rows")
    parser.add_argument("--peer-weights", type=Path, default=PEER_WEIGHTS,
                        help="AvatarPoser-style peer weights (trained by scripts/train_sparse_peer.py when missing)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)

    weights = [w.split("=", 1) for w in args.weights]
    if args.with_shipped or not weights:
        weights.insert(0, ["network", str(DEFAULT_WEIGHTS)])
    models = {label: load_sparse_model(path) for label, path in weights}
    if not args.no_peers:
        models.update(peer_models(args.peer_weights))
    sets = test_sets(args.data, args.max_clips)
    sets = {name: clips for name, clips in sets.items() if not args.sets or name in args.sets}
    rows = evaluate_models(models, sets, max_seconds=args.max_seconds)
    print(json.dumps(rows, indent=1) if args.json else format_table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())

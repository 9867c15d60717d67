#!/usr/bin/env bash
# Train the sparse-tracking ablations of bench/sparse_eval.py with an equal budget each:
# a baseline, the fixed mask token, and each loss term switched off. Two runs at a time, one CPU
# thread each; every run checkpoints and resumes, so re-running the script continues where it stopped.
#   bash scripts/train_sparse_ablations.sh [STEPS] [OUT]      (defaults: 500 steps, runs/ablations)
# Then: .venv/bin/python bench/sparse_eval.py $(bash scripts/train_sparse_ablations.sh --weights)
set -euo pipefail
cd "$(dirname "$0")/.."
steps=${1:-500}
out=${2:-runs/ablations}
declare -A flags=(
  [baseline]=""
  [fixed-token]="--mask-token fixed"
  [no-smooth]="--ablate-loss smooth"
  [no-se3]="--ablate-loss se3"
  [no-forecast]="--ablate-loss forecast"
  [no-aux]="--ablate-loss aux"
)
order=(baseline fixed-token no-smooth no-se3 no-forecast no-aux)
if [[ "$steps" == "--weights" ]]; then
  for name in "${order[@]}"; do echo -n "--weights $name=$out/$name/sparse_poser_best.pt "; done; echo
  exit 0
fi
train() {
  local name=$1
  # shellcheck disable=SC2086
  .venv/bin/humotion train sparse --out "$out/$name" --steps "$steps" --threads 1 --checkpoint-every 100 \
    --exclude hdm05_jointlearning --exclude cmu_iclone_ccskeleton ${flags[$name]} > "$out/$name.out" 2>&1
}
mkdir -p "$out"
(for name in "${order[@]:0:3}"; do train "$name"; done) &
(for name in "${order[@]:3:3}"; do train "$name"; done) &
wait
echo "done: $out"

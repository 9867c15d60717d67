#!/usr/bin/env bash
# Train the sparse-tracking ablations of bench/sparse_eval.py with an equal budget each:
# a baseline, the fixed mask token, the token's full gradient (reaching the encoder), and each loss
# term switched off. Two runs at a time, one CPU thread each; every run checkpoints and resumes, so
# re-running the script continues where it stopped.
#   bash scripts/train_sparse_ablations.sh [STEPS] [OUT]      (defaults: 500 steps, runs/ablations)
# Other seeds (run-to-run spread), e.g. the baseline twice more:
#   SEEDS="1 2" VARIANTS=baseline bash scripts/train_sparse_ablations.sh      (runs NAME-seedN)
# Other networks or settings for every run, e.g. the shipped `fast` recipe:
#   TRAIN_ARGS="--hidden 64 --embed 16" bash scripts/train_sparse_ablations.sh 1700 runs/ablations-fast
# Then: .venv/bin/python bench/sparse_eval.py $(bash scripts/train_sparse_ablations.sh --weights)
set -euo pipefail
cd "$(dirname "$0")/.."
steps=${1:-500}
out=${2:-runs/ablations}
declare -A flags=(
  [baseline]=""
  [fixed-token]="--mask-token fixed"
  [full-gradient]="--token-gradient full"
  [no-smooth]="--ablate-loss smooth"
  [no-se3]="--ablate-loss se3"
  [no-forecast]="--ablate-loss forecast"
  [no-aux]="--ablate-loss aux"
)
read -r -a order <<< "${VARIANTS:-baseline fixed-token full-gradient no-smooth no-se3 no-forecast no-aux}"
read -r -a seeds <<< "${SEEDS:-0}"
runs=()
for name in "${order[@]}"; do
  for seed in "${seeds[@]}"; do runs+=("$name:$seed"); done
done
run_dir() {  # NAME for seed 0, NAME-seedN otherwise
  if [[ "$2" == 0 ]]; then echo "$1"; else echo "$1-seed$2"; fi
}
if [[ "$steps" == "--weights" ]]; then
  for run in "${runs[@]}"; do
    dir=$(run_dir "${run%%:*}" "${run##*:}")
    echo -n "--weights $dir=$out/$dir/sparse_poser_best.pt "
  done; echo
  exit 0
fi
train() {
  local name=${1%%:*} seed=${1##*:}
  local dir
  dir=$(run_dir "$name" "$seed")
  # shellcheck disable=SC2086
  .venv/bin/humotion train sparse --out "$out/$dir" --steps "$steps" --threads 1 --checkpoint-every 100 --seed "$seed" \
    --exclude hdm05_jointlearning --exclude cmu_iclone_ccskeleton ${flags[$name]} ${TRAIN_ARGS:-} > "$out/$dir.out" 2>&1
}
mkdir -p "$out"
half=$(( (${#runs[@]} + 1) / 2 ))
(for run in "${runs[@]:0:half}"; do train "$run"; done) &
(for run in "${runs[@]:half}"; do train "$run"; done) &
wait
echo "done: $out"

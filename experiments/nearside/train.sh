#!/usr/bin/env bash
# One training run of the near-side study, on the schedule of `eg-bench standard` (1000 steps,
# 144x108, CPU, one thread, compiled rasteriser). Writes $OUT/runs/ENTRY/seedSEED (skipped when
# its metrics.json exists) and its log $OUT/logs/ENTRY-seedSEED.log.
#   usage: train.sh ENTRY SEED METHOD DATA [more eg-train flags]
#   CHECKPOINT_EVERY=100 keeps a checkpoint every 100 steps (for --checkpoints all); default 500.
set -euo pipefail
[ $# -ge 4 ] || { sed -n '2,7p' "$0"; exit 2; }
entry=$1; seed=$2; method=$3; data=$4; shift 4
OUT=${OUT:-outputs/experiments/nearside}
every=${CHECKPOINT_EVERY:-500}
keep=2; [ "$every" = 100 ] && keep=20  # as in the measured runs
run=$OUT/runs/$entry/seed$seed
[ -f "$run/metrics.json" ] && { echo "done: $run"; exit 0; }
mkdir -p "$OUT/logs"
echo "training $run"
eg-train "$method" "$@" --data "$data" --max-steps 1000 --seed "$seed" --run-dir "$run" \
  --num-threads 1 --model.raster.backend cpp --quiet --no-save-eval-images \
  --checkpoint-every "$every" --keep-checkpoints "$keep" > "$OUT/logs/$entry-seed$seed.log" 2>&1

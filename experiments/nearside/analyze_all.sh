#!/usr/bin/env bash
# Every `eg-analyze nearside` pass of the near-side study, on the runs of train_all.sh
# (resumable: finished outputs are skipped). Writes under $OUT/analysis:
#   <entry>-seed0/       default, seedsplit, occlusion: Gaussians at every checkpoint (the step
#                        table, the figure nearside.png), em100 at its last checkpoint
#   cancel-step<N>/      Default seed 0 at steps 300 and 1000: per-pixel gradient cancellation in
#                        the clear views 0009, 0017 (indices 7, 14) and view 0001 (index 0)
#   pix/<entry>-seed<k>/ every run, test pixels only (hidden / out-of-view columns of the tables)
set -uo pipefail
OUT=${OUT:-outputs/experiments/nearside}
A=$OUT/analysis
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
mkdir -p "$OUT/logs"
analyze() {  # OUTPUT_DIR eg-analyze-flags...
  local out=$1; shift
  [ -f "$out/nearside.json" ] && return 0
  echo "eg-analyze nearside $* -> $out"
  eg-analyze nearside "$@" --device cpu --out "$out" > "$OUT/logs/analyze-$(basename "$out").log" 2>&1 \
    || echo "  failed, see $OUT/logs/analyze-$(basename "$out").log"
}
for m in default seedsplit occlusion; do
  analyze "$A/$m-seed0" --run "$OUT/runs/$m/seed0" --checkpoints all
done
analyze "$A/em100-seed0" --run "$OUT/runs/em100/seed0" --checkpoints latest
for st in 0000300 0001000; do
  analyze "$A/cancel-step$st" --run "$OUT/runs/default/seed0/checkpoints/step-$st.pt" --checkpoints none \
    --no-train-pixels --cancellation-views 7 14 0
done
for run in "$OUT"/runs/*/seed*; do
  [ -f "$run/metrics.json" ] || continue
  analyze "$A/pix/$(basename "$(dirname "$run")")-$(basename "$run")" --run "$run" --checkpoints none --no-train-pixels
done

#!/usr/bin/env bash
# Every training run of the near-side study (27 runs of 1000 steps; resumable: finished
# runs are skipped). Run from the repository root.
#   usage: train_all.sh [methods|scenes|error-mass|all]   (default all)
# methods:    default seedsplit occlusion guided guided-occlusion, seeds 0-2 (seed 0 with a
#             checkpoint every 100 steps)
# scenes:     Default on the clear-views-x4 scene (seeds 0, 1) and the two oracle scenes (seeds
#             0-2); builds the scenes first under $OUT/scenes
# error-mass: the negative result, seeds 0-2, and half the growth (seed 0); needs
#             `pip install ./experiments/nearside/errormass_negative`
set -euo pipefail
here=$(dirname "$0")
export OUT=${OUT:-outputs/experiments/nearside}
what=${1:-all}
if [[ $what == methods || $what == all ]]; then
  for s in 0 1 2; do for m in default seedsplit occlusion guided guided-occlusion; do
    every=500; [ "$s" = 0 ] && every=100
    CHECKPOINT_EVERY=$every "$here/train.sh" "$m" "$s" "exploregs-$m" builtin:nearside
  done; done
fi
if [[ $what == scenes || $what == all ]]; then
  sc=$OUT/scenes
  [ -f "$sc/nearside-clear4x/split.json" ] || python "$here/make_dup.py" 3 "$sc/nearside-clear4x"
  [ -f "$sc/nearside-oracle/split.json" ] || python "$here/make_oracle.py" "$sc/nearside-oracle" 1
  [ -f "$sc/nearside-oracle3/split.json" ] || python "$here/make_oracle.py" "$sc/nearside-oracle3" 3
  for s in 0 1; do "$here/train.sh" default-clear4x "$s" exploregs-default "$sc/nearside-clear4x"; done
  for s in 0 1 2; do
    "$here/train.sh" default-oracle "$s" exploregs-default "$sc/nearside-oracle"
    "$here/train.sh" default-oracle3 "$s" exploregs-default "$sc/nearside-oracle3"
  done
fi
if [[ $what == error-mass || $what == all ]]; then
  for s in 0 1 2; do
    "$here/train.sh" em100 "$s" exploregs-default builtin:nearside --strategy error-mass --method-name exploregs-em100
  done
  "$here/train.sh" em050 0 exploregs-default builtin:nearside --strategy error-mass --strategy.error-share 0.5 \
    --method-name exploregs-em050
fi

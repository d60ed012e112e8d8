#!/usr/bin/env bash
# The count rule's trial on CUDA (issue 55): eg-train exploregs-mcmc --strategy.cap-max validated on
# the built-in tiny scene with the torch renderer on the GPU, twice, so that the trial's copy and
# restore of a CUDA pipeline (its generator included) is exercised where most people train. Run
# ON the lent machine from the repository root, with .gpu-stage carried (stage.sh fills it):
#     bash experiments/gpu/count_rule_cuda.sh
# Prints each run's decision line and final figures, and whether the two runs chose alike.
set -uo pipefail
SITE=/tmp/eg_count_rule_site
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target "$SITE" .gpu-stage/wheels/*.whl
PYTHONPATH=$SITE python3 -m pip install -q --no-index --no-deps --no-build-isolation -e .
export PYTHONPATH=$SITE EXPLOREGS_CACHE=/tmp/eg_count_rule_cache PYTHONUNBUFFERED=1
PATH=$(python3 -c 'import sysconfig; print(sysconfig.get_path("scripts"))'):$PATH
nvidia-smi --query-gpu=name --format=csv,noheader
for run in 1 2; do
    eg-train exploregs-mcmc --data builtin:tiny --device cuda --model.raster.backend torch --max-steps 1500 \
        --strategy.cap-max validated --eval-count 1 --run-dir "/tmp/eg_count_rule_$run" 2>&1 | grep -v "^step "
done
python3 - <<'PY'
import json
a, b = (json.load(open(f"/tmp/eg_count_rule_{r}/metrics.json")) for r in (1, 2))
for m in (a, b):
    print(f"{m['num_gaussians']} Gaussians, {m['psnr']:.3f} dB | {m['count_decision']}")
print("the two runs kept the same count:", a["num_gaussians"] == b["num_gaussians"])
PY

#!/usr/bin/env bash
# One short device session (about 8 minutes): the Pallas kernel's tests compiled for the GPU, then
# bench_render and bench_train with both compositors side by side (scripts/gpu_check.sh's render and
# train stages). Figures go to OUT (first argument, else $OUT).
#
#   scripts/gpu_session.sh "$OUT"
set -uo pipefail
cd "$(dirname "$0")/.."
out="${1:-${OUT:-runs/gpu_session}}"
mkdir -p "$out"
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" XLA_PYTHON_CLIENT_PREALLOCATE=false
# The device images name their interpreter python3 only.
command -v python >/dev/null || { mkdir -p /tmp/pybin && ln -sf "$(command -v python3)" /tmp/pybin/python; export PATH="/tmp/pybin:$PATH"; }
timeout 120 python -m pytest -q -n 0 -p no:cacheprovider tests/unit/test_pallas_composite.py 2>&1 | tee "$out/pallas_tests.log" | tail -5
BUDGET_S="${RENDER_S:-220}" scripts/gpu_check.sh "$out/render" --stages render --render-configs 2dgs,tex8-mip-prefilter 2>&1 | tee "$out/render.log" | tail -40
BUDGET_S="${TRAIN_S:-150}" scripts/gpu_check.sh "$out/train" --stages train --train-configs 2dgs,tex8-mip-prefilter 2>&1 | tee "$out/train.log" | tail -30

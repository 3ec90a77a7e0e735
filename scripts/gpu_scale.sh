#!/usr/bin/env bash
# The paper's scale on one GPU (about 8 minutes of device time): experiments.bench_scale at 1M and
# 3M Gaussians and 1237x822 views (every host-side stage of a run, the Eq. 6 renders, evaluation,
# and the 2DGS and textured training steps with the device's peak memory). Figures go to OUT (first
# argument, else $OUT, else runs/gpu_scale): bench_scale_<N>.json and their logs. A stage cut
# short by its time limit keeps the rows it measured (the JSON is rewritten after every row).
#
#   scripts/gpu_scale.sh "$OUT"
set -uo pipefail
cd "$(dirname "$0")/.."
out="${1:-${OUT:-runs/gpu_scale}}"
mkdir -p "$out"
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
# One process at a time, but the 3M state must not find 75% of the card taken by a preallocation.
export XLA_PYTHON_CLIENT_PREALLOCATE=false
command -v python >/dev/null || { mkdir -p /tmp/pybin && ln -sf "$(command -v python3)" /tmp/pybin/python; export PATH="/tmp/pybin:$PATH"; }
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null | tee "$out/gpu.txt"
python -c "import jax; print('jax', jax.__version__, jax.devices())"
timeout "${S1M:-200}" python -m experiments.bench_scale --gaussians 1000000 --views 8 --steps 3 \
  --json "$out/bench_scale_1m.json" 2>&1 | tee "$out/bench_scale_1m.log" | grep -v "^\s*$" | tail -40
# At 3M the host-side file rows (checkpoint, PLY: gigabytes through this machine's disk) are left
# to the CPU runs: the device's time goes to the renders and the steps.
timeout "${S3M:-200}" python -m experiments.bench_scale --gaussians 3000000 --views 8 --steps 3 \
  --skip checkpoint,ply --json "$out/bench_scale_3m.json" 2>&1 | tee "$out/bench_scale_3m.log" | grep -v "^\s*$" | tail -40

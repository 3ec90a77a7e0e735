#!/usr/bin/env bash
# The paper's scale on one GPU (about 8 minutes of device time): experiments.bench_scale at 1M
# Gaussians (every row) and 3M (the rows that are not file or render work), 1237x822 views: every
# host-side stage of a run, the Eq. 6 renders, evaluation, and the 2DGS and textured training steps
# with their own peak device memory; then, with BEER set (a pinhole COLMAP scene, e.g. the capture
# undistorted by `python -m experiments.device_check --bundle .device --beer ../shared/data/beer`),
# `train --plan` of patexgs on it at full size and 1M / 3M Gaussians, its steps timed on the device,
# beside what bench_scale measured. Figures go to OUT (first argument, else $OUT, else
# runs/gpu_scale): bench_scale_<N>.json, plan_<N>.json and the logs. A stage cut short by its time
# limit keeps the rows it measured (the JSON is rewritten after every row).
#
#   BEER=.device/beer scripts/gpu_scale.sh "$OUT"     (carry .device/beer)
set -uo pipefail
cd "$(dirname "$0")/.."
out="${1:-${OUT:-runs/gpu_scale}}"
mkdir -p "$out"
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
# Each step row runs in its own process beside the first: no process may take 75% of the card.
export XLA_PYTHON_CLIENT_PREALLOCATE=false
command -v python >/dev/null || { mkdir -p /tmp/pybin && ln -sf "$(command -v python3)" /tmp/pybin/python; export PATH="/tmp/pybin:$PATH"; }
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null | tee "$out/gpu.txt"
timeout "${S1M:-190}" python -m experiments.bench_scale --gaussians 1000000 --views 8 --steps 3 \
  --json "$out/bench_scale_1m.json" 2>&1 | tee "$out/bench_scale_1m.log" | grep -v "^\s*$" | tail -30
# At 3M the file rows (checkpoint, PLY: gigabytes through this machine's disk), the renders and the
# Eq. 6 counts are left to the 1M run and the CPU: the device's time goes to the host events and steps.
timeout "${S3M:-170}" python -m experiments.bench_scale --gaussians 3000000 --views 8 --steps 3 \
  --skip counts,checkpoint,ply,eval --json "$out/bench_scale_3m.json" 2>&1 | tee "$out/bench_scale_3m.log" \
  | grep -v "^\s*$" | tail -20
if [ -n "${BEER:-}" ]; then
  for n in 1000000 3000000; do
    timeout "${SPLAN:-70}" python -m patexgs_jax.train --data "$BEER" --factor 1 --method patexgs --preset paper \
      --max-gaussians "$n" --plan --plan-steps 3 --plan-device rtx4090-24gb --json "$out/plan_$n.json" 2>&1 \
      | tee "$out/plan_$n.log" | grep -v "train views" | tail -12
  done
fi

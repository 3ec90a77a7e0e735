#!/usr/bin/env bash
# The project's check on one GPU (see the README): the renderer's float32 tests, bench_render (50k
# Gaussians at 640x480, 1M at 1920x1080), bench_train (100k at 1280x960), bench_viewer (640x480) and,
# with BEER set, a full-size study of that capture for 2dgs and patexgs, within BUDGET_S seconds
# (default 510: a 9-minute device session with room to start). Figures and logs go to OUT (first
# argument, else $OUT, else runs/gpu_check): device_check.json (with provenance), device_check.md.
#
#   BEER=../shared/data/beer VIEWER_RUN=runs/bench_viewer/patexgs scripts/gpu_check.sh "$OUT"
#
# The render and train stages time both compositors side by side in one process (the XLA one and the
# Pallas kernel, RenderConfig.compositor; --compositors xla narrows it). A short session, the
# kernel checked on the GPU and the render side by side (about 4 minutes of device time):
#
#   python -m pytest -q tests/unit/test_pallas_composite.py && \
#     BUDGET_S=180 scripts/gpu_check.sh "$OUT" --stages render --render-configs 2dgs,tex8-mip-prefilter
#
# Extra arguments go to `python -m experiments.device_check` (e.g. --stages render,train).
set -uo pipefail
cd "$(dirname "$0")/.."
out="${1:-${OUT:-runs/gpu_check}}"
shift || true
# Several processes share the GPU (the tests' workers, the stages): allocate on demand, not 75% each.
export XLA_PYTHON_CLIENT_PREALLOCATE=false
# Stages compile some of the same programs: keep them between processes.
export JAX_COMPILATION_CACHE_DIR="${JAX_COMPILATION_CACHE_DIR:-/tmp/patexgs_xla_cache}"
args=(--out "$out" --budget-s "${BUDGET_S:-510}")
[ -n "${BEER:-}" ] && args+=(--beer "$BEER")
[ -n "${VIEWER_RUN:-}" ] && args+=(--viewer-run "$VIEWER_RUN")
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null || true
python -c "import jax; print('jax', jax.__version__, jax.devices())"
exec python -m experiments.device_check "${args[@]}" "$@"

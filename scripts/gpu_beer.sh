#!/usr/bin/env bash
# Beer at full size with the small preset on one GPU, inside BUDGET_S seconds (default 540: a
# 15-minute device session with room to start and to rerun): 2dgs and patexgs from one shared
# stage 1, evaluated at 1, 1/2, 1/4 and 1/8, then the renderer and viewer benchmarks while the
# budget lasts. Figures in OUT/gpu_beer.json (first argument, else $OUT, else runs/gpu_beer); the
# layout is in docs/benchmarks.md ("The beer GPU check").
#
#   BEER=.device/beer scripts/gpu_beer.sh "$OUT"              # on the GPU (see docs/benchmarks.md)
#   PATEXGS_GPU_CHECK_REHEARSE=1 BEER=../shared/data/beer scripts/gpu_beer.sh /tmp/rehearsal   # CPU
#
# The rehearsal runs the same phases at factor 8, a short tiny schedule and toy benchmark sizes.
# Extra arguments go to `python -m experiments.gpu_beer` (e.g. --no-lpips, --test-views 4).
set -uo pipefail
cd "$(dirname "$0")/.."
out="${1:-${OUT:-runs/gpu_beer}}"
shift || true
if [ -z "${BEER:-}" ]; then
  echo "gpu_beer.sh: set BEER to the beer capture (a COLMAP folder; .device/beer from" \
       "python -m experiments.device_check --bundle .device --beer PATH on a machine with pycolmap)" >&2
  exit 2
fi
export XLA_PYTHON_CLIENT_PREALLOCATE=false PATEXGS_PROGRESS=0 PYTHONUNBUFFERED=1
export JAX_COMPILATION_CACHE_DIR="${JAX_COMPILATION_CACHE_DIR:-/tmp/patexgs_xla_cache}"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null || true
python=${PYTHON:-python}
budget=()
[ -n "${BUDGET_S:-}" ] && budget=(--budget-s "$BUDGET_S")  # (default 540 s; the rehearsal's 4 h)
exec "$python" -m experiments.gpu_beer --data "$BEER" --out "$out" "${budget[@]}" "$@"

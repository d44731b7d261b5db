#!/usr/bin/env bash
# A budget ladder of train_gs on one GPU: several bench_train runs of one bundle (each a variant and an
# iteration count at the GPU budget, whole images, LPIPS where weights are found), side by side as separate
# processes, so that a lease of minutes measures where more steps stop paying. A step is launch-bound on the
# host (benchmarks/RESULTS.md, the GPU check), so runs side by side share the device well until its own work
# per step adds up to the wall time.
#
#   benchmarks/gpu_ladder.sh BUNDLE WHEELS OUT BUILDING JOB...
#
# JOB is VARIANT:ITERATIONS[:LOG_EVERY[:KEY=VALUE,...]], the keys [train_gs] keys for that run (bench_train's
# --set), e.g. benchmarks/gpu_ladder.sh gcw.npz wheels out gcw_dev mlp:1000 sh:5000:500
# mlp:4000:500:densify.opacity_reset_interval=1000
# OUT receives each run's log (its last line "result: {...}", bench_train's figures) and the CUDA tests' log.
# Environment: TORCH_CUDA_ARCH_LIST (default 9.0), JOB_S (each run's time limit, default 460 s),
# FACADE_LPIPS_DIR (as gpu_check.sh), TESTS=0 to skip the CUDA tests run beside the jobs.
set -euo pipefail

BUNDLE=${1:?usage: benchmarks/gpu_ladder.sh BUNDLE WHEELS OUT BUILDING JOB...}
WHEELS=${2:?}
OUT=${3:?}
BUILDING=${4:?}
shift 4
PY=${PYTHON:-python3}
JOB_S=${JOB_S:-460}
export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} PYTHONUNBUFFERED=1 TQDM_DISABLE=1 FACADE_BUDGET=gpu
mkdir -p "$OUT"
ROOT=$(cd "$(dirname "$0")/.." && pwd)
cd "$ROOT"
[ -f "$BUNDLE" ] || { echo "gpu_ladder: $BUNDLE: expected a bundle (bench_train.py --save-bundle), found no file" >&2; exit 2; }
T0=$(date +%s)

. benchmarks/gsplat_build.sh
build_gsplat "$WHEELS" "$OUT" || exit 1
echo "== $(( $(date +%s) - T0 )) s: gsplat built; ${#@} runs side by side"
export PYTHONPATH="$ROOT${PYTHONPATH:+:$PYTHONPATH}"

pids=()
for job in "$@"; do
  IFS=: read -r variant iters every keys <<< "$job"
  sets=()
  IFS=, read -ra pairs <<< "${keys:-}"
  for kv in "${pairs[@]}"; do sets+=(--set "$kv"); done
  log="$OUT/${variant}_${iters}${keys:+_${keys//[^A-Za-z0-9]/_}}.log"
  OMP_NUM_THREADS=2 timeout "$JOB_S" "$PY" benchmarks/bench_train.py --bundle "$BUNDLE" --building "$BUILDING" \
    --device cuda --patch-px 0 --no-write --lpips --only "$variant" --iterations "$iters" \
    --log-every "${every:-$(( iters / 10 ))}" "${sets[@]}" > "$log" 2>&1 &
  pids+=($!)
done
if [ "${TESTS:-1}" != 0 ]; then
  OMP_NUM_THREADS=2 timeout "$JOB_S" "$PY" -m pytest -q -p no:cacheprovider -m gpu tests/splatting/test_gsplat.py \
    tests/training/test_trainer_gpu.py > "$OUT/tests.log" 2>&1 &
  pids+=($!)
fi
for p in "${pids[@]}"; do wait "$p" || true; done
echo "== $(( $(date +%s) - T0 )) s: done"
for f in "$OUT"/*.log; do
  echo "--- $(basename "$f"): $(grep -h '^result: \|passed\|failed\|stopped' "$f" | tail -1 | cut -c1-400)"
done

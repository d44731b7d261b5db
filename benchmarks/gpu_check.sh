#!/usr/bin/env bash
# The GPU check of train_gs in one command: builds gsplat from its wheel, runs the CUDA tests, times the mlp
# and sh models per whole-image iteration on demo with the GPU's peak memory, trains one short
# accuracy-vs-time point and prints one summary table. About 6 minutes on an H100 (at most 8).
#
# It runs on a fresh GPU machine with torch (and numpy, scipy, pytest, tqdm) but none of the I/O stack
# (open3d, pycolmap, OpenEXR), from the project's root, with two things beside the tree:
#   BUNDLE  demo's training data with its exposure estimate, written where the I/O stack is:
#             .venv/bin/python benchmarks/bench_train.py --data-root /tmp/bench --save-bundle BUNDLE
#   WHEELS  a folder holding gsplat's wheel: pip download --no-deps --only-binary=:all: -d WHEELS gsplat==1.5.3
#
#   benchmarks/gpu_check.sh BUNDLE WHEELS [OUT]
#
# OUT (default: a new temporary folder) receives each step's log and summary.md. Environment:
#   TORCH_CUDA_ARCH_LIST  the GPU architecture gsplat is built for (default 9.0: H100, H200)
#   SPEED_ITERS           timed iterations per model with gsplat (default 300, after 30 warm-up ones)
#   ACCURACY_ITERS        whole-image iterations of the accuracy point (default 1000)
#   DEVICE                cuda (default), or cpu for a dry run of the Python steps (no gsplat, tiny sizes)
set -euo pipefail

BUNDLE=${1:?usage: benchmarks/gpu_check.sh BUNDLE WHEELS [OUT]}
WHEELS=${2:?usage: benchmarks/gpu_check.sh BUNDLE WHEELS [OUT]}
OUT=${3:-$(mktemp -d -t gpu_check.XXXXXX)}
DEVICE=${DEVICE:-cuda}
SPEED_ITERS=${SPEED_ITERS:-300}
ACCURACY_ITERS=${ACCURACY_ITERS:-1000}
PY=${PYTHON:-python3}
export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} PYTHONUNBUFFERED=1 TQDM_DISABLE=1
mkdir -p "$OUT"
ROOT=$(cd "$(dirname "$0")/.." && pwd)
cd "$ROOT"
[ -f "$BUNDLE" ] || { echo "gpu_check: $BUNDLE: expected demo's bundle (see the header), found no file" >&2; exit 2; }
T0=$(date +%s)
step() { echo "== $(( $(date +%s) - T0 )) s: $*"; }

# gsplat: installed from the wheel into a folder of its own, then its CUDA code built (JIT) once
SITE="$OUT/site"
GSPLAT_BUILD_S=-
if [ "$DEVICE" = cuda ]; then
  "$PY" -c "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)" \
    || { echo "gpu_check: expected a CUDA device, found none (DEVICE=cpu for a dry run)" >&2; exit 2; }
  if ! "$PY" -c "import gsplat" 2>/dev/null; then
    WHEEL=$(ls "$WHEELS"/gsplat-*.whl 2>/dev/null | head -1) \
      || { echo "gpu_check: $WHEELS: expected gsplat's wheel, found none" >&2; exit 2; }
    "$PY" -m pip install -q --no-index --no-deps --no-compile --target "$SITE" "$WHEEL"
    export PYTHONPATH="$SITE${PYTHONPATH:+:$PYTHONPATH}"
  fi
  step "building gsplat for sm_${TORCH_CUDA_ARCH_LIST/./}"
  B0=$(date +%s)
  MAX_JOBS=${MAX_JOBS:-16} "$PY" -c "from gsplat.cuda._backend import _C; assert _C is not None" \
    > "$OUT/gsplat_build.log" 2>&1 || { tail -30 "$OUT/gsplat_build.log"; exit 1; }
  GSPLAT_BUILD_S=$(( $(date +%s) - B0 ))
fi
export PYTHONPATH="$ROOT${PYTHONPATH:+:$PYTHONPATH}"

step "CUDA tests"
set +e
"$PY" -m pytest -q -p no:cacheprovider -m gpu tests/splatting/test_gsplat.py tests/training/test_trainer_gpu.py \
  > "$OUT/tests.log" 2>&1
set -e
tail -3 "$OUT/tests.log"

BENCH=("$PY" benchmarks/bench_train.py --bundle "$BUNDLE" --device "$DEVICE" --patch-px 0 --no-write)
if [ "$DEVICE" = cpu ]; then  # a dry run: few splats, few iterations
  BENCH+=(--init-points 300 --max-gaussians 600)
  SPEED_ITERS=2 ACCURACY_ITERS=2 WARMUP=1
fi
WARMUP=${WARMUP:-30}

step "speed"
"${BENCH[@]}" --speed "$SPEED_ITERS" --warmup "$WARMUP" --only mlp,sh > "$OUT/speed.log" 2>&1 \
  || { tail -30 "$OUT/speed.log"; exit 1; }
step "accuracy after $ACCURACY_ITERS whole-image iterations"
"${BENCH[@]}" --iterations "$ACCURACY_ITERS" --only mlp > "$OUT/accuracy.log" 2>&1 \
  || { tail -30 "$OUT/accuracy.log"; exit 1; }

"$PY" benchmarks/gpu_summary.py "$OUT" "$GSPLAT_BUILD_S" "$ACCURACY_ITERS" "$(( $(date +%s) - T0 ))" \
  | tee "$OUT/summary.md"

#!/usr/bin/env bash
# The GPU check of train_gs in one command: builds gsplat from its wheel, times the mlp and sh models per
# whole-image iteration on demo with the GPU's peak memory (the GPU budget; beside it the reflection MLP in
# float32; again compiled, [run] compile; last, where time is left, the CPU budget's smaller model), runs the
# CUDA tests, trains demo's GPU budget at 1k, 3k, 10k and 30k iterations as far as the time allows (accuracy
# against time, LPIPS where weights are found) and prints one summary table.
# Each step runs on when one before it fails; the logs say what failed.
#
# It runs on a fresh GPU machine with torch (and numpy, scipy, pytest, tqdm) but none of the I/O stack
# (open3d, pycolmap, OpenEXR), from the project's root, with two things beside the tree:
#   BUNDLE  demo's training data with its exposure estimate, written where the I/O stack is:
#             .venv/bin/python benchmarks/bench_train.py --data-root /tmp/bench --save-bundle BUNDLE
#   WHEELS  a folder holding gsplat's wheel: pip download --no-deps --only-binary=:all: -d WHEELS gsplat==1.5.3
#
#   benchmarks/gpu_check.sh BUNDLE WHEELS [OUT]
#
# OUT (default: a new temporary folder) receives each step's log, summary.md and accuracy_vs_time.svg.
# Environment:
#   TORCH_CUDA_ARCH_LIST  the GPU architecture gsplat is built for (default 9.0: H100, H200)
#   SPEED_ITERS           timed iterations per model and budget (default 200, after 30 warm-up ones)
#   ACCURACY_ITERS        the accuracy points, whole-image iterations (default "1000 3000 10000 30000")
#   DEADLINE_S            no accuracy point starts that its projected time (from the point before, or the
#                         speed step) would end past this many seconds from the start (default 480)
#   FACADE_LPIPS_DIR      a folder with lpips_vgg_v0.1_fp16.pth (LPIPS is "unavailable" without it)
#   DEVICE                cuda (default), or cpu for a dry run of the Python steps (no gsplat, tiny sizes)
set -euo pipefail

BUNDLE=${1:?usage: benchmarks/gpu_check.sh BUNDLE WHEELS [OUT]}
WHEELS=${2:?usage: benchmarks/gpu_check.sh BUNDLE WHEELS [OUT]}
OUT=${3:-$(mktemp -d -t gpu_check.XXXXXX)}
DEVICE=${DEVICE:-cuda}
SPEED_ITERS=${SPEED_ITERS:-200}
ACCURACY_ITERS=${ACCURACY_ITERS:-"1000 3000 10000 30000"}
DEADLINE_S=${DEADLINE_S:-480}
PY=${PYTHON:-python3}
export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} PYTHONUNBUFFERED=1 TQDM_DISABLE=1
mkdir -p "$OUT"
ROOT=$(cd "$(dirname "$0")/.." && pwd)
cd "$ROOT"
[ -f "$BUNDLE" ] || { echo "gpu_check: $BUNDLE: expected demo's bundle (see the header), found no file" >&2; exit 2; }
T0=$(date +%s)
step() { echo "== $(( $(date +%s) - T0 )) s: $*"; }

GSPLAT_BUILD_S=-
if [ "$DEVICE" = cuda ]; then
  "$PY" -c "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)" \
    || { echo "gpu_check: expected a CUDA device, found none (DEVICE=cpu for a dry run)" >&2; exit 2; }
  step "building gsplat for sm_${TORCH_CUDA_ARCH_LIST/./}"
  . benchmarks/gsplat_build.sh
  build_gsplat "$WHEELS" "$OUT" || exit 1
fi
export PYTHONPATH="$ROOT${PYTHONPATH:+:$PYTHONPATH}"

left() { echo $(( DEADLINE_S - ($(date +%s) - T0) )); }

BENCH=("$PY" benchmarks/bench_train.py --bundle "$BUNDLE" --device "$DEVICE" --patch-px 0 --no-write)
if [ "$DEVICE" = cpu ]; then  # a dry run: few splats, few iterations
  BENCH+=(--init-points 300 --max-gaussians 600 --mlp-width 16 --mlp-depth 2 --align-steps 2)
  SPEED_ITERS=2 ACCURACY_ITERS="2 4" WARMUP=1 PROFILE_ITERS=1
fi
WARMUP=${WARMUP:-30}

# the speed first: it is what a short lease must not miss (the GPU budget's steps then profiled: where a
# step's time goes, by operator), beside it the reflection MLP in float32 (its bfloat16 products' reference)
step "speed, gpu budget"
FACADE_BUDGET=gpu timeout 180 "${BENCH[@]}" --speed "$SPEED_ITERS" --warmup "$WARMUP" --only mlp,sh \
  --profile "${PROFILE_ITERS:-20}" > "$OUT/speed_gpu.log" 2>&1 || tail -20 "$OUT/speed_gpu.log"
step "speed, gpu budget, float32 MLP"
FACADE_BUDGET=gpu timeout 120 "${BENCH[@]}" --speed "$SPEED_ITERS" --warmup "$WARMUP" --only mlp --fp32-mlp \
  > "$OUT/speed_gpu_fp32.log" 2>&1 || tail -20 "$OUT/speed_gpu_fp32.log"

# the same steps compiled ([run] compile: torch.compile of the shading, losses and densification statistics;
# its warm-up steps wait for the compiler, at most COMPILE_S); the accuracy points train compiled where that
# was faster
step "speed, gpu budget, compiled"
FACADE_BUDGET=gpu timeout "${COMPILE_S:-240}" "${BENCH[@]}" --compile --speed "$SPEED_ITERS" --warmup "$WARMUP" \
  --only mlp,sh > "$OUT/speed_gpu_compiled.log" 2>&1 || tail -20 "$OUT/speed_gpu_compiled.log"
COMPILE=()
if "$PY" -c "import re,sys; ms=[re.search(r'^mlp: ([\d.]+) ms', open(f).read(), re.M) for f in sys.argv[1:]]; \
sys.exit(0 if all(ms) and float(ms[1].group(1)) < float(ms[0].group(1)) else 1)" \
  "$OUT/speed_gpu.log" "$OUT/speed_gpu_compiled.log" 2>/dev/null; then
  COMPILE=(--compile)
  rate_log="$OUT/speed_gpu_compiled.log"
else
  rate_log="$OUT/speed_gpu.log"
fi

step "CUDA tests"
timeout 180 "$PY" -m pytest -q -p no:cacheprovider -m gpu tests/splatting/test_gsplat.py \
  tests/training/test_trainer_gpu.py > "$OUT/tests.log" 2>&1 || true
tail -3 "$OUT/tests.log"

# accuracy against time: each point trains from scratch with its own schedule; a point starts only when its
# projected time fits before DEADLINE_S
# rate: seconds per training iteration; overhead: a point's seconds beside its training (start-up and the
# measurement: alignment, LPIPS), both from the point before (the first from the speed step, and a guess)
rate=$("$PY" -c "import re,sys; m=re.search(r'^mlp: ([\d.]+) ms', open(sys.argv[1]).read(), re.M); \
print(float(m.group(1))/1000*1.5 if m else 0.1)" "$rate_log" 2>/dev/null || echo 0.1)
overhead=${OVERHEAD_S:-90}
for n in $ACCURACY_ITERS; do
  projected=$("$PY" -c "print(int($n * $rate + $overhead))")
  if [ "$projected" -gt "$(left)" ]; then
    echo "skipped: $n iterations (projected $projected s, $(left) s left)" | tee -a "$OUT/skipped.log"
    break
  fi
  step "accuracy after $n whole-image iterations (projected $projected s)"
  P0=$(date +%s)
  FACADE_BUDGET=gpu timeout $(( $(left) + 60 )) "${BENCH[@]}" "${COMPILE[@]}" --iterations "$n" --log-every $(( n / 10 )) --only mlp --lpips \
    > "$OUT/accuracy_$n.log" 2>&1 || { tail -20 "$OUT/accuracy_$n.log"; break; }
  read -r rate overhead < <("$PY" -c "import json,sys; \
r=[json.loads(l[8:]) for l in open(sys.argv[1]) if l.startswith('result: ')][-1]; \
print(r['wall_s']/max(1, r.get('iterations_run', r['iterations']))*1.15, int(1.2*($(date +%s)-$P0-r['wall_s'])))" "$OUT/accuracy_$n.log") || break
done

# the CPU budget's smaller model on the GPU, where time is left
if [ "$(left)" -gt 45 ] || [ "$DEVICE" = cpu ]; then
  step "speed, cpu budget"
  FACADE_BUDGET=cpu timeout "$(( $(left) > 90 ? $(left) : 90 ))" "${BENCH[@]}" --speed "$SPEED_ITERS" \
    --warmup "$WARMUP" --only mlp,sh > "$OUT/speed_cpu.log" 2>&1 || tail -20 "$OUT/speed_cpu.log"
fi

"$PY" benchmarks/gpu_summary.py "$OUT" "$GSPLAT_BUILD_S" "$(( $(date +%s) - T0 ))" | tee "$OUT/summary.md"

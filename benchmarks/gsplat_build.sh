# Sourced by the GPU scripts (gpu_check.sh, gpu_ladder.sh): gsplat installed from its wheel into a folder of
# its own where the machine has none, then its CUDA code built (JIT) once, before any run needs it, so that
# runs side by side do not race for the build's lock.
#   build_gsplat WHEELS OUT   (uses $PY; exports PYTHONPATH with OUT/site; sets GSPLAT_BUILD_S; the log in
#                              OUT/gsplat_build.log; returns 1 with its tail printed where the build fails)
build_gsplat() {
  local wheels=$1 out=$2 wheel b0
  if ! "$PY" -c "import gsplat" 2>/dev/null; then
    wheel=$(ls "$wheels"/gsplat-*.whl 2>/dev/null | head -1) \
      || { echo "$(basename "$0"): $wheels: expected gsplat's wheel, found none" >&2; return 2; }
    "$PY" -m pip install -q --no-index --no-deps --no-compile --target "$out/site" "$wheel"
    export PYTHONPATH="$out/site${PYTHONPATH:+:$PYTHONPATH}"
  fi
  b0=$(date +%s)
  MAX_JOBS=${MAX_JOBS:-16} "$PY" -c "from gsplat.cuda._backend import _C; assert _C is not None" \
    > "$out/gsplat_build.log" 2>&1 || { tail -30 "$out/gsplat_build.log"; return 1; }
  GSPLAT_BUILD_S=$(( $(date +%s) - b0 ))
}

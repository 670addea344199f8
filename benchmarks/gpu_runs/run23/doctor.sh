#!/usr/bin/env bash
# Device-side: bash benchmarks/gpu_runs/run23/doctor.sh (outputs under $OUT/doctor/); from the repository root, with
# .gpu/ carried. `pig doctor` and `pig weights` where the GPU stack exists: torch's CUDA build and the H100 named,
# gsplat's JIT build in $TORCH_EXTENSIONS_DIR found and loaded (not compiled), nvcc if any, the lpips wheel's linear
# layers (in /tmp/site/lpips/weights/v0.1) against the table's SHA-256s; then the same with an empty extension folder
# (gsplat's build not found: warn with nvcc, missing without) and a check that the doctor built nothing there.
# Expected GPU wall time: ~2 min on a fresh machine (the kit's set-up 60-90 s, each doctor ~5-10 s), ~30 s warm.
set -u
mkdir -p $OUT/doctor
[ -d /tmp/site/gsplat ] && [ -d /tmp/text ] || bash .gpu/device-setup.sh >/dev/null
export PYTHONPATH=/tmp/site:$PWD TORCH_EXTENSIONS_DIR=/tmp/text PYTHONUNBUFFERED=1
D=$OUT/doctor PY=$(command -v python3)
run() {  # NAME COMMAND...: output and exit status to $D/NAME.txt, wall time beside them
  local name=$1 start=$SECONDS
  shift
  "$@" > $D/$name.txt 2>&1
  echo "exit $? wall $((SECONDS - start)) s: $*" >> $D/$name.txt
  tail -1 $D/$name.txt
}
run paper_synthetic $PY -m pig doctor --preset paper --dataset synthetic --results /tmp/doctor/results
run cpu_demo $PY -m pig doctor --results /tmp/doctor/results
run weights $PY -m pig weights
mkdir -p /tmp/doctor/noext
run paper_no_build env TORCH_EXTENSIONS_DIR=/tmp/doctor/noext $PY -m pig doctor --preset paper --dataset synthetic \
  --results /tmp/doctor/results
run paper_no_build_no_nvcc env PATH=/usr/bin:/bin CUDA_HOME=/nonexistent TORCH_EXTENSIONS_DIR=/tmp/doctor/noext \
  $PY -m pig doctor --preset paper --dataset synthetic --results /tmp/doctor/results
{ echo "left in the empty extension folder (expected nothing):"; find /tmp/doctor/noext -mindepth 1; } > $D/noext.txt
which nvcc >> $D/noext.txt 2>&1; nvidia-smi --query-gpu=name,driver_version --format=csv,noheader >> $D/noext.txt
cat $D/noext.txt

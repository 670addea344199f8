#!/usr/bin/env bash
# Device-side batch: bash benchmarks/gpu_runs/run22/batch.sh STAGE (outputs under $OUT); from the repository root,
# with .gpu/ carried. Parity of the fast path and the float32 path over 2000 iterations (held-out PSNR every 250), each
# run twice with the same seed on the same capture (24 cameras x 6 frames at 1330 x 1150, seed 0), so that the
# paths' difference can be set beside each path's difference from itself. Every run evaluates both its iterate and a
# weight average (decay 0.99 from the start). a: the capture and fast_a; b: base_a; c: fast_b; d: base_b.
set -u
bash .gpu/device-setup.sh >/dev/null
export PYTHONPATH=/tmp/site:$PWD TORCH_EXTENSIONS_DIR=/tmp/text PYTHONUNBUFFERED=1
quiet() { grep --line-buffered -v "^fit: \|LPIPS\|FID\|UserWarning\|sparse_csr\|it/s\|frame/s\|batch/s\|warn"; }
AVG=fit.average_decay=0.99,fit.average_start=0
BASE=fit.precision=float32,fit.compile=false,fit.compile_posing=false,fit.batched_render=false,fit.fused_adam=false,fit.log_every=1,fit.host_band=false,precond.cg_check_every=1,precond.cg_compile=false,precond.cg_graphs=false
run() {  # NAME OVERRIDES [extra fit_gpu arguments]
  timeout 585 python3 benchmarks/fit_gpu.py --workdir /tmp/fb --frames 6 --iterations 2000 --warmup 100 --eval-every 250 \
    --variant "$1:$2" --json $OUT/$1.json "${@:3}" 2>&1 | quiet > $OUT/$1.txt
  cp /tmp/fb/fit_$1/train_log.csv $OUT/$1_train_log.csv 2>/dev/null
  grep "generate_s\|preprocess_s\|^variant" $OUT/$1.txt; grep -A12 "^Held-out novel-view PSNR (finest LOD) per evaluation" $OUT/$1.txt
}
case $1 in
  a) run fast_a $AVG ;;
  b) run base_a $AVG,$BASE --reuse-capture ;;
  c) run fast_b $AVG --reuse-capture ;;
  d) run base_b $AVG,$BASE --reuse-capture ;;
esac

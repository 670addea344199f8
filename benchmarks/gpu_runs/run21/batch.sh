#!/usr/bin/env bash
# Device-side batch: bash benchmarks/gpu_runs/run21/batch.sh STAGE (outputs under $OUT); from the repository root,
# with .gpu/ carried. The subject (24 cameras x 10 frames at 1330 x 1150, seed 0): a generates it and fills
# the compile cache, b fits it for 240 s and evaluates every LOD, c fits the fast path twice for 2000 iterations
# (held-out PSNR every 250): the same seed and capture, to measure how far the path differs from itself.
set -u
bash .gpu/device-setup.sh >/dev/null
export PYTHONPATH=/tmp/site:$PWD TORCH_EXTENSIONS_DIR=/tmp/text PYTHONUNBUFFERED=1
quiet() { grep --line-buffered -v "^fit: \|LPIPS\|FID\|UserWarning\|sparse_csr\|it/s\|frame/s\|batch/s\|warn"; }
RATES=fit.lr_decoders=3.0e-3,precond.grid_lr=3.0e-2
case $1 in
  a)  timeout 580 python3 benchmarks/fit_gpu.py --workdir /tmp/s10 --frames 10 --iterations 22 --warmup 2 \
        --variant pig:$RATES 2>&1 | quiet > $OUT/warm.txt; grep "generate_s\|preprocess_s\|^variant" $OUT/warm.txt ;;
  b)  timeout 590 python3 benchmarks/fit_gpu.py --workdir /tmp/s10 --frames 10 --reuse-capture --iterations 70 --warmup 15 \
        --budget 240 --eval-every 500 --variant pig:$RATES --json $OUT/budget240.json 2>&1 | quiet > $OUT/budget240.txt
      cp /tmp/s10/fit_pig/train_log.csv $OUT/budget240_train_log.csv; grep "^| pig\|^variant" $OUT/budget240.txt | head ;;
  c)  timeout 590 python3 benchmarks/fit_gpu.py --workdir /tmp/s10 --frames 10 --reuse-capture --iterations 2000 --warmup 100 \
        --eval-every 250 --variant fast_a: --variant fast_b: --plot $OUT/repeat.png --json $OUT/repeat.json 2>&1 \
        | quiet > $OUT/repeat.txt; grep -A14 "^Held-out novel-view PSNR (finest LOD) per evaluation" $OUT/repeat.txt ;;
esac

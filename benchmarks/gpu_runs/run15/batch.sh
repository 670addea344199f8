#!/usr/bin/env bash
# Device-side batch for this sitting: bash .gpu/run15.sh STAGE (outputs under $OUT)
# Kept as last run (a sitting edits its stages between calls); run from the repository root, with .gpu/ carried.
set -u
bash .gpu/device-setup.sh >/dev/null
export PYTHONPATH=/tmp/site:$PWD TORCH_EXTENSIONS_DIR=/tmp/text PYTHONUNBUFFERED=1
stage=$1
common="--workdir /tmp/ab --frames 6 --iterations 70 --warmup 15 --budget 90 --eval-every 200 --finest-only"
case $stage in
  a)  timeout 540 python3 benchmarks/fit_gpu.py $common --warm-compile 40 \
        --variant grid_precond_only:precond.anchor_lambda=0 --variant anchor_precond_only:precond.grid_lambda=0 \
        --json $OUT/ablation_a.json 2>&1 | tee $OUT/ablation_a.txt | grep -v "^fit: \|LPIPS\|FID\|UserWarning\|sparse_csr" ;;
  b)  timeout 540 python3 benchmarks/fit_gpu.py $common --reuse-capture --warm-compile 20 \
        --variant anchor_precond_only:precond.grid_lambda=0 --variant fixed_anchors: --variant no_offsets: \
        --json $OUT/ablation_b.json 2>&1 | tee $OUT/ablation_b.txt | grep -v "^fit: \|LPIPS\|FID\|UserWarning\|sparse_csr" ;;
  c)  timeout 540 python3 benchmarks/fit_gpu.py $common --reuse-capture --warm-compile 20 \
        --variant no_offsets: --variant single_mlp: --variant noise_0.1: \
        --json $OUT/ablation_c.json 2>&1 | tee $OUT/ablation_c.txt | grep -v "^fit: \|LPIPS\|FID\|UserWarning\|sparse_csr" ;;
esac

#!/usr/bin/env bash
# Device-side batch: bash benchmarks/gpu_runs/run20/batch.sh STAGE (outputs under $OUT); from the repository root,
# with .gpu/ carried. Stages a, b, c run back to back on one machine: b and c reuse a's capture and the compile cache.
set -u
bash .gpu/device-setup.sh >/dev/null
export PYTHONPATH=/tmp/site:$PWD TORCH_EXTENSIONS_DIR=/tmp/text PYTHONUNBUFFERED=1
quiet() { grep --line-buffered -v "^fit: \|LPIPS\|FID\|UserWarning\|sparse_csr\|it/s\|frame/s\|batch/s\|warn"; }
LEVERS=fit.host_band=true,fit.overlap_copies=true
case $1 in
  a)  python3 benchmarks/fit_gpu.py --workdir /tmp/ab --frames 6 --capture-only > $OUT/capture.txt 2>&1 &
      timeout 250 python3 -m pytest -q -p no:cacheprovider tests/gpu > $OUT/test_gpu.txt 2>&1; tail -3 $OUT/test_gpu.txt
      wait; tail -1 $OUT/capture.txt
      timeout 280 python3 benchmarks/render_fps.py --device cuda --precision bf16 --repeats 60 --real-time-only --floor \
        > $OUT/render_fps_unfitted.txt 2>&1; grep "^|" $OUT/render_fps_unfitted.txt ;;
  b)  timeout 570 python3 benchmarks/fit_gpu.py --workdir /tmp/ab --frames 6 --reuse-capture --iterations 160 --warmup 40 \
        --warm-compile 20 --variant pig: --variant host_band:fit.host_band=true --variant overlap:fit.overlap_copies=true \
        --variant both:$LEVERS --variant pig_again: --variant both_again:$LEVERS --json $OUT/speed.json 2>&1 \
        | quiet > $OUT/speed.txt
      grep "^variant\|^| " $OUT/speed.txt | head -12 ;;
  c)  timeout 330 python3 benchmarks/fit_gpu.py --workdir /tmp/ab --frames 6 --reuse-capture --iterations 70 --warmup 15 \
        --warm-compile 20 --budget 90 --eval-every 200 --finest-only --variant pig:fit.host_band=true --json $OUT/budget.json 2>&1 \
        | quiet > $OUT/budget.txt
      grep "^| pig\|^variant" $OUT/budget.txt | head
      timeout 250 python3 benchmarks/render_fps.py --device cuda --checkpoint /tmp/ab/fit_pig/avatar.pt --precision bf16 \
        --repeats 60 --real-time-only --floor > $OUT/render_fps_fitted.txt 2>&1; grep "^|" $OUT/render_fps_fitted.txt ;;
esac

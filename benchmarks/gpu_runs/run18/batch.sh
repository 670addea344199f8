#!/usr/bin/env bash
# Device-side batch: bash .gpu/run18.sh STAGE (outputs under $OUT); run from the repository root, with .gpu/ carried.
set -u
bash .gpu/device-setup.sh >/dev/null
export PYTHONPATH=/tmp/site:$PWD TORCH_EXTENSIONS_DIR=/tmp/text PYTHONUNBUFFERED=1
quiet() { grep -v "^fit: \|LPIPS\|FID\|UserWarning\|sparse_csr\|it/s\|frame/s\|batch/s"; }
case $1 in
  a)  python3 benchmarks/fit_gpu.py --workdir /tmp/ab --frames 6 --capture-only > $OUT/capture.txt 2>&1 &
      python3 benchmarks/fit_kernels_gpu.py --only band > $OUT/band.txt 2>&1; tail -3 $OUT/band.txt
      wait; tail -1 $OUT/capture.txt
      timeout 420 python3 benchmarks/fit_gpu.py --workdir /tmp/ab --frames 6 --reuse-capture --iterations 130 --warmup 40 \
        --profile-ops 3 --op-rows 40 --variant pig: --variant posing:fit.compile_posing=true --json $OUT/speed.json 2>&1 \
        | quiet > $OUT/speed.txt
      grep "^variant\|^| pig\|^| posing" $OUT/speed.txt ;;
  b)  timeout 330 python3 benchmarks/fit_gpu.py --workdir /tmp/ab --frames 6 --reuse-capture --iterations 70 --warmup 15 \
        --budget 90 --eval-every 200 --finest-only --variant posing:fit.compile_posing=true --json $OUT/budget.json 2>&1 \
        | quiet > $OUT/budget.txt
      grep "^| posing\|^variant" $OUT/budget.txt | head
      timeout 240 python3 benchmarks/render_fps.py --device cuda --checkpoint /tmp/ab/fit_posing/avatar.pt --precision bf16 \
        --repeats 60 --real-time-only > $OUT/render_fps_fitted.txt 2>&1; tail -6 $OUT/render_fps_fitted.txt ;;
  c)  timeout 240 python3 benchmarks/render_fps.py --device cuda --precision bf16 --repeats 60 --real-time-only \
        > $OUT/render_fps_unfitted.txt 2>&1; tail -6 $OUT/render_fps_unfitted.txt
      timeout 150 python3 -m pytest -q -p no:cacheprovider tests/gpu/test_frame_graph.py 2>&1 | tail -2 ;;
esac

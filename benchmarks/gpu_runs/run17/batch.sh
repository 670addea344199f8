#!/usr/bin/env bash
# Device-side batch: bash .gpu/run17.sh STAGE (outputs under $OUT); run from the repository root, with .gpu/ carried.
set -u
bash .gpu/device-setup.sh >/dev/null
export PYTHONPATH=/tmp/site:$PWD TORCH_EXTENSIONS_DIR=/tmp/text PYTHONUNBUFFERED=1
quiet() { grep -v "^fit: \|LPIPS\|FID\|UserWarning\|sparse_csr\|it/s\|frame/s\|batch/s"; }
case $1 in
  a)  python3 benchmarks/fit_gpu.py --workdir /tmp/ab --frames 6 --capture-only > $OUT/capture.txt 2>&1 &
      timeout 220 python3 benchmarks/render_fps.py --device cuda --precision bf16 --repeats 30 --real-time-only \
        --profile-frame 20 --op-rows 12 > $OUT/render_fps_unfitted.txt 2>&1
      grep -A6 "Real-time path\|^| LOD" $OUT/render_fps_unfitted.txt | head -20; grep "kernels and" $OUT/render_fps_unfitted.txt
      timeout 250 python3 -m pytest -q -p no:cacheprovider tests/gpu > $OUT/test_gpu.txt 2>&1; tail -3 $OUT/test_gpu.txt
      wait; tail -2 $OUT/capture.txt ;;
  b)  timeout 480 python3 benchmarks/fit_gpu.py --workdir /tmp/ab --frames 6 --reuse-capture --iterations 70 --warmup 15 \
        --profile-phases 6 --profile-ops 3 --op-rows 60 --variant pig: --json $OUT/profile.json 2>&1 | quiet > $OUT/profile.txt
      grep -B2 -A40 "^| variant" $OUT/profile.txt | head -80 ;;
  c)  timeout 330 python3 benchmarks/fit_gpu.py --workdir /tmp/ab --frames 6 --reuse-capture --iterations 70 --warmup 15 \
        --budget 90 --eval-every 200 --finest-only --variant pig: --json $OUT/budget.json 2>&1 | quiet > $OUT/budget.txt
      tail -5 $OUT/budget.txt
      timeout 240 python3 benchmarks/render_fps.py --device cuda --checkpoint /tmp/ab/fit_pig/avatar.pt --precision bf16 \
        --repeats 30 --real-time-only > $OUT/render_fps_fitted.txt 2>&1; tail -12 $OUT/render_fps_fitted.txt ;;
esac

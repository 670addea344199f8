#!/usr/bin/env bash
# Device-side batch: bash .gpu/run16.sh STAGE (outputs under $OUT)
# Kept as last run (a sitting edits its stages between calls); run from the repository root, with .gpu/ carried.
set -u
bash .gpu/device-setup.sh >/dev/null
export PYTHONPATH=/tmp/site:$PWD TORCH_EXTENSIONS_DIR=/tmp/text PYTHONUNBUFFERED=1
common="--workdir /tmp/ab --frames 6 --iterations 70 --warmup 15 --budget 90 --eval-every 200 --finest-only --reuse-capture"
quiet() { grep -v "^fit: \|LPIPS\|FID\|UserWarning\|sparse_csr\|it/s\|frame/s\|batch/s"; }
case $1 in
  d)  python3 benchmarks/fit_gpu.py --workdir /tmp/ab --frames 6 --capture-only > $OUT/capture.txt 2>&1 &
      timeout 330 python3 benchmarks/render_fps.py --device cuda --precision bf16 --repeats 30 --profile-frame 20 \
        --op-rows 25 > $OUT/render_fps.txt 2>&1
      timeout 150 python3 -m pytest -q -p no:cacheprovider tests/gpu/test_frame_graph.py > $OUT/test_frame_graph.txt 2>&1
      wait; tail -3 $OUT/test_frame_graph.txt; cat $OUT/capture.txt | tail -2 ;;
  e)  timeout 580 python3 benchmarks/fit_gpu.py $common --warm-compile 40 \
        --variant grid_delay_500:precond.grid_delay=500 --variant pig: \
        --json $OUT/ablation_e.json 2>&1 | tee $OUT/ablation_e.txt | quiet ;;
  f)  timeout 420 python3 benchmarks/fit_gpu.py $common --warm-compile 20 \
        --variant noise_0.1: --variant template_bound: \
        --json $OUT/ablation_f.json 2>&1 | tee $OUT/ablation_f.txt | quiet ;;
esac
case $1 in
  g)  timeout 200 python3 benchmarks/render_fps.py --device cuda --precision bf16 --repeats 30 --real-time-only \
        --profile-frame 20 --op-rows 12 > $OUT/render_fps_g.txt 2>&1
      grep -A6 "Real-time path" $OUT/render_fps_g.txt; grep "kernels and" $OUT/render_fps_g.txt
      timeout 120 python3 -m pytest -q -p no:cacheprovider tests/gpu/test_frame_graph.py 2>&1 | tail -2 ;;
esac

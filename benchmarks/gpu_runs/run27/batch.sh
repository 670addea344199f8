#!/usr/bin/env bash
# Equal-time study (issue 38), hold 2 of a 2-GPU machine: seed 0, `pig` against `no_precond` at 900 training seconds
# (wall time less compilation, held-out evaluations and checkpoint writes: pig.avatar.training_clock), started
# together, each alone on its GPU; then novel view and novel pose at the finest LOD with the ground-truth metrics.
# From the repository root with .gpu/ carried; outputs under $OUT.
#   a: set-up, the subject (24 cameras x 10 frames at 1330 x 1150, seed 0; one generating process per core), then
#      both fits started detached from a copy under /tmp
#   w: wait up to 570 s (or until both fits wrote their JSON), print progress
#   c: collect tables, logs and JSON
#   t: issue 42 on the same machine: the 2-GPU NCCL tests
#   s N: issue 42: the `paper` step with the LPIPS term on N GPUs (benchmarks/fit_multi_gpu.py), this subject
set -u
RES=/tmp/run27
SRC=/tmp/run27_src
RATES=fit.lr_decoders=3.0e-3,precond.grid_lr=3.0e-2,fit.weight_lpips=0
BUDGET=900
NAMES="pig no_precond"
progress() {
  date +%T; nvidia-smi --query-gpu=index,utilization.gpu,memory.used --format=csv,noheader
  for name in $NAMES; do echo "== $name"; tr '\r' '\n' < $RES/$name.txt | grep -v "^\s*$\|Warning\|warn(" | tail -2; done
}
case $1 in
  a)  bash .gpu/device-setup.sh || exit 1
      nvidia-smi --query-gpu=index,name,memory.total --format=csv
      rm -rf $SRC $RES; mkdir -p $RES; cp -r . $SRC; cd $SRC
      export PYTHONPATH=/tmp/site:$SRC TORCH_EXTENSIONS_DIR=/tmp/text PYTHONUNBUFFERED=1
      ( time python3 benchmarks/fit_gpu.py --workdir /tmp/s0 --seed 0 --frames 10 --workers $(nproc) --capture-only ) \
        > $RES/capture.txt 2>&1
      tail -4 $RES/capture.txt
      gpu=0
      for name in $NAMES; do
        CUDA_VISIBLE_DEVICES=$gpu setsid nohup python3 benchmarks/fit_gpu.py --workdir /tmp/s0 --seed 0 --frames 10 \
          --reuse-capture --iterations 300 --warmup 200 --budget $BUDGET --eval-every 1000 --finest-only \
          --variant $name:$RATES --json $RES/$name.json > $RES/$name.txt 2>&1 < /dev/null &
        echo "started $name on GPU $gpu at $(date +%T)"; gpu=$((gpu + 1))
      done ;;
  w)  for i in $(seq 114); do
        done_all=1; for name in $NAMES; do [ -s $RES/$name.json ] || done_all=0; done
        [ $done_all = 1 ] && break
        sleep 5
      done
      progress ;;
  c)  for name in $NAMES; do
        tr '\r' '\n' < $RES/$name.txt | grep -v "%|\|UserWarning\|warn(" > $OUT/$name.txt
        cp $RES/$name.json $OUT/ 2>/dev/null
        cp /tmp/s0/fit_$name/train_log.csv $OUT/${name}_train_log.csv 2>/dev/null
        grep "^variant\|^| $name\|left out" $OUT/$name.txt
      done
      cp $RES/capture.txt $OUT/ ;;
  t)  cd $SRC; export PYTHONPATH=/tmp/site:$SRC TORCH_EXTENSIONS_DIR=/tmp/text PYTHONUNBUFFERED=1
      ( time python3 -m pytest -q -p no:cacheprovider tests/gpu/test_fit_parallel_gpu.py ) > $OUT/parallel_tests.txt 2>&1
      tail -5 $OUT/parallel_tests.txt ;;
  s)  cd $SRC; export PYTHONPATH=/tmp/site:$SRC TORCH_EXTENSIONS_DIR=/tmp/text PYTHONUNBUFFERED=1
      mkdir -p /tmp/pig_multi_gpu_bench/data; [ -d /tmp/pig_multi_gpu_bench/data/capture ] || cp -r /tmp/s0/capture /tmp/pig_multi_gpu_bench/data/
      ( time python3 benchmarks/fit_multi_gpu.py --gpus $2 --iterations 120 --warmup 40 --profile-phases 10 ) \
        > $OUT/multi_gpu_$2.txt 2>&1
      tail -25 $OUT/multi_gpu_$2.txt ;;
esac

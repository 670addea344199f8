#!/usr/bin/env bash
# Equal-time study (issue 38), hold 1 of a 2-GPU machine: seed 0, `pig` against `no_precond`, started together,
# each alone on its GPU, 600 training seconds each (wall time less compilation, held-out evaluations and checkpoint
# writes: pig.avatar.training_clock), then novel view and novel pose at the finest LOD with the ground-truth metrics.
# From the repository root with .gpu/ carried; outputs under $OUT.
#   a: set-up, the subject (24 cameras x 10 frames at 1330 x 1150, seed 0), then both fits started detached
#   b: progress so far
#   c: wait for both fits (up to 570 s), then collect their tables, logs and JSON
set -u
RES=/tmp/run25
SRC=/tmp/run25_src
RATES=fit.lr_decoders=3.0e-3,precond.grid_lr=3.0e-2,fit.weight_lpips=0
BUDGET=600
case $1 in
  a)  bash .gpu/device-setup.sh || exit 1
      nvidia-smi --query-gpu=index,name,memory.total --format=csv
      rm -rf $SRC $RES; mkdir -p $RES; cp -r . $SRC; cd $SRC
      export PYTHONPATH=/tmp/site:$SRC TORCH_EXTENSIONS_DIR=/tmp/text PYTHONUNBUFFERED=1
      ( time python3 benchmarks/fit_gpu.py --workdir /tmp/s0 --seed 0 --frames 10 --capture-only ) > $RES/capture.txt 2>&1
      tail -4 $RES/capture.txt
      for pair in 0:pig 1:no_precond; do
        gpu=${pair%%:*}; name=${pair#*:}
        CUDA_VISIBLE_DEVICES=$gpu setsid nohup python3 benchmarks/fit_gpu.py --workdir /tmp/s0 --seed 0 --frames 10 \
          --reuse-capture --iterations 300 --warmup 200 --budget $BUDGET --eval-every 1000 --finest-only \
          --variant $name:$RATES --json $RES/$name.json > $RES/$name.txt 2>&1 < /dev/null &
        echo "started $name on GPU $gpu at $(date +%T)"
      done ;;
  b)  date +%T; nvidia-smi --query-gpu=index,utilization.gpu,memory.used --format=csv
      for f in $RES/pig.txt $RES/no_precond.txt; do echo "== $f"; tr '\r' '\n' < $f | grep -v "^\s*$" | tail -3; done ;;
  c)  for i in $(seq 114); do
        [ -s $RES/pig.json ] && [ -s $RES/no_precond.json ] && break
        sleep 5
      done
      date +%T
      for name in pig no_precond; do
        tr '\r' '\n' < $RES/$name.txt | grep -v "%|\|UserWarning\|warn(" > $OUT/$name.txt
        cp $RES/$name.json $OUT/ 2>/dev/null
        cp /tmp/s0/fit_$name/train_log.csv $OUT/${name}_train_log.csv 2>/dev/null
        grep "^variant\|^| $name\|left out" $OUT/$name.txt
      done
      cp $RES/capture.txt $OUT/ ;;
esac

#!/usr/bin/env bash
# Device-side batch: bash benchmarks/gpu_runs/run22/batch.sh STAGE [X Y] (outputs under $OUT); from the repository
# root, with .gpu/ carried. Parity of the fast path (the `paper` profile) and the float32 path (every speed lever off)
# over 2000 iterations, held-out PSNR every 250, each path run twice with the same seed on the same capture (24
# cameras x 6 frames at 1330 x 1150, seed 0), so that the paths' difference can be set beside each path's difference
# from itself (X Y: the runs' suffixes, a b by default; c d for a second pair). Every run evaluates both its iterate
# and a weight average (decay 0.99 from the start).
# Run one after another, the four fits take ~28 minutes, the most a machine is held; so they run side by side on the
# one GPU (peaks ~47 GiB together: two float32 fits and one fast fit at a time), in their own sessions (setsid), which
# outlive a device call: stage a generates the capture and starts them, stage w waits for them (call it again at once
# until it prints "all done": a machine left idle goes back, and the fits with it); each stage copies what exists so
# far to $OUT. Their ms/it mean nothing (they share the GPU); the held-out PSNRs are what counts.
set -u
W=/tmp/fb X=${2:-a} Y=${3:-b}
RUNS="base_$X base_$Y fast_$X fast_$Y"
# The kit's install took 60-90 s of a 600 s call (run22); a warm machine has it from the call before.
[ -d /tmp/site/gsplat ] && [ -d /tmp/text ] || bash .gpu/device-setup.sh >/dev/null
export PYTHONPATH=/tmp/site:$PWD TORCH_EXTENSIONS_DIR=/tmp/text PYTHONUNBUFFERED=1
AVG=fit.average_decay=0.99,fit.average_start=0
BASE=fit.precision=float32,fit.compile=false,fit.compile_posing=false,fit.batched_render=false,fit.fused_adam=false,fit.log_every=1,fit.host_band=false,precond.cg_check_every=1,precond.cg_compile=false,precond.cg_graphs=false
fit() {  # NAME OVERRIDES
  python3 benchmarks/fit_gpu.py --workdir $W --frames 6 --reuse-capture --iterations 2000 --warmup 100 \
    --eval-every 250 --variant "$1:$2" --json $W/out/$1.json > $W/out/$1.txt 2>&1
}
collect() {
  for n in $RUNS; do
    [ -e $W/out/$n.json ] && cp $W/out/$n.json $OUT/
    [ -e $W/fit_$n/train_log.csv ] && cp $W/fit_$n/train_log.csv $OUT/${n}_train_log.csv
    [ -e $W/out/$n.txt ] && echo "$n: $(grep -c . $W/fit_$n/train_log.csv 2>/dev/null) log rows; $(grep '^variant' $W/out/$n.txt)"
  done
  nvidia-smi --query-gpu=memory.used,utilization.gpu --format=csv,noheader
}
wait_all() {  # SECONDS
  local end=$((SECONDS + $1))
  done_runs() { for n in $RUNS; do [ -e $W/out/$n.json ] && echo $n; done | wc -l; }
  while [ $SECONDS -lt $end ] && [ "$(done_runs)" -lt 4 ]; do sleep 10; done
  collect
  [ "$(done_runs)" -eq 4 ] && echo "all done"
}
case $1 in
  a) python3 benchmarks/fit_gpu.py --workdir $W --frames 6 --capture-only 2>&1 | tail -2
     mkdir -p $W/out
     export -f fit; export W AVG BASE
     setsid bash -c "fit base_$X $AVG,$BASE" < /dev/null &
     setsid bash -c "fit base_$Y $AVG,$BASE" < /dev/null &
     setsid bash -c "fit fast_$X $AVG && fit fast_$Y $AVG" < /dev/null &  # the second reuses the first's compiled code
     sleep 5; wait_all 280 ;;  # set-up 60-90 s and capture 120-175 s (run22) of the call's 600
  w) wait_all 520 ;;
esac

#!/usr/bin/env bash
# Device-side: bash benchmarks/gpu_runs/run39/eval_rate.sh a|p|w [FRACTION] [ITERATIONS] (outputs under
# $OUT/eval_rate/), from the repository root with .gpu/ carried; stage a also needs the code before issue 39 in
# .old39/ (made here by `mkdir -p .old39 && git archive 6891c5e pig | tar -x -C .old39`, an untracked folder the
# run carries). benchmarks/eval_scale.py on THuman4's protocol, 24 cameras at 1330 x 1150, every frame generated at
# 1/5 of the size and upscaled (--upscale 5: no two ground-truth frames share pixels), paper preset, LPIPS-VGG and
# FID with stand-in weights, PNG chunks, 14 decode/encode threads, batches of 16:
#   a: FRACTION (default 0.1) of the 2000 + 500 frames (5,600 view scores at 4 LODs), the old code with one
#      evaluate process per LOD, then this code with one per split and the breakdown of an evaluate second.
#   p: the whole protocol (FRACTION 1: 56,000 view scores) with this code, after an ITERATIONS-long fit (default
#      3000; the fit's last line gives its held-out PSNR, which must reach 30 dB), its disk bytes and memory; EXTRA:
#      more eval_scale.py arguments (e.g. "--lpips-precision float16 --channels-last" once item 1 has shown them within
#      issue 39's parity bounds).
# Each runs in its own session (setsid) and waits up to 480 s (the set-up before it: the call stays under the
# tool's 600 s, which run42's first call passed at 540); stage w waits again (call it until it prints "done").
set -u
W=/tmp/evrate F=${2:-0.1} I=${3:-3000} D=$OUT/eval_rate
[ -d /tmp/site/gsplat ] && [ -d /tmp/text ] || bash .gpu/device-setup.sh >/dev/null
# Run from a copy: a later call re-sends the working tree and replaces its folders under a running job (run26).
SRC=/tmp/run39_src
if [ "$1" != w ]; then rm -rf $SRC && cp -r . $SRC; fi
cd $SRC
. benchmarks/gpu_runs/kit_env.sh $SRC  # set-up's build environment: no second build of gsplat's extension
mkdir -p $D $W
COMMON="--workdir $W --upscale 5 --workers 16 --codec png --encode-workers 14 --batch-size 16"
wait_run() {  # SECONDS
  local end=$((SECONDS + $1))
  while [ $SECONDS -lt $end ] && [ ! -e $W/done ]; do sleep 10; done
  cp $W/*.txt $W/*.json $D/ 2>/dev/null
  tail -c 5000 "$(ls -t $W/*.txt | head -1)"
  nvidia-smi --query-gpu=memory.used,utilization.gpu --format=csv,noheader
  df -h /tmp | tail -1
  [ -e $W/done ] && echo "done"
}
case $1 in
  a) rm -f $W/done
     setsid bash -c "python3 benchmarks/eval_scale.py $COMMON --fraction $F --iterations 300 --code .old39 --tag old \
       --evaluate-per-lod --json $W/before.json > $W/before.txt 2>&1; \
       python3 benchmarks/eval_scale.py $COMMON --fraction $F --iterations 300 --tag new --breakdown-batches 8 \
       --json $W/after.json > $W/after.txt 2>&1; touch $W/done" \
       < /dev/null > /dev/null 2>&1 &
     sleep 5; wait_run 480 ;;
  p) rm -f $W/done
     setsid bash -c "python3 benchmarks/eval_scale.py $COMMON --fraction $F --iterations $I --tag full \
       --breakdown-batches 8 ${EXTRA:-} --json $W/full.json > $W/full.txt 2>&1; touch $W/done" \
       < /dev/null > /dev/null 2>&1 &
     sleep 5; wait_run 480 ;;
  w) wait_run 560 ;;
esac

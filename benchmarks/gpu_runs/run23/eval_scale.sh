#!/usr/bin/env bash
# Device-side: bash benchmarks/gpu_runs/run23/eval_scale.sh a|w [FRACTION] (outputs under $OUT/eval_scale/), from the
# repository root with .gpu/ carried. The THuman4 protocol's render and evaluate (benchmarks/eval_scale.py): 24 cameras
# at 1330 x 1150, FRACTION (default 0.1) of its 2000 + 500 frames, so 5,600 of the 56,000 views at every LOD; paper
# preset, a 200-iteration fit, LPIPS-VGG and FID with stand-in random weights, PNG chunks encoded on 14 threads; then
# both codecs timed on 100 rendered views. Expected ~6-8 min at 0.1 (capture ~2, fit ~1-2, render ~1, evaluate ~3),
# so it runs in its own session (setsid): stage a starts it and waits up to 540 s, stage w waits again (call it at once
# until it prints "done"). The whole protocol (FRACTION 1) would take ~25-35 min: more than the batch can give.
set -u
W=/tmp/evscale F=${2:-0.1} D=$OUT/eval_scale
[ -d /tmp/site/gsplat ] && [ -d /tmp/text ] || bash .gpu/device-setup.sh >/dev/null
export PYTHONPATH=/tmp/site:$PWD TORCH_EXTENSIONS_DIR=/tmp/text PYTHONUNBUFFERED=1
mkdir -p $D $W
wait_run() {  # SECONDS
  local end=$((SECONDS + $1))
  while [ $SECONDS -lt $end ] && [ ! -e $W/done ]; do sleep 10; done
  cp $W/eval_scale.txt $D/ 2>/dev/null; cp $W/eval_scale.json $D/ 2>/dev/null
  tail -c 4000 $W/eval_scale.txt
  nvidia-smi --query-gpu=memory.used,utilization.gpu --format=csv,noheader
  [ -e $W/done ] && echo "done"
}
case $1 in
  a) rm -f $W/done
     setsid bash -c "python3 benchmarks/eval_scale.py --workdir $W --fraction $F --iterations 200 --workers 16 \
       --codec png --encode-workers 14 --batch-size 16 --codec-sample 100 --json $W/eval_scale.json \
       > $W/eval_scale.txt 2>&1; touch $W/done" < /dev/null &
     sleep 5; wait_run 540 ;;
  w) wait_run 560 ;;
esac

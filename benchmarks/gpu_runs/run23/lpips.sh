#!/usr/bin/env bash
# Device-side: bash benchmarks/gpu_runs/run23/lpips.sh STAGE (outputs under $OUT/lpips/); from the repository root,
# with .gpu/ carried. The LPIPS term of Eq. 15 inside the `paper` fit loop (100k anchors, 4 views x 5 timesteps of
# 1330 x 1150, random VGG weights: fit.lpips_weights=random), one process, 20 warm-up + 200 timed iterations per
# variant, each lever added to the one before: the term off; `full` (today's term); `mmlphuman` with MMLPHuman's
# literal crop (a view at a time, host syncs) and the float32 head; + the bf16 head; + the fixed-shape crop; + the
# network compiled (= the `paper` preset). Peak GPU memory and graphs compiled (warm-up / timed window) per variant.
# Capture: 8 cameras x 5 frames, generated there (~40 s). Stage a sets up, generates, starts the fit process in its
# own session and waits up to 420 s; stage w waits for it up to 540 s more (call it at once after a, until it
# prints "all done"). Expected GPU wall time: ~9 min on a fresh machine (set-up 60-90 s, the paper preset's
# compilation ~3-4 min in the first variant, `full` ~2 min at ~0.5 s/it, the mmlphuman variants ~30 s each), ~6 min
# where the paper preset was compiled before on the same machine. SKIP_FULL=1 leaves out `full` (~2 min; run10
# measured it at 574 ms/it).
set -u
W=/tmp/lpips23
mkdir -p $OUT/lpips
[ -d /tmp/site/gsplat ] && [ -d /tmp/text ] || bash .gpu/device-setup.sh >/dev/null
export PYTHONPATH=/tmp/site:$PWD TORCH_EXTENSIONS_DIR=/tmp/text PYTHONUNBUFFERED=1
R=fit.lpips_weights=random
OLD=fit.lpips_bf16_head=false,fit.lpips_compile=false
VARIANTS=(
  "off:fit.weight_lpips=0"
  "full:$R,fit.lpips_form=full,$OLD"
  "mmlphuman:$R,fit.lpips_crop_sliced=true,$OLD"
  "bf16_head:$R,fit.lpips_crop_sliced=true,fit.lpips_compile=false"
  "fixed_shapes:$R,fit.lpips_compile=false"
  "compiled:$R"
)
collect() {
  cp $W/lpips.txt $W/lpips.json $OUT/lpips/ 2>/dev/null
  grep '^variant' $W/lpips.txt
  nvidia-smi --query-gpu=memory.used,utilization.gpu --format=csv,noheader
}
wait_done() {  # SECONDS
  local end=$((SECONDS + $1))
  while [ $SECONDS -lt $end ] && [ ! -e $W/lpips.json ]; do sleep 10; done
  collect
  [ -e $W/lpips.json ] && echo "all done"
}
case $1 in
  a) python3 benchmarks/fit_gpu.py --workdir $W --cameras 8 --frames 5 --capture-only 2>&1 | tail -1
     args=(); for v in "${VARIANTS[@]}"; do [ "${SKIP_FULL:-0}" = 1 ] && [ "${v%%:*}" = full ] || args+=(--variant "$v"); done
     setsid python3 benchmarks/fit_gpu.py --workdir $W --cameras 8 --frames 5 --reuse-capture --iterations 220 \
       --warmup 20 --json $W/lpips.json "${args[@]}" > $W/lpips.txt 2>&1 < /dev/null &
     wait_done 420 ;;
  w) wait_done 540 ;;
esac

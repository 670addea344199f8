#!/usr/bin/env bash
# One hold of the equal-time study (issue 38; benchmarks/gpu_runs/equal_time.yaml lists the holds still to run):
# one fit per GPU, started together, each `benchmarks/fit_gpu.py --budget` of the same training seconds
# (pig.avatar.training_clock: compilation, held-out evaluations and checkpoint writes left out), then its novel view
# and novel pose at the finest LOD with the ground-truth metrics.
# From the repository root with .gpu/ carried, and .gpu_cache/ where an earlier hold brought back torch.compile's
# artifacts (VARIANT.bin.gz: fit_gpu.py --compile-cache; most of the 3-4 minutes of compilation skipped); raw results
# under $OUT (results.tar: every fit's output, train log and JSON; VARIANT.bin.gz: the artifacts for .gpu_cache/),
# then committed under benchmarks/gpu_runs/runNN.
#   a SEED BUDGET_S VARIANT...   set-up, the subject (24 cameras x 10 frames at 1330 x 1150; the preset's 16
#                                generating processes: 32 on a 32-core host took 334 s against 176 s), one fit per
#                                GPU started detached from a copy under /tmp; a VARIANT may carry overrides after a
#                                colon (fit_gpu.py --variant), e.g. pig:fit.average_decay=0.99 ; each fit works in
#                                /tmp/s$GPU (a copy of the capture) and its files are NAME_GPU.*
#   w                            wait up to 570 s, or until every fit wrote its JSON; copy what exists to $OUT
#   w SECONDS                    the same, at most SECONDS (the hold's last device seconds: nothing is lost)
# The copy to $OUT runs every few seconds, so a call cut short by the end of the device time still brings back
# the progress lines, each train log once its fit has written it, and each JSON once its evaluation ended.
set -u
RES=/tmp/equal_time
SRC=/tmp/equal_time_src
RATES=fit.lr_decoders=3.0e-3,precond.grid_lr=3.0e-2,fit.weight_lpips=0
collect() {  # one tar of the small files (a call brings back at most 8 files), the artifacts beside it
  mkdir -p $RES/out
  while read -r run gpu name; do
    tr '\r' '\n' < $RES/$run.txt | grep -v "%|\|UserWarning\|warn(\|^\s*$" > $RES/out/$run.txt
    [ -s $RES/$run.json ] && cp $RES/$run.json $RES/out/
    [ -s /tmp/s$gpu/fit_$name/train_log.csv ] && cp /tmp/s$gpu/fit_$name/train_log.csv $RES/out/${run}_train_log.csv
    [ -s /tmp/cc/$run.bin.gz ] && cp /tmp/cc/$run.bin.gz $OUT/$name.bin.gz
  done < $RES/names
  cp $RES/capture.txt $RES/names $RES/out/ 2>/dev/null
  tar -cf $OUT/results.tar.partial -C $RES/out . && mv $OUT/results.tar.partial $OUT/results.tar
}
finished() {
  while read -r run _; do [ -s $RES/$run.json ] || return 1; done < $RES/names
}
case $1 in
  a)  seed=$2; budget=$3; shift 3
      bash .gpu/device-setup.sh || exit 1
      nvidia-smi --query-gpu=index,name,memory.total --format=csv
      gpus=$(nvidia-smi -L | wc -l)
      [ $# -le $gpus ] || { echo "$# fits for $gpus GPUs"; exit 1; }
      rm -rf $SRC $RES /tmp/s /tmp/s[0-9]* /tmp/cc; mkdir -p $RES /tmp/cc; cp -r . $SRC; cd $SRC
      export PYTHONPATH=/tmp/site:$SRC TORCH_EXTENSIONS_DIR=/tmp/text PYTHONUNBUFFERED=1
      ( time python3 benchmarks/fit_gpu.py --workdir /tmp/s --seed $seed --frames 10 --capture-only ) > $RES/capture.txt 2>&1
      tail -4 $RES/capture.txt
      gpu=0; : > $RES/names
      for spec in "$@"; do
        name=${spec%%:*}; extra=${spec#$name}; extra=${extra#:}; run=${name}_$gpu
        echo "$run $gpu $name" >> $RES/names
        mkdir -p /tmp/s$gpu; cp -r /tmp/s/capture /tmp/s$gpu/
        [ -f .gpu_cache/$name.bin.gz ] && cp .gpu_cache/$name.bin.gz /tmp/cc/$run.bin.gz
        CUDA_VISIBLE_DEVICES=$gpu setsid nohup python3 benchmarks/fit_gpu.py --workdir /tmp/s$gpu --seed $seed \
          --frames 10 --reuse-capture --iterations 300 --warmup 200 --budget $budget --eval-every 1000 --finest-only \
          --variant "$name:$RATES${extra:+,$extra}" --compile-cache /tmp/cc/$run.bin.gz --json $RES/$run.json \
          > $RES/$run.txt 2>&1 < /dev/null &
        echo "started $run ($name${extra:+ with $extra}) on GPU $gpu at $(date +%T)"; gpu=$((gpu + 1))
      done ;;
  w)  end=$((SECONDS + ${2:-570}))
      while [ $SECONDS -lt $end ] && ! finished; do collect; sleep 4; done
      collect; date +%T; nvidia-smi --query-gpu=index,utilization.gpu,memory.used --format=csv,noheader
      ls -la $OUT
      while read -r run _; do echo "== $run"; grep "^fit /tmp" $RES/out/$run.txt | tail -1
        grep "^\[evaluate\] novel_\w* lod[0-9]*: PSNR [0-9]" $RES/out/$run.txt; done < $RES/names ;;
esac

#!/usr/bin/env bash
# One hold of the equal-time study (issue 38; benchmarks/gpu_runs/equal_time.yaml lists the holds still to run):
# rounds of fits, one fit per GPU, started together, each `benchmarks/fit_gpu.py --budget` of the same training
# seconds (pig.avatar.training_clock: compilation, held-out evaluations and checkpoint writes left out), then its novel
# view and novel pose at the finest LOD with the ground-truth metrics. From the repository root with .gpu/ carried;
# raw results under $OUT (results.tar: every fit's output, train log and JSON), then committed under
# benchmarks/gpu_runs/runNN.
#   a SEED BUDGET_S VARIANT...   set-up, the subject (24 cameras x 10 frames at 1330 x 1150, the preset's 16
#                                processes: 19.3 s on a 64-CPU 4-GPU host, run33; capture.txt's "render workers"
#                                table says where the time went), gsplat's extension loaded once (kit_env.sh: a
#                                rebuild, if the machine needs one, before the fits start), then the first round: one
#                                fit per GPU, started detached from a copy under /tmp. A VARIANT may carry
#                                overrides after a colon (fit_gpu.py --variant), e.g. pig:fit.average_decay=0.99; a
#                                fit with a weight average is evaluated twice, the average and then its last iterate
#                                (fit_gpu.py --evaluate-iterate: ~100 s more at the end of the round)
#   n BUDGET_S VARIANT...        the next round on the same subject, once the last round has ended (its fits start
#                                together again; torch.compile's artifacts of an earlier round's variant are loaded:
#                                fit_gpu.py --compile-cache, kept on the machine, since at 23-27 MB a variant they
#                                exceed what a call brings back and, beside .gpu's 38 MB, what it carries)
#   w [SECONDS]                  wait up to SECONDS (570), or until the round's fits wrote their JSON; copy to $OUT
# Fit NAME of round R on GPU G is run NAME_rRgG (round 1: NAME_G); it works in /tmp/w_RUN (a copy of the capture).
# The copy to $OUT runs every few seconds, so a call cut short by the end of the device time still brings back the
# progress lines, each train log once its fit has written it, and each JSON once its evaluation ended.
set -u
RES=/tmp/equal_time
SRC=/tmp/equal_time_src
RATES=fit.lr_decoders=3.0e-3,precond.grid_lr=3.0e-2,fit.weight_lpips=0
collect() {  # one tar of the small files: a call brings back at most 8 files
  mkdir -p $RES/out
  cat $RES/names.* | while read -r run gpu name; do
    tr '\r' '\n' < $RES/$run.txt | grep -v "%|\|UserWarning\|warn(\|^\s*$" > $RES/out/$run.txt
    [ -s $RES/$run.json ] && cp $RES/$run.json $RES/out/
    [ -s /tmp/w_$run/fit_$name/train_log.csv ] && cp /tmp/w_$run/fit_$name/train_log.csv $RES/out/${run}_train_log.csv
  done
  cp $RES/capture.txt $RES/out/ 2>/dev/null
  cat $RES/names.* > $RES/out/names
  tar -cf $OUT/results.tar.partial -C $RES/out . && mv $OUT/results.tar.partial $OUT/results.tar
}
finished() {  # every fit of the last round wrote its JSON
  while read -r run _; do [ -s $RES/$run.json ] || return 1; done < "$(ls $RES/names.* | sort -V | tail -1)"
}
start_round() {  # BUDGET_S VARIANT...: one fit per GPU
  local budget=$1 round gpu=0 spec name extra run; shift
  round=$(($(ls $RES/names.* 2>/dev/null | wc -l) + 1))
  [ $# -le "$(nvidia-smi -L | wc -l)" ] || { echo "$# fits for $(nvidia-smi -L | wc -l) GPUs"; exit 1; }
  : > $RES/names.$round
  for spec in "$@"; do
    name=${spec%%:*}; extra=${spec#$name}; extra=${extra#:}
    run=${name}_$gpu; [ $round -gt 1 ] && run=${name}_r${round}g$gpu
    echo "$run $gpu $name" >> $RES/names.$round
    mkdir -p /tmp/w_$run; cp -r /tmp/s/capture /tmp/w_$run/
    earlier=$(ls /tmp/cc/${name}_*.bin.gz 2>/dev/null | head -1)  # one file a run: two fits of a round may share a variant
    [ -n "$earlier" ] && cp "$earlier" /tmp/cc/$run.bin.gz
    CUDA_VISIBLE_DEVICES=$gpu setsid nohup python3 benchmarks/fit_gpu.py --workdir /tmp/w_$run --seed "$(cat $RES/seed)" \
      --frames 10 --reuse-capture --iterations 300 --warmup 200 --budget $budget --eval-every 1000 --finest-only --evaluate-iterate \
      --variant "$name:$RATES${extra:+,$extra}" --compile-cache /tmp/cc/$run.bin.gz --json $RES/$run.json \
      > $RES/$run.txt 2>&1 < /dev/null &
    echo "started $run ($name${extra:+ with $extra}, $budget s) on GPU $gpu at $(date +%T)"; gpu=$((gpu + 1))
  done
}
case $1 in
  a)  seed=$2; shift 2
      bash .gpu/device-setup.sh || exit 1
      nvidia-smi --query-gpu=index,name,memory.total --format=csv
      rm -rf $SRC $RES /tmp/s /tmp/w_* /tmp/cc; mkdir -p $RES /tmp/cc; echo $seed > $RES/seed
      cp -r . $SRC; cd $SRC
      . benchmarks/gpu_runs/kit_env.sh $SRC
      ( time python3 benchmarks/fit_gpu.py --workdir /tmp/s --seed $seed --frames 10 --capture-only ) > $RES/capture.txt 2>&1
      tail -4 $RES/capture.txt
      start_round "$@" ;;
  n)  shift; cd $SRC || exit 1
      . benchmarks/gpu_runs/kit_env.sh $SRC
      finished || { echo "the last round has not ended"; exit 1; }
      start_round "$@" ;;
  w)  end=$((SECONDS + ${2:-570}))
      while [ $SECONDS -lt $end ] && ! finished; do collect; sleep 4; done
      collect; date +%T; nvidia-smi --query-gpu=index,utilization.gpu,memory.used --format=csv,noheader
      ls -la $OUT
      cat $RES/names.* | while read -r run _; do echo "== $run"; grep "^fit /tmp" $RES/out/$run.txt | tail -1
        grep "^\[evaluate\] novel_\w* lod[0-9]*: PSNR [0-9]" $RES/out/$run.txt
        # A fit that ended without its JSON: say so loudly, with its error, so the next call can restart it.
        if [ ! -s $RES/$run.json ] && ! pgrep -f "json $RES/$run.json" > /dev/null; then
          echo "!! $run ENDED WITHOUT RESULTS: $(grep -E '^[A-Za-z.]*(Error|Exception)' $RES/out/$run.txt | tail -1)"; fi; done ;;
esac

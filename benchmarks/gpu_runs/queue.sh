#!/usr/bin/env bash
# Commands one after another on the GPU machine, detached from the call (setsid, from a copy of the tree under /tmp,
# which a later call's re-sent tree cannot replace under them), so a queue longer than one call's 10 minutes goes on
# between calls; every command's output is kept and comes back with each `w`.
#   a CMD...   set-up (from the repository root with .gpu carried), the copy, then the queue started; waits as `w`
#   w [S]      wait up to S seconds (540) or until the queue has ended; copy what exists to $OUT/queue.tar
# Each CMD runs under `bash -c` in the copy with the kit on PYTHONPATH; its output goes to NN.txt, its start, end and
# exit status to status.txt; a command may write more files under $Q (exported), which come back too. E.g. issue 42:
#   bash benchmarks/gpu_runs/queue.sh a "python3 benchmarks/fit_multi_gpu.py --gpus 1 --iterations 120 --warmup 40 \
#     --profile-phases 10" "python3 benchmarks/fit_multi_gpu.py --gpus 4 --shard-solves off on --iterations 120 ..."
set -u
Q=/tmp/queue SRC=/tmp/queue_src
collect() {
  tar -cf "$OUT/queue.tar.partial" -C $Q . && mv "$OUT/queue.tar.partial" "$OUT/queue.tar"
}
wait_queue() {  # SECONDS
  local end=$((SECONDS + $1))
  while [ $SECONDS -lt $end ] && [ ! -e $Q/ended ]; do collect; sleep 5; done
  collect
  cat $Q/status.txt
  command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=index,utilization.gpu,memory.used --format=csv,noheader
  [ -e $Q/ended ] && echo "queue ended" || tail -c 3000 "$(ls -t $Q/[0-9]*.txt | head -1)"
}
case $1 in
  a)  shift
      [ -d /tmp/site ] || bash .gpu/device-setup.sh || exit 1
      rm -rf $Q $SRC; mkdir -p $Q $SRC
      tar -c --exclude=./.gpu --exclude=./.git --exclude=./results . | tar -x -C $SRC
      n=0; for cmd in "$@"; do n=$((n + 1)); printf '%s\n' "$cmd" > "$Q/$(printf %02d $n).cmd"; done
      export Q; cd $SRC && . benchmarks/gpu_runs/kit_env.sh $SRC
      setsid bash -c '
        for file in $Q/*.cmd; do
          out=${file%.cmd}.txt
          echo "$(basename $file .cmd) start $(date +%T): $(head -c 200 $file)" >> $Q/status.txt
          bash -c "$(cat $file)" > $out 2>&1 < /dev/null
          echo "$(basename $file .cmd) end $(date +%T) rc $?" >> $Q/status.txt
        done
        touch $Q/ended' < /dev/null > /dev/null 2>&1 &
      sleep 3; cd - > /dev/null; wait_queue "${WAIT:-540}" ;;
  w)  wait_queue "${2:-540}" ;;
esac

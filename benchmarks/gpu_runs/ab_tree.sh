#!/usr/bin/env bash
# One step of benchmarks/fit_multi_gpu.py on one GPU, from an older tree and from this one side by side on GPUs 0 and
# 1 of one machine: ms/it and peak memory of the same command, so that a change between two holds is told from the
# machine's (run33: peak 33.2 against 20.1 GiB, 32.8 against 15.4 in the equal-time fits). Run through queue.sh
# after any hold script has made /tmp/s/capture, with the older tree carried as an ignored folder:
#   here:   mkdir -p .ab/OLD && git archive OLD -- pig config benchmarks ':!benchmarks/gpu_runs' pyproject.toml | tar -x -C .ab/OLD
#   device: WAIT=330 bash benchmarks/gpu_runs/queue.sh a "bash benchmarks/gpu_runs/ab_tree.sh .ab/OLD"   (carry .gpu, .ab)
# Each side's output goes to $Q/ab_old.txt and $Q/ab_new.txt (they come back with the queue's tar).
set -u
old=$(cd "$1" && pwd) new=$PWD
run() {  # TREE GPU NAME
  mkdir -p /tmp/ab_$3/data && rm -rf /tmp/ab_$3/data/capture && cp -r /tmp/s/capture /tmp/ab_$3/data/capture
  (cd "$1" && PYTHONPATH=/tmp/site:$1 CUDA_VISIBLE_DEVICES=$2 timeout 300 python3 benchmarks/fit_multi_gpu.py \
    --workdir /tmp/ab_$3 --gpus 1 --iterations 60 --warmup 40 --profile-phases 5 > "$Q/ab_$3.txt" 2>&1)
}
run "$old" 0 old & run "$new" 1 new; wait
grep -h "ms/it, peak" "$Q"/ab_old.txt "$Q"/ab_new.txt

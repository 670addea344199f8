#!/usr/bin/env bash
# One step of benchmarks/fit_multi_gpu.py on one GPU, from several trees side by side, each alone on its GPU (more
# trees than GPUs run in batches of the GPU count: run35's 2-GPU machine ran four trees two to a GPU, whose ms/it then
# mixed two processes): ms/it and peak memory of the same command, so that a change between two holds is told from
# the machine's (run33: peak 33.2 against 20.1 GiB, 32.8 against 15.4 in the equal-time fits; run34: 26bda42 20.12
# GiB, 2e5d54c 33.15 GiB on one machine). Each tree compiles into its own inductor cache (a cache an earlier run
# filled would hand one side kernels the other compiles). Run through queue.sh, with the older trees carried as ignored
# folders; the capture is the equal-time subject of seed 1 (made here unless a hold script already made /tmp/s):
#   here:   mkdir -p .ab/OLD && git archive OLD -- pig config benchmarks ':!benchmarks/gpu_runs' pyproject.toml | tar -x -C .ab/OLD
#   device: WAIT=400 bash benchmarks/gpu_runs/queue.sh a "bash benchmarks/gpu_runs/ab_tree.sh .ab/OLD ."   (carry .gpu, .ab)
# Each tree's output goes to $Q/ab_NAME.txt (NAME: the folder's name, `this` for .), which come back with the queue's tar.
set -u
[ -d /tmp/s/capture ] || python3 benchmarks/fit_gpu.py --workdir /tmp/s --seed 1 --frames 10 --capture-only > "$Q/ab_capture.txt" 2>&1 || exit 1
gpus=$(nvidia-smi -L | wc -l) index=0 names=()
for tree in "$@"; do
  path=$(cd "$tree" && pwd) name=$(basename "$path"); [ "$tree" = . ] && name=this
  names+=("$name")
  [ $index -gt 0 ] && [ $((index % gpus)) -eq 0 ] && wait
  mkdir -p /tmp/ab_$name/data && rm -rf /tmp/ab_$name/data/capture && cp -r /tmp/s/capture /tmp/ab_$name/data/capture
  (cd "$path" && PYTHONPATH=/tmp/site:$path CUDA_VISIBLE_DEVICES=$((index % gpus)) TORCHINDUCTOR_CACHE_DIR=/tmp/ic_$name \
    timeout 400 python3 benchmarks/fit_multi_gpu.py --workdir /tmp/ab_$name --gpus 1 --iterations 60 --warmup 40 \
    --profile-phases 5 > "$Q/ab_$name.txt" 2>&1) &
  index=$((index + 1))
done
wait
for name in "${names[@]}"; do
  echo "$name: $(grep -h "ms/it, peak" "$Q/ab_$name.txt")"
done

#!/usr/bin/env bash
# Issue 42: where the 4-GPU step's host time goes, Python frame by frame. py-spy samples every rank's stacks (its
# subprocesses, with threads, without pausing them) through a 4-GPU fit of 400 iterations, and
# benchmarks/host_stacks.py reads them (compilation and evaluations left out). Through queue.sh, py-spy installed
# first from .gpu/pyspy/ (here: `mkdir -p .gpu/pyspy && pip download --no-deps -d .gpu/pyspy py-spy==0.4.2`, or the
# wheel from a local wheel store), in one call with carry [".gpu"]:
#   python3 -m pip install -q --no-index --no-deps --target /tmp/pyspy .gpu/pyspy/*.whl &&
#   WAIT=420 bash benchmarks/gpu_runs/queue.sh a "bash benchmarks/gpu_runs/host_stacks.sh"
# The raw stacks ($Q/host_stacks.txt) and the tables ($Q/01.txt) come back with the queue's tar. ARGS: more
# fit_multi_gpu.py arguments (e.g. "--pin-cpus", "--compile-mode reduce-overhead").
set -eu
[ -x /tmp/pyspy/bin/py-spy ] || { echo "py-spy is not installed in /tmp/pyspy (see this script's header)"; exit 1; }
work=/tmp/mg_spy
mkdir -p $work/data
[ -d $work/data/capture ] || [ ! -d /tmp/s/capture ] || cp -r /tmp/s/capture $work/data/capture
/tmp/pyspy/bin/py-spy record --subprocesses --threads --nonblocking --format raw --rate 200 -o "$Q/host_stacks.txt" -- \
  python3 benchmarks/fit_multi_gpu.py --workdir $work --gpus 4 --shard-solves on --iterations 400 --warmup 40 ${ARGS:-}
python3 benchmarks/host_stacks.py "$Q/host_stacks.txt"

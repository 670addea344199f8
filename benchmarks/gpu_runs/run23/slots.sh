#!/usr/bin/env bash
# Device-side: bash benchmarks/gpu_runs/run23/slots.sh a|w  (outputs under $OUT/slots/), from the repository root
# with .gpu carried, after `bash benchmarks/gpu_runs/run23/wheels.sh` here (Snakemake's cp312 wheels into
# .gpu/snakemake/: the GPU machine has no Snakemake). Issue 31: the all_tables target, `paper` preset, through the
# local GPU slots on the one GPU, with the full method and the four structural ablations (5 fits: every table of
# the synthetic subject). Overrides of `paper` (written to a preset in the run's folder): synthetic 12 cameras x 10
# frames at 665 x 575 without supersampling (a quarter of the paper's pixels: its capture took 120-175 s for 6 frames
# in run22), fit.time_budget_s 30, fit.weight_lpips 0 (no VGG weights there), the compile levers off (the first
# compilation takes minutes, more than the budget). Stage a starts Snakemake in its own session (setsid, so it
# outlives the call) and waits up to $WAIT s, 420 by default (the kit's set-up may take 90 s of the call's 600); stage w waits up to
# $WAIT s, 540 by default, more (call it at once, only when a did not print "all done"). Expected: ~2 min set-up and capture, 5 fits of
# ~1 min, 10 render and 40 evaluate jobs of a few seconds each, one at a time on the one GPU: 9-12 min in all.
# Each stage copies to $OUT: Snakemake's output, the job table (benchmarks/job_timeline.py: start and end of every
# job, the device its log names), the plan (plan_tables), the tables' Markdown.
# Off the GPU machine, a trial on the CPU with two stand-in GPUs: BASE=test SYNTHETIC='{"frames": 4}'
# VARIANTS='variants=[pig,no_offsets]' PIG_GPU_DEVICES=0,1 OUT=/tmp/o W=/tmp/w bash benchmarks/gpu_runs/run23/slots.sh a
set -u
REPO=$PWD W=${W:-/tmp/w23} R=$OUT/slots
BASE=${BASE:-paper}
SYNTHETIC=${SYNTHETIC:-'{"cameras": 12, "frames": 10, "width": 665, "height": 575, "supersample": 1}'}
VARIANTS=${VARIANTS:-'variants=[pig,no_precond,fixed_anchors,no_offsets,single_mlp]'}
if [ "$BASE" = paper ]; then
  # The kit's install took 60-90 s of a 600 s call (run22); a warm machine has it from the call before.
  [ -d /tmp/site/gsplat ] && [ -d /tmp/text ] || bash .gpu/device-setup.sh >/dev/null
  [ -d /tmp/snk/snakemake ] || python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/snk \
    .gpu/snakemake/*.whl
  export PYTHONPATH=/tmp/site:/tmp/snk:$PWD TORCH_EXTENSIONS_DIR=/tmp/text PYTHONUNBUFFERED=1
else
  export PYTHONPATH=$PWD PYTHONUNBUFFERED=1
fi
if ! command -v python >/dev/null; then  # the rules call `python`
  mkdir -p /tmp/shim && ln -sf "$(command -v python3)" /tmp/shim/python && export PATH=/tmp/shim:$PATH
fi
mkdir -p "$R"
snake() { (cd "$W" && python3 -m snakemake --snakefile "$REPO/Snakefile" --scheduler greedy "$@"); }
collect() {
  cp "$W/snakemake.out" "$R/snakemake.txt"
  python3 benchmarks/job_timeline.py "$W/snakemake.out" --workdir "$W" > "$R/jobs.md"
  cp "$W"/results/tables/*.md "$R/" 2>/dev/null
  [ -e "$W/rc" ] && echo "snakemake exit $(cat "$W/rc"); all done"
  grep -c '| done |' "$R/jobs.md" | sed 's/$/ jobs done/'
}
wait_run() {  # SECONDS
  local end=$((SECONDS + $1))
  while [ $SECONDS -lt $end ] && [ ! -e "$W/rc" ]; do sleep 5; done
  collect
}
case $1 in
  a) rm -rf "$W" && mkdir -p "$W" && cp -r config "$W/"
     python3 - "$W/config/presets/run23.yaml" "$BASE" "$SYNTHETIC" <<'PY'
import json, sys
import yaml
from pig.config import load_preset
path, base, synthetic = sys.argv[1:]
preset = load_preset(base)
preset.pop("_path")
preset["synthetic"].update(json.loads(synthetic))
preset["fit"].update(time_budget_s=30.0, weight_lpips=0.0, compile=False, compile_posing=False)
preset["precond"].update(cg_compile=False)
for rule in ("fit_avatar", "render_split", "evaluate"):  # as in `paper` (for a trial on another base)
    preset["resources"].setdefault(rule, {})["gpu"] = 1
with open(path, "w") as out:
    yaml.safe_dump(preset, out, sort_keys=False)
PY
     (nvidia-smi -L || echo "no nvidia-smi") > "$R/devices.txt" 2>&1
     snake plan_tables --cores 1 --config preset=run23 "$VARIANTS" > "$R/plan.txt" 2>&1
     export -f snake; export W REPO VARIANTS
     setsid bash -c 'snake all_tables --config preset=run23 "$VARIANTS" > "$W/snakemake.out" 2>&1; echo $? > "$W/rc"' \
       < /dev/null > /dev/null 2>&1 &
     sleep 5; wait_run "${WAIT:-420}" ;;
  w) wait_run "${WAIT:-540}" ;;
esac

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
# Issue 39 item 3 on a 4-GPU machine (the kill and the rerun included), e.g.:
#   BUDGET=120 CKPT=0.5 WAIT=400 bash benchmarks/gpu_runs/run23/slots.sh a   then `slots.sh w` until it says "all done"
#   or, for the kill: `KILL_AFTER=45 bash ... slots.sh k` (waits until a fit started after another's end has run KILL_AFTER s,
#   then sends the Snakemake session SIGINT, as Ctrl-C in its terminal does), then `bash ... slots.sh r` (the same
#   target again: finished fits are kept, killed ones resume from their checkpoint) and `w` until "all done".
# BUDGET: fit.time_budget_s (training seconds; 30 by default), CKPT: fit.checkpoint_minutes, FIT: more `fit` settings
# as JSON (a CPU trial of the kill: BASE=test FIT='{"iterations": 100000}' BUDGET=25 CKPT=0.1 KILL_AFTER=12). Stage a also samples
# nvidia-smi every 2 s (smi.csv): the per-GPU utilisation over the run.
set -u
# Run from a copy: a later call re-sends the working tree and replaces its files under a running job (run26).
REPO=${SRC:-/tmp/slots_src} W=${W:-/tmp/w23} R=$OUT/slots
BASE=${BASE:-paper}
SYNTHETIC=${SYNTHETIC:-'{"cameras": 12, "frames": 10, "width": 665, "height": 575, "supersample": 1}'}
VARIANTS=${VARIANTS:-'variants=[pig,no_precond,fixed_anchors,no_offsets,single_mlp]'}
if [ "$BASE" = paper ]; then
  # The kit's install took 60-90 s of a 600 s call (run22); a warm machine has it from the call before.
  [ -d /tmp/site/gsplat ] && [ -d /tmp/text ] || bash .gpu/device-setup.sh >/dev/null
  [ -d /tmp/snk/snakemake ] || python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/snk \
    .gpu/snakemake/*.whl
  # Set-up's build environment, and gsplat's extension loaded once before the GPU jobs start side by side
  # (benchmarks/gpu_runs/kit_env.sh: run33 lost two of four fits to a rebuild race).
  . benchmarks/gpu_runs/kit_env.sh "$REPO"
  export PYTHONPATH=/tmp/site:/tmp/snk:$REPO
else
  export PYTHONPATH=$REPO PYTHONUNBUFFERED=1
fi
if ! command -v python >/dev/null; then  # the rules call `python`
  mkdir -p /tmp/shim && ln -sf "$(command -v python3)" /tmp/shim/python && export PATH=/tmp/shim:$PATH
fi
mkdir -p "$R"
snake() { (cd "$W" && python3 -m snakemake --snakefile "$REPO/Snakefile" --scheduler greedy "$@"); }
collect() {
  local run
  for run in "" 2; do
    [ -e "$W/snakemake$run.out" ] || continue
    cp "$W/snakemake$run.out" "$R/snakemake$run.txt"
    python3 "$REPO/benchmarks/job_timeline.py" "$W/snakemake$run.out" --workdir "$W" > "$R/jobs$run.md"
  done
  cp "$W/smi.csv" "$R/" 2>/dev/null
  grep -h "resuming" "$W"/results/*/*/*/logs/fit.log > "$R/resumed.txt" 2>/dev/null
  cp "$W"/results/tables/*.md "$R/" 2>/dev/null
  [ -e "$W/rc" ] && echo "snakemake exit $(cat "$W/rc"); all done"
  grep -c '| done |' "$R/jobs.md" | sed 's/$/ jobs done/'
}
wait_run() {  # SECONDS
  local end=$((SECONDS + $1))
  while [ $SECONDS -lt $end ] && [ ! -e "$W/rc" ]; do sleep 5; done
  collect
}
start_snake() {  # OUTPUT_NAME: all_tables in its own session (setsid: it outlives the call), its group in $W/pgid
  export -f snake; export W REPO VARIANTS
  # A background job of a script starts with SIGINT ignored, and bash cannot undo that: python restores the default.
  setsid python3 -c 'import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_DFL); os.execvp(sys.argv[1], sys.argv[1:])' \
    bash -c 'echo $$ > "$W/pgid"; snake all_tables --config preset=run23 "$VARIANTS" > "$W/'"$1"'.out" 2>&1
    echo $? > "$W/rc"' < /dev/null > /dev/null 2>&1 &
}
case $1 in
  a) rm -rf "$W" "$REPO" && mkdir -p "$W" "$REPO" && cp -r config "$W/"
     tar -c --exclude=./results --exclude=./.git --exclude=./.gpu --exclude=./.snakemake . | tar -x -C "$REPO"
     python3 - "$W/config/presets/run23.yaml" "$BASE" "$SYNTHETIC" "${BUDGET:-30}" "${CKPT:-}" "${FIT:-{\}}" <<'PY'
import json, sys
import yaml
from pig.config import load_preset
path, base, synthetic, budget, checkpoint_minutes, fit = sys.argv[1:]
preset = load_preset(base)
preset.pop("_path")
preset["synthetic"].update(json.loads(synthetic))
preset["fit"].update(time_budget_s=float(budget), weight_lpips=0.0, compile=False, compile_posing=False)
if checkpoint_minutes:
    preset["fit"]["checkpoint_minutes"] = float(checkpoint_minutes)
preset["fit"].update(json.loads(fit))
preset["precond"].update(cg_compile=False)
for rule in ("fit_avatar", "render_split", "evaluate"):  # as in `paper` (for a trial on another base)
    preset["resources"].setdefault(rule, {})["gpu"] = 1
with open(path, "w") as out:
    yaml.safe_dump(preset, out, sort_keys=False)
PY
     (nvidia-smi -L || echo "no nvidia-smi") > "$R/devices.txt" 2>&1
     snake plan_tables --cores 1 --config preset=run23 "$VARIANTS" > "$R/plan.txt" 2>&1
     # An `if`, not `command -v ... && setsid ... &`: that backgrounds the whole list in a subshell that keeps the
     # call's output open while the sampler runs (run44: a call piped to `tail` hung to its time limit).
     if command -v nvidia-smi >/dev/null; then
       setsid nvidia-smi --query-gpu=timestamp,index,utilization.gpu,memory.used --format=csv -l 2 \
         > "$W/smi.csv" 2>/dev/null < /dev/null &
     fi
     start_snake snakemake; sleep 5; wait_run "${WAIT:-420}" ;;
  k) # a fit ended and another has run KILL_AFTER s: SIGINT to Snakemake's process group, as Ctrl-C
     end=$((SECONDS + ${WAIT:-540}))
     until [ $SECONDS -ge $end ] || python3 - "$W/snakemake.out" "${KILL_AFTER:-45}" "$REPO/benchmarks" <<'PY'
import datetime, sys
sys.path.insert(0, sys.argv[3])
from job_timeline import parse
fits = [j for j in parse(open(sys.argv[1]).read()).values() if j["rule"] == "fit_avatar"]
first_end = min((j["end"] for j in fits if j["status"] == "done"), default=None)
# a fit started after another ended, and running long enough to have written a checkpoint
late = [j for j in fits if j["status"] == "running" and first_end and j["start"] >= first_end
        and (datetime.datetime.now() - j["start"]).total_seconds() >= float(sys.argv[2])]
sys.exit(0 if late else 1)
PY
     do sleep 5; done
     kill -INT -- -"$(cat "$W/pgid")" && date +"killed at %T" | tee "$R/killed.txt"
     sleep 20; collect ;;
  r) rm -f "$W/rc"; start_snake snakemake2; sleep 5; wait_run "${WAIT:-420}" ;;
  w) wait_run "${WAIT:-540}" ;;
esac

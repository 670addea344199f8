#!/usr/bin/env bash
# Device-side: bash benchmarks/gpu_runs/run23/determinism.sh (outputs under $OUT/determinism/); from the repository
# root, with .gpu/ carried. Expected GPU wall time ~5 min (kit set-up where absent, capture ~50 s, six fits ~3 min).
# What `fit.deterministic` (torch.use_deterministic_algorithms) costs and buys on the GPU: six identical fits of the
# paper preset with its speed levers off (float32, nothing compiled: compilation would take 4-5 of the minutes),
# 100 iterations each (80 timed) on one capture (8 cameras x 6 frames at 1330 x 1150, seed 0), in one process, alternating
# off / on three times: ms/it of each (the cost, same process, interleaved), and per setting the avatar.pt tensors
# of the three fits against each other and the spread of their final held-out PSNR (benchmarks/compare_fits.py).
set -u
[ -d /tmp/site/gsplat ] && [ -d /tmp/text ] || bash .gpu/device-setup.sh >/dev/null
export PYTHONPATH=/tmp/site:$PWD TORCH_EXTENSIONS_DIR=/tmp/text PYTHONUNBUFFERED=1
# cuBLAS reads its workspace setting when the process first uses it, before the first fit that asks for determinism:
# set for every fit, so that "on" fits get deterministic matmuls and "off" fits differ from them only in torch's switch.
export CUBLAS_WORKSPACE_CONFIG=:4096:8
W=/tmp/det D=$OUT/determinism
mkdir -p $D
BASE=fit.precision=float32,fit.compile=false,fit.compile_posing=false,fit.batched_render=false,fit.fused_adam=false,fit.log_every=1,fit.host_band=false,precond.cg_check_every=1,precond.cg_compile=false,precond.cg_graphs=false
V=()
for r in a b c; do V+=(--variant "off_$r:$BASE,fit.deterministic=false" --variant "on_$r:$BASE,fit.deterministic=true"); done
timeout 540 python3 benchmarks/fit_gpu.py --workdir $W --frames 6 --cameras 8 --iterations 100 --warmup 20 \
  --eval-every 100 "${V[@]}" --json $D/fits.json > $D/fits.txt 2>&1
echo "fit_gpu exit $?"; tail -25 $D/fits.txt
for s in off on; do
  python3 benchmarks/compare_fits.py $W/fit_${s}_a $W/fit_${s}_b $W/fit_${s}_c --json $D/compare_$s.json \
    > $D/compare_$s.txt 2>&1
  cat $D/compare_$s.txt
  cp $W/fit_${s}_a/train_log.csv $D/${s}_a_train_log.csv 2>/dev/null
done
grep -i "determinis" $D/fits.txt | sort | uniq -c | head -5 > $D/warnings.txt
cat $D/warnings.txt

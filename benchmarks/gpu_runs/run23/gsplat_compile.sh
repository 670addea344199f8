#!/usr/bin/env bash
# Device-side: bash benchmarks/gpu_runs/run23/gsplat_compile.sh, from the repository root with .gpu/ carried; outputs
# under $OUT/gsplat_compile/. What a new GPU user's first gsplat call costs (docs/gpu.md, "What the first runs spend
# compiling"): gsplat 1.5.3's JIT build of its CUDA extension into an empty TORCH_EXTENSIONS_DIR with gsplat's own
# defaults (MAX_JOBS unset: 10 compile jobs; TORCH_CUDA_ARCH_LIST unset: the visible GPU's architecture), as a pip
# user gets it, then a second process loading that cached build. The kit's prebuilt extension (/tmp/text) is not used.
# Expected GPU wall time: ~2-3 min (kit install 60-90 s on a fresh machine, none on a warm one; the build ~1-2 min of
# nvcc on the CPU cores, the GPU idle; the cached load seconds).
set -u
[ -d /tmp/site/gsplat ] && [ -d /tmp/text ] || bash .gpu/device-setup.sh >/dev/null
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
D=$OUT/gsplat_compile
mkdir -p "$D"
cache=$(mktemp -d /tmp/gsplat_cold.XXXXXX)
{
  echo "cores: $(nproc)"
  if command -v nvcc >/dev/null; then echo "nvcc: $(command -v nvcc)"; nvcc --version | tail -n 2; else echo "nvcc: not on PATH"; fi
  nvidia-smi --query-gpu=name,driver_version --format=csv,noheader 2>&1 || echo "nvidia-smi: none"
} 2>&1 | tee "$D/machine.txt"
# The extension import timed alone (torch imported first); gsplat prints its own build time when it builds.
probe='
import os, sys, time
t0 = time.perf_counter()
import torch
t1 = time.perf_counter()
from gsplat.cuda._backend import _C
t2 = time.perf_counter()
state = "loaded" if _C is not None else "MISSING (no CUDA toolkit, or the build failed)"
cache = os.environ["TORCH_EXTENSIONS_DIR"]
print(f"{sys.argv[1]}: gsplat CUDA extension {state}; import {t2 - t1:.1f} s (torch {t1 - t0:.1f} s); "
      f"torch {torch.__version__}, CUDA {torch.version.cuda}; TORCH_EXTENSIONS_DIR {cache}")
'
for run in cold cached; do
  start=$SECONDS
  env -u MAX_JOBS -u TORCH_CUDA_ARCH_LIST TORCH_EXTENSIONS_DIR="$cache" timeout 420 python3 -c "$probe" "$run" \
    > "$D/$run.txt" 2>&1
  echo "$run: rc $?, wall $((SECONDS - start)) s" >> "$D/$run.txt"
  grep -v '^\s*$' "$D/$run.txt" | tail -n 4
done
{ du -sh "$cache"; ls "$cache"/gsplat_cuda/*.so 2>&1; } | tee "$D/cache.txt"

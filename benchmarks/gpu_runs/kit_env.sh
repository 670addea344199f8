# Sourced by the hold scripts on the GPU machine after .gpu/device-setup.sh: the environment that set-up built or
# unpacked gsplat's CUDA extension under, then one load of that extension before anything starts in parallel. With
# another TORCH_CUDA_ARCH_LIST or MAX_JOBS, torch's extension loader sees other build flags and rebuilds; four fits
# that rebuild at once race on the build directory's lock (run33: two of four died with "gsplat_cuda.so: file too
# short"), so any rebuild happens here, once.
export PYTHONPATH=/tmp/site:$1 TORCH_EXTENSIONS_DIR=/tmp/text TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16 PYTHONUNBUFFERED=1
python3 -c "from gsplat.cuda._backend import _C; assert _C is not None" || { echo "gsplat's CUDA extension does not load"; exit 1; }

python3 benchmarks/fit_gpu.py --workdir /tmp/mg/data --frames 10 --cameras 8 --capture-only

python3 benchmarks/fit_multi_gpu.py --workdir /tmp/mg --gpus 4 --parity 3000 --repeats 2

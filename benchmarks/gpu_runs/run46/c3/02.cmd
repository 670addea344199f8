for g in 0 1 2 3; do CUDA_VISIBLE_DEVICES=$g python3 benchmarks/fit_multi_gpu.py --workdir /tmp/mg --gpus 1 --parity 3000 --repeats 1 > $Q/parity_1gpu_$g.txt 2>&1 & sleep 2; done; wait

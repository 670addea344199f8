CUDA_VISIBLE_DEVICES=2 timeout 330 python3 benchmarks/fit_multi_gpu.py --workdir /tmp/mg1 --gpus 1 --shard-solves on --iterations 60 --warmup 40 --profile-phases 5 --kernel-profile 5

timeout 275 python3 benchmarks/fit_multi_gpu.py --workdir /tmp/mg --gpus 4 --shard-solves on --iterations 60 --warmup 40 --profile-phases 5 --kernel-profile 5

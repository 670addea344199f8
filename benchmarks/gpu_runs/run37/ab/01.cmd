bash benchmarks/gpu_runs/ab_tree.sh .ab/6958fcf .

# Every table of a dataset in one target, and its plan. For the paper's runs (the full method on the dataset's
# subjects, the structural ablations and the noise levels on their subjects):
#   snakemake --cores all plan_tables --configfile config/paper_tables.yaml --config preset=paper dataset=dna
#   snakemake --cores all all_tables --configfile config/paper_tables.yaml --config preset=paper dataset=dna
# A killed run resumes: finished fits stay (Snakemake's outputs), a killed fit continues from its checkpoint.pt.


rule all_tables:
    """Every table of the config's dataset that applies: main and LOD; ablation and noise where the dataset names
    their subjects; regions where it has ground truth."""
    input:
        all_table_targets(),


rule plan_tables:
    """Print the fits of all_tables, which are done, and the GPU-hours of the others: preset iterations x
    `ms_per_iteration` or `ms_per_iteration_lpips` of the config, then each fit's render and evaluate of the
    dataset's protocol (the `plan_rates` of the config, else pig plan's H100 defaults); the wall time on the
    `plan_gpus` counts, else on this machine's GPU slots."""
    log:
        f"results/tables/logs/plan_{config['dataset']}.log",
    localrule: True
    conda:
        CPU_ENV
    params:
        results=f"results/{config['dataset']}",
        dataset=config["datasets"][config["dataset"]],
        runs=lambda wildcards: planned_runs(),
        preset=config["preset"],
        ms=config["ms_per_iteration"],
        ms_lpips=config["ms_per_iteration_lpips"],
        rates=lambda wildcards: plan_rate_options(),
        gpus=lambda wildcards: " ".join(map(str, config.get("plan_gpus") or [gpu_slot_count()])),
    shell:
        "python -m pig.stages.plan --results {params.results:q} --dataset {params.dataset:q} {params.runs} "
        "--preset {params.preset:q} --ms-per-iteration {params.ms} --ms-per-iteration-lpips {params.ms_lpips} "
        "{params.rates} --gpus {params.gpus} 2>&1 | tee {log:q}"

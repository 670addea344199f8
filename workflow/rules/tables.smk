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
    """Print the fits of all_tables, which are done, and the GPU-hours of the others (preset iterations x
    `ms_per_iteration` or `ms_per_iteration_lpips` of the config)."""
    log:
        f"results/tables/logs/plan_{config['dataset']}.log",
    localrule: True
    conda:
        CPU_ENV
    params:
        results=f"results/{config['dataset']}",
        runs=lambda wildcards: planned_runs(),
        preset=config["preset"],
        ms=config["ms_per_iteration"],
        ms_lpips=config["ms_per_iteration_lpips"],
        gpus=lambda wildcards: gpu_slot_count(),
    shell:
        "python -m pig.stages.plan --results {params.results:q} {params.runs} --preset {params.preset:q} "
        "--ms-per-iteration {params.ms} --ms-per-iteration-lpips {params.ms_lpips} --gpus {params.gpus} "
        "2>&1 | tee {log:q}"

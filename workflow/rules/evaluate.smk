# Render the held-out splits at every level of detail, score them, and build the paper's tables.
# Each table collects the config's `variants` that belong to it (pig.avatar.variants.table_variants), e.g.
#   snakemake --cores 2 results/tables/synthetic_ablation.csv --config 'variants=[pig,no_precond,template_bound]'
# fits, renders and scores just those. The regions table needs ground truth: only generated datasets have it.


rule render_split:
    """Render every view of a held-out split at every level of detail."""
    input:
        checkpoint="results/{dataset}/{subject}/{variant}/avatar.pt",
        capture="results/{dataset}/{subject}/capture/report.json",
    output:
        directory("results/{dataset}/{subject}/{variant}/renders/{split}"),
    log:
        "results/{dataset}/{subject}/{variant}/logs/render_{split}.log",
    benchmark:
        "results/{dataset}/{subject}/{variant}/benchmarks/render_{split}.tsv"
    wildcard_constraints:
        split="|".join(SPLITS),
    conda:
        conda_env("render_split")
    threads: preset_threads("render_split")
    resources:
        **preset_resources("render_split"),
    params:
        capture=lambda wildcards, input: str(Path(input.capture).parent),
        preset=config["preset"],
        # Not used by the command: a change reruns the rule (params trigger).
        settings=preset_settings("evaluate", "rasterizer"),
    shell:
        "python -m pig.gpu_slots --gpus {resources.gpu} --preset {params.preset:q} --rule render_split -- "
        "python -m pig render --checkpoint {input.checkpoint:q} --capture {params.capture:q} "
        "--split {wildcards.split:q} --output {output:q} --preset {params.preset:q} --encode-workers {threads} "
        "> {log:q} 2>&1"


rule evaluate:
    """Score every level of detail of a rendered split in one pass: PSNR, SSIM, LPIPS per image, FID per set."""
    input:
        renders="results/{dataset}/{subject}/{variant}/renders/{split}",
        capture="results/{dataset}/{subject}/capture/report.json",
    output:
        # Written after every LOD's {split}_lod{l}.csv / .json (their number is the variant's avatar.levels).
        record="results/{dataset}/{subject}/{variant}/metrics/{split}.json",
    log:
        "results/{dataset}/{subject}/{variant}/logs/evaluate_{split}.log",
    benchmark:
        "results/{dataset}/{subject}/{variant}/benchmarks/evaluate_{split}.tsv"
    wildcard_constraints:
        split="|".join(SPLITS),
    conda:
        conda_env("evaluate")
    threads: preset_threads("evaluate")
    resources:
        **preset_resources("evaluate"),
    params:
        capture=lambda wildcards, input: str(Path(input.capture).parent),
        output=lambda wildcards, output: str(Path(output.record).parent),
        preset=config["preset"],
        # Not used by the command: a change reruns the rule (params trigger).
        settings=preset_settings("evaluate"),
    shell:
        "python -m pig.gpu_slots --gpus {resources.gpu} --preset {params.preset:q} --rule evaluate -- "
        "python -m pig evaluate --capture {params.capture:q} --renders {input.renders:q} "
        "--split {wildcards.split:q} --output {params.output:q} "
        "--preset {params.preset:q} --encode-workers {threads} > {log:q} 2>&1"


rule make_tables:
    """The main and LOD tables and the plot of held-out PSNR against training time of every variant."""
    input:
        passes=lambda wildcards: table_passes(wildcards.dataset, "main"),
        train_logs=table_train_logs,
    output:
        table="results/tables/{dataset}.csv",
        markdown="results/tables/{dataset}.md",
        page=report(
            "results/tables/{dataset}.html",
            caption="../report/main_table.rst",
            category="Tables",
            labels={"dataset": "{dataset}", "table": "main"},
        ),
        lod="results/tables/{dataset}_lod.csv",
        lod_markdown="results/tables/{dataset}_lod.md",
        lod_page=report(
            "results/tables/{dataset}_lod.html",
            caption="../report/lod_table.rst",
            category="Tables",
            labels={"dataset": "{dataset}", "table": "levels of detail"},
        ),
        plot=report(
            "results/tables/{dataset}_training.png",
            caption="../report/training.rst",
            category="Training",
            subcategory="Held-out PSNR against time",
            labels={"dataset": "{dataset}"},
        ),
    log:
        "results/tables/logs/{dataset}.log",
    benchmark:
        "results/tables/benchmarks/{dataset}.tsv"
    wildcard_constraints:
        dataset="|".join(map(re.escape, config["datasets"])),
    conda:
        CPU_ENV
    threads: preset_threads("make_tables")
    resources:
        **preset_resources("make_tables"),
    params:
        summaries=lambda wildcards: table_summaries(wildcards.dataset, "main"),
        variants=variant_names("main"),
        output=lambda wildcards, output: str(Path(output.table).parent),
    shell:
        "python -m pig tables --dataset {wildcards.dataset:q} --summaries {params.summaries:q} "
        "--train-logs {input.train_logs:q} --variants {params.variants:q} --output {params.output:q} "
        "> {log:q} 2>&1"


rule make_table:
    """One of the structural ablation, noise and ground-truth region tables."""
    input:
        passes=lambda wildcards: table_passes(wildcards.dataset, wildcards.table),
    output:
        table="results/tables/{dataset}_{table}.csv",
        markdown="results/tables/{dataset}_{table}.md",
        page=report(
            "results/tables/{dataset}_{table}.html",
            caption="../report/other_table.rst",
            category="Tables",
            labels={"dataset": "{dataset}", "table": "{table}"},
        ),
    log:
        "results/tables/logs/{dataset}_{table}.log",
    benchmark:
        "results/tables/benchmarks/{dataset}_{table}.tsv"
    wildcard_constraints:
        dataset="|".join(map(re.escape, config["datasets"])),
        table="|".join(OTHER_TABLES),
    conda:
        CPU_ENV
    threads: preset_threads("make_table")
    resources:
        **preset_resources("make_table"),
    params:
        summaries=lambda wildcards: table_summaries(wildcards.dataset, wildcards.table),
        variants=lambda wildcards: table_variants(preset(), variant_names(wildcards.table), wildcards.table),
        output=lambda wildcards, output: str(Path(output.table).parent),
        preset=config["preset"],
    shell:
        "python -m pig tables --table {wildcards.table:q} --dataset {wildcards.dataset:q} "
        "--summaries {params.summaries:q} --variants {params.variants:q} --preset {params.preset:q} "
        "--output {params.output:q} > {log:q} 2>&1"

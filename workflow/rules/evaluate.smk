# Render the held-out splits at every level of detail, score them, and build the paper's tables.
# Each table collects the config's `variants` that belong to it (pig.avatar.variants.table_variants), e.g.
#   snakemake --cores 2 results/tables/synthetic_ablation.csv --config 'variants=[pig,no_precond,template_bound]'
# fits, renders and scores just those. The regions table needs ground truth: only generated datasets have it.
from pig.avatar.config import AvatarConfig
from pig.avatar.variants import table_variants, variant_overrides
from pig.config import load_section

SPLITS = ["novel_view", "novel_pose"]
OTHER_TABLES = ["ablation", "noise", "regions"]


def lod_levels(variant):
    """LOD indices 0..L-1 of a variant: the preset's `avatar.levels` after the variant's overrides."""
    overrides = variant_overrides(preset(), variant).get("avatar")
    return list(range(load_section(preset(), "avatar", AvatarConfig, overrides).levels))


def table_runs(dataset, table):
    """(subject, variant) pairs of a table: its variants among the config's on the dataset's `subjects` (main and
    regions tables) or `<table>_subjects` (ablation, noise). Refused at once, naming the target, when it has none."""
    target = f"results/tables/{dataset}{'' if table == 'main' else '_' + table}.csv"
    if table == "regions" and not dataset_config(dataset).get("generated", False):
        raise ValueError(f"{target}: region metrics need the ground-truth meshes that only generated datasets have "
                         f"(`generated: true`, e.g. synthetic); {config['datasets'][dataset]} is a real capture")
    names = table_variants(preset(), config["variants"], table)
    if not names:
        raise ValueError(f"{target}: none of the variants {config['variants']} belongs to the {table} table; "
                         "name them with --config 'variants=[pig,...]'")
    people = subjects(dataset, "main" if table in ("main", "regions") else table)
    if not people:
        raise ValueError(f"{target}: {config['datasets'][dataset]} names no `{table}_subjects`")
    return [(subject, variant) for subject in people for variant in names]


def table_summaries(dataset, table):
    return [
        f"results/{dataset}/{subject}/{variant}/metrics/{split}_lod{lod}.json"
        for subject, variant in table_runs(dataset, table)
        for split in SPLITS
        for lod in lod_levels(variant)
    ]


rule render_split:
    input:
        checkpoint="results/{dataset}/{subject}/{variant}/avatar.pt",
        capture="results/{dataset}/{subject}/capture/report.json",
    output:
        directory("results/{dataset}/{subject}/{variant}/renders/{split}"),
    params:
        capture=lambda wildcards, input: str(Path(input.capture).parent),
        preset=config["preset"],
        # Not used by the command: a change reruns the rule (params trigger).
        settings=preset_settings("evaluate", "rasterizer"),
    log:
        "results/{dataset}/{subject}/{variant}/logs/render_{split}.log",
    benchmark:
        "results/{dataset}/{subject}/{variant}/benchmarks/render_{split}.tsv"
    wildcard_constraints:
        split="|".join(SPLITS),
    threads: preset_threads("render_split")
    resources:
        **preset_resources("render_split"),
    shell:
        "python -m pig.stages.render --checkpoint {input.checkpoint:q} --capture {params.capture:q} "
        "--split {wildcards.split:q} --output {output:q} --preset {params.preset:q} > {log:q} 2>&1"


rule evaluate:
    input:
        renders="results/{dataset}/{subject}/{variant}/renders/{split}",
        capture="results/{dataset}/{subject}/capture/report.json",
    output:
        csv="results/{dataset}/{subject}/{variant}/metrics/{split}_lod{lod}.csv",
        summary="results/{dataset}/{subject}/{variant}/metrics/{split}_lod{lod}.json",
    params:
        capture=lambda wildcards, input: str(Path(input.capture).parent),
        output=lambda wildcards, output: str(Path(output.csv).parent),
        preset=config["preset"],
        # Not used by the command: a change reruns the rule (params trigger).
        settings=preset_settings("evaluate"),
    log:
        "results/{dataset}/{subject}/{variant}/logs/evaluate_{split}_lod{lod}.log",
    benchmark:
        "results/{dataset}/{subject}/{variant}/benchmarks/evaluate_{split}_lod{lod}.tsv"
    wildcard_constraints:
        split="|".join(SPLITS),
        lod=r"\d+",
    threads: preset_threads("evaluate")
    resources:
        **preset_resources("evaluate"),
    shell:
        "python -m pig.stages.evaluate --capture {params.capture:q} --renders {input.renders:q} "
        "--split {wildcards.split:q} --lod {wildcards.lod:q} --output {params.output:q} --preset {params.preset:q} "
        "> {log:q} 2>&1"


# The main and LOD tables and the training plot (held-out PSNR against wall time) of every variant.
rule make_tables:
    input:
        summaries=lambda wildcards: table_summaries(wildcards.dataset, "main"),
        train_logs=lambda wildcards: [
            f"results/{wildcards.dataset}/{subject}/{variant}/train_log.csv"
            for subject, variant in table_runs(wildcards.dataset, "main")
        ],
    output:
        table="results/tables/{dataset}.csv",
        markdown="results/tables/{dataset}.md",
        lod="results/tables/{dataset}_lod.csv",
        lod_markdown="results/tables/{dataset}_lod.md",
        plot="results/tables/{dataset}_training.png",
    params:
        variants=config["variants"],
        output=lambda wildcards, output: str(Path(output.table).parent),
    log:
        "results/tables/logs/{dataset}.log",
    benchmark:
        "results/tables/benchmarks/{dataset}.tsv"
    wildcard_constraints:
        dataset="|".join(config["datasets"]),
    threads: preset_threads("make_tables")
    resources:
        **preset_resources("make_tables"),
    shell:
        "python -m pig.stages.tables --dataset {wildcards.dataset:q} --summaries {input.summaries:q} "
        "--train-logs {input.train_logs:q} --variants {params.variants:q} --output {params.output:q} > {log:q} 2>&1"


# The structural ablation, noise and ground-truth region tables.
rule make_table:
    input:
        summaries=lambda wildcards: table_summaries(wildcards.dataset, wildcards.table),
    output:
        table="results/tables/{dataset}_{table}.csv",
        markdown="results/tables/{dataset}_{table}.md",
    params:
        variants=lambda wildcards: table_variants(preset(), config["variants"], wildcards.table),
        output=lambda wildcards, output: str(Path(output.table).parent),
        preset=config["preset"],
    log:
        "results/tables/logs/{dataset}_{table}.log",
    benchmark:
        "results/tables/benchmarks/{dataset}_{table}.tsv"
    wildcard_constraints:
        dataset="|".join(config["datasets"]),
        table="|".join(OTHER_TABLES),
    resources:
        mem_mb=2000,
        runtime=10,
    shell:
        "python -m pig.stages.tables --table {wildcards.table:q} --dataset {wildcards.dataset:q} "
        "--summaries {input.summaries:q} --variants {params.variants:q} --preset {params.preset:q} "
        "--output {params.output:q} > {log:q} 2>&1"

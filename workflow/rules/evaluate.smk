# Render the held-out splits at every level of detail, score them, and build the paper's tables.
from pig.avatar.config import AvatarConfig
from pig.avatar.variants import variant_overrides
from pig.config import load_section

SPLITS = ["novel_view", "novel_pose"]


def lod_levels(variant):
    """LOD indices 0..L-1 of a variant: the profile's `avatar.levels` after the variant's overrides."""
    overrides = variant_overrides(profile(), variant).get("avatar")
    return list(range(load_section(profile(), "avatar", AvatarConfig, overrides).levels))


rule render_split:
    input:
        checkpoint="results/{dataset}/{subject}/{variant}/avatar.pt",
        capture="results/{dataset}/{subject}/capture/report.json",
    output:
        directory("results/{dataset}/{subject}/{variant}/renders/{split}"),
    params:
        capture=lambda wildcards, input: str(Path(input.capture).parent),
        profile=PROFILE,
        # Not used by the command: a change reruns the rule (params trigger).
        settings=profile_settings("evaluate", "rasterizer"),
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
        "--split {wildcards.split:q} --output {output:q} --profile {params.profile:q} > {log:q} 2>&1"


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
        profile=PROFILE,
        # Not used by the command: a change reruns the rule (params trigger).
        settings=profile_settings("evaluate"),
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
        "--split {wildcards.split:q} --lod {wildcards.lod:q} --output {params.output:q} --profile {params.profile:q} "
        "> {log:q} 2>&1"


rule make_tables:
    input:
        summaries=lambda wildcards: [
            f"results/{wildcards.dataset}/{subject}/{variant}/metrics/{split}_lod{lod}.json"
            for subject in subjects(wildcards.dataset)
            for variant in config["variants"]
            for split in SPLITS
            for lod in lod_levels(variant)
        ],
        train_logs=lambda wildcards: expand(
            "results/{dataset}/{subject}/{variant}/train_log.csv",
            dataset=wildcards.dataset, subject=subjects(wildcards.dataset), variant=config["variants"],
        ),
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

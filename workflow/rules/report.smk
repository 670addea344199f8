# Pictures for `snakemake --report report.html` (captions and the workflow's description in workflow/report/):
# a ground-truth / render / error montage of each rendered split (pig.render.montage).


rule montage_split:
    """Ground truth, finest-LOD render and error of a few views of a rendered split."""
    input:
        renders="results/{dataset}/{subject}/{variant}/renders/{split}",
        capture="results/{dataset}/{subject}/capture/report.json",
    output:
        report(
            "results/{dataset}/{subject}/{variant}/montage/{split}.png",
            caption="../report/montage.rst",
            category="Renders",
            labels={"dataset": "{dataset}", "subject": "{subject}", "variant": "{variant}", "split": "{split}"},
        ),
    log:
        "results/{dataset}/{subject}/{variant}/logs/montage_{split}.log",
    benchmark:
        "results/{dataset}/{subject}/{variant}/benchmarks/montage_{split}.tsv"
    wildcard_constraints:
        split="|".join(SPLITS),
    conda:
        CPU_ENV
    threads: preset_threads("montage_split")
    resources:
        **preset_resources("montage_split"),
    params:
        capture=lambda wildcards, input: str(Path(input.capture).parent),
    shell:
        "python -m pig montage --capture {params.capture:q} --renders {input.renders:q} "
        "--split {wildcards.split:q} --output {output:q} > {log:q} 2>&1"

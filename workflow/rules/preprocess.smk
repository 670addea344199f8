# Preprocess a raw subject (THuman4 layout, DNA-Rendering, or the generated synthetic capture) into
# results/{dataset}/{subject}/capture/ (sentinel report.json): undistorted, masked, resized frames,
# cameras, SMPL-X parameters, splits, projection check. Reruns when the raw files (params.raw: sizes and mtimes),
# the dataset YAML or the preset's `preprocess` section change.


rule preprocess_capture:
    """Undistort, mask and resize a raw subject's frames; cameras, SMPL-X parameters, splits."""
    input:
        unpack(preprocess_inputs),
    output:
        "results/{dataset}/{subject}/capture/report.json",
    log:
        "results/{dataset}/{subject}/logs/preprocess.log",
    benchmark:
        "results/{dataset}/{subject}/benchmarks/preprocess.tsv"
    conda:
        CPU_ENV
    threads: preset_threads("preprocess_capture")
    resources:
        **preset_resources("preprocess_capture"),
    params:
        root=lambda wildcards: raw_root(wildcards.dataset, wildcards.subject),
        output=lambda wildcards, output: str(Path(output[0]).parent),
        format=lambda wildcards: dataset_config(wildcards.dataset)["format"],
        dataset=lambda wildcards: config["datasets"][wildcards.dataset],
        body_model=body_model_option,
        preset=config["preset"],
        # Not used by the command: a change of either reruns the rule (params trigger).
        settings=preprocess_settings,
        raw=raw_manifest,
    shell:
        "python -m pig preprocess --format {params.format:q} --input {params.root:q} "
        "--output {params.output:q} --preset {params.preset:q} --dataset {params.dataset:q} "
        "--subject {wildcards.subject:q} {params.body_model:q} > {log:q} 2>&1"

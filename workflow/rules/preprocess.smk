# Preprocess a raw subject (THuman4 layout, DNA-Rendering, or the generated synthetic capture) into
# results/{dataset}/{subject}/capture/ (sentinel report.json): undistorted, masked, resized frames,
# cameras, SMPL-X parameters, splits, projection check.
from snakemake.exceptions import WorkflowError

from pig.data.formats import capture_format
from pig.data.raw import CaptureError


def preprocess_inputs(wildcards):
    """Raw files of the subject; a real dataset whose data or body model is absent fails here, at DAG time."""
    dataset = dataset_config(wildcards.dataset)
    source = config["datasets"][wildcards.dataset]
    root = Path(raw_root(wildcards.dataset, wildcards.subject))
    if dataset.get("generated"):
        return {"raw": str(root)}  # written by the generate rule
    try:
        files = capture_format(dataset["format"]).required_files(root)
    except CaptureError as err:
        raise WorkflowError(f"dataset {wildcards.dataset!r} (root {dataset['root']!r} in {source}): {err}") from None
    inputs = {"raw": [str(p) for p in files]}
    body_model = dataset.get("body_model")
    if not body_model or not Path(body_model).is_file():
        found = f"{body_model!r} does not exist" if body_model else "it is not set"
        raise WorkflowError(
            f"dataset {wildcards.dataset!r}: `body_model` in {source} must name the SMPL-X model file ({found}); "
            "download SMPLX_NEUTRAL.npz (licensed, smpl-x.is.tue.mpg.de), put it e.g. at "
            "data/body_models/SMPLX_NEUTRAL.npz and set `body_model:` to that path")
    inputs["body_model"] = body_model
    return inputs


def body_model_option(wildcards, input):
    return f"--body-model {input.body_model}" if "body_model" in input.keys() else ""


rule preprocess_capture:
    input:
        unpack(preprocess_inputs),
    output:
        "results/{dataset}/{subject}/capture/report.json",
    params:
        root=lambda wildcards: raw_root(wildcards.dataset, wildcards.subject),
        output=lambda wildcards, output: str(Path(output[0]).parent),
        format=lambda wildcards: dataset_config(wildcards.dataset)["format"],
        dataset=lambda wildcards: config["datasets"][wildcards.dataset],
        body_model=body_model_option,
        profile=PROFILE,
    log:
        "results/{dataset}/{subject}/logs/preprocess.log",
    benchmark:
        "results/{dataset}/{subject}/benchmarks/preprocess.tsv"
    threads: 2
    resources:
        gpu=0,
        mem_mb=4000,
        runtime=60,
    shell:
        "python -m pig.stages.preprocess --format {params.format} --input {params.root} --output {params.output} "
        "--profile {params.profile} --dataset {params.dataset} --subject {wildcards.subject} {params.body_model} "
        "> {log} 2>&1"

# Preprocess a raw subject (THuman4 layout, DNA-Rendering, or the generated synthetic capture) into
# results/{dataset}/{subject}/capture/ (sentinel report.json): undistorted, masked, resized frames,
# cameras, SMPL-X parameters, splits, projection check. Reruns when the raw files (params.raw: sizes and mtimes),
# the dataset YAML or the preset's `preprocess` section change.
from snakemake.exceptions import WorkflowError

from pig.data.formats import capture_format
from pig.data.raw import CaptureError


def preprocess_inputs(wildcards):
    """Raw files of the subject; a real dataset whose data or body model is absent fails here, at DAG time."""
    dataset = dataset_config(wildcards.dataset)
    source = config["datasets"][wildcards.dataset]
    root = Path(raw_root(wildcards.dataset, wildcards.subject))
    if dataset.get("generated"):
        # Written by the generate rule. A changed file under it reruns preprocess through params.raw, which
        # Snakemake evaluates for a job downstream of a rerun generate only when it runs, after the rewrite.
        return {"raw": str(root)}
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
    return ["--body-model", input.body_model] if "body_model" in input.keys() else []


# The keys of a dataset YAML that pig.stages.preprocess reads (subject lists and root are not among them).
PREPROCESS_DATASET_KEYS = ("name", "format", "body_model", "split")


def preprocess_settings(wildcards):
    """Hash of what the stage reads besides the raw files: the preset's `preprocess` section with this dataset's
    entry of `preprocess.datasets`, and the dataset YAML's PREPROCESS_DATASET_KEYS."""
    dataset = dataset_config(wildcards.dataset)
    section = dict(preset().get("preprocess") or {})
    per_dataset = (section.pop("datasets", None) or {}).get(dataset.get("name"))
    return settings_hash({"preprocess": section, "dataset_overrides": per_dataset,
                          "dataset": {key: dataset.get(key) for key in PREPROCESS_DATASET_KEYS}})


def raw_manifest(wildcards):
    """Hash of the sizes and mtimes of the subject's raw folder (images, masks, calibration, parameters), of the
    files its format requires and of the body model."""
    paths = [raw_root(wildcards.dataset, wildcards.subject)]
    if not dataset_config(wildcards.dataset).get("generated"):
        inputs = preprocess_inputs(wildcards)
        paths += [*inputs["raw"], inputs["body_model"]]
    return file_manifest(paths)


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
        preset=config["preset"],
        # Not used by the command: a change of either reruns the rule (params trigger).
        settings=preprocess_settings,
        raw=raw_manifest,
    log:
        "results/{dataset}/{subject}/logs/preprocess.log",
    benchmark:
        "results/{dataset}/{subject}/benchmarks/preprocess.tsv"
    threads: preset_threads("preprocess_capture")
    resources:
        **preset_resources("preprocess_capture"),
    shell:
        "python -m pig.stages.preprocess --format {params.format:q} --input {params.root:q} --output {params.output:q} "
        "--preset {params.preset:q} --dataset {params.dataset:q} --subject {wildcards.subject:q} "
        "{params.body_model:q} > {log:q} 2>&1"

# Generate the built-in synthetic subject (THuman4 layout + ground-truth meshes) under the synthetic
# dataset's root; its sizes come from the preset's `synthetic` section (pig.data.synthetic).
from pig.config import load_section
from pig.data.synthetic_config import SyntheticConfig


def synthetic_config():
    return load_section(preset(), "synthetic", SyntheticConfig)


rule generate_capture:
    output:
        directory(str(Path(dataset_config("synthetic")["root"]) / "{subject}")),
    params:
        preset=config["preset"],
        # Not used by the command: a changed `synthetic` section changes this and so reruns the rule.
        settings=repr(synthetic_config()),
    log:
        "results/synthetic/logs/generate_{subject}.log",
    benchmark:
        "results/synthetic/benchmarks/generate_{subject}.tsv"
    threads: synthetic_config().workers
    resources:
        gpu=0,
        # Per render process: a 256 MB ray cache plus chunked casting and one view's buffers.
        mem_mb=1500 + 800 * synthetic_config().workers,
        runtime=10 + synthetic_config().cameras * synthetic_config().frames // 100,
    shell:
        "python -m pig.stages.generate --output {output:q} --preset {params.preset:q} --workers {threads} "
        "--overwrite --quiet > {log:q} 2>&1"

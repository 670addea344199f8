# Generate the built-in synthetic subject (THuman4 layout + ground-truth meshes) under the synthetic
# dataset's root; its sizes come from the preset's `synthetic` section (pig.data.synthetic.config).


rule generate_capture:
    """Render the synthetic subject: multi-view video, masks, cameras, SMPL-X parameters, true meshes."""
    output:
        # Generated subjects are never nested (`subject_paths` is for real layouts): root/{subject} as a pattern.
        directory(str(Path(dataset_config("synthetic")["root"]) / "{subject}")),
    log:
        "results/synthetic/logs/generate_{subject}.log",
    benchmark:
        "results/synthetic/benchmarks/generate_{subject}.tsv"
    conda:
        CPU_ENV
    threads: synthetic_config().workers
    resources:
        gpu=0,
        # Per render process: a 256 MB ray cache plus chunked casting and one view's buffers.
        mem_mb=1500 + 800 * synthetic_config().workers,
        runtime=10 + synthetic_config().cameras * synthetic_config().frames // 100,
    params:
        preset=config["preset"],
        # Not used by the command: a changed `synthetic` section changes this and so reruns the rule.
        settings=repr(synthetic_config()),
    shell:
        "python -m pig generate --output {output:q} --preset {params.preset:q} --workers {threads} "
        "--overwrite --quiet > {log:q} 2>&1"

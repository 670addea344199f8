# Fit one avatar per (dataset, subject, variant) on the preprocessed capture's train split.
# A killed fit resumes from {variant}/checkpoint.pt when the rule runs again. Reruns when the preset sections the
# fit reads or the variant's overrides change (params.settings). Its progress lines (iteration, loss, held-out PSNR,
# time left) go to the log and, through `tee`, to the console (the shell's pipefail keeps the fit's exit status).
# A preset's `gpu: N` for the rule (N > 1) fits one avatar on N GPUs at once: the local slots give the job N devices,
# Slurm's sbatch asks for N (--gpus), and `pig fit --gpus N` runs one process on each (docs/gpu.md).
# Fits start before the renders and evaluations that are ready beside them (`priority`): they are the longest jobs,
# and Snakemake otherwise picks among equal priorities the job with the most input bytes, a render or an evaluate,
# so the last fits start late and leave devices idle at the end (run44, 6 fits on 4 GPUs: 330 s against 278 s
# replayed fits first; benchmarks/NOTES.md, "Workflow", "The tables workload on four GPUs").


rule fit_avatar:
    """Fit one avatar (a method variant) to a preprocessed capture's training views."""
    input:
        capture="results/{dataset}/{subject}/capture/report.json",
    output:
        checkpoint="results/{dataset}/{subject}/{variant}/avatar.pt",
        log_csv="results/{dataset}/{subject}/{variant}/train_log.csv",
        curve=report(
            "results/{dataset}/{subject}/{variant}/train_log.png",
            caption="../report/train_log.rst",
            category="Training",
            subcategory="Loss curves",
            labels={"dataset": "{dataset}", "subject": "{subject}", "variant": "{variant}"},
        ),
    log:
        "results/{dataset}/{subject}/{variant}/logs/fit.log",
    benchmark:
        "results/{dataset}/{subject}/{variant}/benchmarks/fit.tsv"
    priority: 1
    conda:
        conda_env("fit_avatar")
    threads: preset_threads("fit_avatar")
    resources:
        **preset_resources("fit_avatar"),
    params:
        capture=lambda wildcards, input: str(Path(input.capture).parent),
        output=lambda wildcards, output: str(Path(output.checkpoint).parent),
        preset=config["preset"],
        # Not used by the command: a change reruns the rule (params trigger).
        settings=lambda wildcards: preset_settings(
            "avatar", "fit", "field", "precond", "rasterizer", variant=wildcards.variant
        ),
    shell:
        "python -m pig.gpu_slots --gpus {resources.gpu} --preset {params.preset:q} --rule fit_avatar -- "
        "python -m pig fit --capture {params.capture:q} --output {params.output:q} "
        "--preset {params.preset:q} --variant {wildcards.variant:q} --threads {threads} --gpus {resources.gpu} "
        "2>&1 | tee {log:q}"

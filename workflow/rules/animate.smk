# Drive fitted avatars with motion (pig.stages.animate). A clip is `turntable` (the first training pose held still,
# one orbit) or the name of a motion shipped in pig/data/motions/ (e.g. `demo`, made by the project's own motion
# generator), or `preview`: a short, small turntable that the default target makes for the report (PREVIEW_OPTIONS).
# Example target: `snakemake --cores 2 animate_examples` (a turntable and the demo motion of the default dataset's
# first subject, full method, orbit camera; minutes on two CPU cores). Each clip's page (`{clip}.html`, the video
# embedded) is the report's item.


rule animate:
    """Render a fitted avatar driven by a motion clip as a video."""
    input:
        checkpoint="results/{dataset}/{subject}/{variant}/avatar.pt",
    output:
        video=directory("results/{dataset}/{subject}/{variant}/animate/{clip}"),
        page=report(
            "results/{dataset}/{subject}/{variant}/animate/{clip}.html",
            caption="../report/animation.rst",
            category="Animations",
            labels={"dataset": "{dataset}", "subject": "{subject}", "variant": "{variant}", "clip": "{clip}"},
        ),
    log:
        "results/{dataset}/{subject}/{variant}/logs/animate_{clip}.log",
    conda:
        conda_env("animate")
    threads: preset_threads("animate")
    resources:
        **preset_resources("animate"),
    params:
        motion=motion_argument,
        preset=config["preset"],
        options=animate_options,
        # Not used by the command: a change reruns the rule (params trigger).
        settings=preset_settings("rasterizer"),
    shell:
        "python -m pig.gpu_slots --gpus {resources.gpu} --preset {params.preset:q} --rule animate -- "
        "python -m pig animate --checkpoint {input.checkpoint:q} --output {output.video:q} --page {output.page:q} "
        "{params.motion} --preset {params.preset:q} {params.options} > {log:q} 2>&1"


rule animate_examples:
    """The example animations: a turntable and the shipped demo motion."""
    input:
        animate_examples(),

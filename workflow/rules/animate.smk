# Drive fitted avatars with motion (pig.stages.animate). A clip is `turntable` (the first training pose held still,
# one orbit) or the name of a motion shipped in pig/data/motions/ (e.g. `demo`, made by the project's own motion
# generator). Example target: `snakemake --cores 2 animate_examples` (a turntable and the demo motion of the
# default dataset's first subject, full method, orbit camera; minutes on two CPU cores).
import shlex
from importlib.resources import files

MOTIONS = files("pig.data") / "motions"
ANIMATE_OPTIONS = "--fps 15 --size 384 384"  # the examples: small and quick on a CPU


def motion_argument(wildcards):
    """`--motion FILE` for a shipped clip, nothing for the turntable."""
    return [] if wildcards.clip == "turntable" else ["--motion", str(MOTIONS / f"{wildcards.clip}.npz")]


rule animate:
    input:
        checkpoint="results/{dataset}/{subject}/{variant}/avatar.pt",
    output:
        directory("results/{dataset}/{subject}/{variant}/animate/{clip}"),
    params:
        motion=lambda wildcards: " ".join(shlex.quote(a) for a in motion_argument(wildcards)),
        preset=config["preset"],
        options=ANIMATE_OPTIONS,
        # Not used by the command: a change reruns the rule (params trigger).
        settings=preset_settings("rasterizer"),
    log:
        "results/{dataset}/{subject}/{variant}/logs/animate_{clip}.log",
    threads: preset_threads("animate")
    resources:
        **preset_resources("animate"),
    shell:
        "python -m pig.stages.animate --checkpoint {input.checkpoint:q} --output {output:q} {params.motion} "
        "--preset {params.preset:q} {params.options} > {log:q} 2>&1"


rule animate_examples:
    input:
        expand("results/{dataset}/{subject}/pig/animate/{clip}", dataset=config["dataset"],
               subject=subjects(config["dataset"])[0], clip=["turntable", "demo"]),

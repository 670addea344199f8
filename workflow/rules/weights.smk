# The metric networks' weight files (LPIPS, FID): the project's only network use, and only when asked for by name:
#   snakemake --cores 1 fetch_weights
# Without them the LPIPS and FID columns are n/a, and a run whose fits use the LPIPS term (the paper preset's) is
# refused at its start (`pig weights` lists what is there).


rule fetch_weights:
    """Download the missing metric weight files into the torch hub cache, each checked against its published
    SHA-256 before it takes its name; nothing already there is replaced (`pig weights --fetch`)."""
    log:
        "results/logs/fetch_weights.log",
    localrule: True
    conda:
        CPU_ENV
    shell:
        "python -m pig.stages.weights --fetch 2>&1 | tee {log:q}"

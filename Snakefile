# PiG-Avatar pipeline. `snakemake --cores 2` builds the default target (the synthetic table and the report's
# montages); `snakemake --report report.html` then writes the HTML report. See README.md and ../shared/DESIGN.md.
# Rules live in workflow/rules/*.smk, their helpers in workflow/rules/common.smk.
from snakemake.utils import validate


configfile: "config/config.yaml"


include: "workflow/rules/common.smk"


check_renamed_config_keys()
validate(config, "config/schema/config.schema.yaml")
check_config_paths()
register_gpu_slots()


report: "workflow/report/workflow.rst"


include: "workflow/rules/generate.smk"
include: "workflow/rules/preprocess.smk"
include: "workflow/rules/fit.smk"
include: "workflow/rules/evaluate.smk"
include: "workflow/rules/tables.smk"
include: "workflow/rules/report.smk"
include: "workflow/rules/animate.smk"
include: "workflow/rules/weights.smk"


check_preset_resources()


onstart:
    refuse_gpu_jobs()
    refuse_missing_loss_weights()


rule all:
    """The default target: the config dataset's main table and the montages of its runs."""
    input:
        default_targets(),

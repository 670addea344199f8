# PiG-Avatar pipeline. `snakemake --cores 2` builds the default target (the synthetic table);
# see README.md and ../shared/DESIGN.md. Rules live in workflow/rules/*.smk.
from snakemake.utils import validate


configfile: "config/config.yaml"


include: "workflow/rules/common.smk"


check_renamed_config_keys()
validate(config, "config/schema/config.schema.yaml")


include: "workflow/rules/generate.smk"
include: "workflow/rules/preprocess.smk"
include: "workflow/rules/fit.smk"
include: "workflow/rules/evaluate.smk"
include: "workflow/rules/animate.smk"


check_preset_resources()


rule all:
    input:
        default_targets(),

# Shared helpers of the rules (workflow/rules/*.smk hold rules only): dataset lookup, the compute preset and the
# resources and conda environment it gives each rule, input functions, and the settings hashes that make Snakemake
# rerun a rule when what its stage reads changes. Every rule calls a stage as `python -m pig STAGE` (the `pig`
# command, which the conda environment does not install). Nothing here imports torch: it would cost every
# `snakemake` start seconds (tests/test_workflow.py checks).
import hashlib
import json
import os
import re
import shlex
from functools import cache
from importlib.resources import files
from pathlib import Path

from snakemake.exceptions import WorkflowError
from snakemake_interface_executor_plugins.settings import ExecMode

from pig.avatar.config import AvatarConfig
from pig.avatar.variants import table_variants, variant_overrides
from pig.config import load_preset, load_section, load_yaml
from pig.data.formats import capture_format, subject_path
from pig.data.raw import CaptureError
from pig.data.synthetic.config import SyntheticConfig
from pig.gpu_slots import LOCAL_SLOTS_ENV, machine_devices
from pig.job_lifetime import JOB_ENV
from pig.metrics.weight_files import FETCH_COMMAND, loss_weight_problems
from pig.names import safe_name, snakemake_syntax
from pig.resources import check_rule_names, rule_resources

SPLITS = ["novel_view", "novel_pose"]
OTHER_TABLES = ["ablation", "noise", "regions"]
# Conda environments (`--sdm conda`), relative to workflow/rules/ where the rules are defined.
CPU_ENV = "../../envs/pig.yaml"
CUDA_ENV = "../../envs/pig-cuda.yaml"
MOTIONS = files("pig.data") / "motions"
ANIMATE_OPTIONS = "--fps 15 --size 384 384"  # the examples: small and quick on a CPU
# The default target's turntable for the report: 20 frames of 160 x 160, one revolution; ~8 s on two CPU cores for
# the cpu-demo avatar (benchmarks/NOTES.md).
PREVIEW_CLIP = "preview"
PREVIEW_OPTIONS = "--fps 8 --seconds 2.5 --orbit-period 2.5 --size 160 160"
# The keys of a dataset YAML that pig.stages.preprocess reads (subject lists and root are not among them).
PREPROCESS_DATASET_KEYS = ("name", "format", "body_model", "split", "reader")


def check_renamed_config_keys():
    """Refuses the config key `profile`, which named the compute preset before `preset` did."""
    if "profile" in config:
        raise WorkflowError(
            f"config key `profile` is now `preset` (compute presets are config/presets/*.yaml, apart from "
            f"Snakemake's profiles): use --config preset={config['profile']} or `preset:` in your config file"
        )


def check_config_paths():
    """Refuses a preset path holding Snakemake's path syntax: the rules' commands name it, and Snakemake would read
    `{x}` in it as a wildcard (WildcardError naming neither the preset nor the key)."""
    problem = snakemake_syntax(str(config["preset"]))
    if problem:
        raise WorkflowError(f"config `preset` {config['preset']!r} {problem}; rename the preset file or its folder")


@cache
def preset():
    """The preset's mapping, read once per Snakemake run so that every rule sees the same settings."""
    return load_preset(config["preset"])


# Rules whose threads and resources come from the preset's `resources:` section (pig.resources).
PRESET_RESOURCE_RULES = set()


def preset_threads(name):
    """Threads from the preset's `resources:` section, for the rule called `name`."""
    PRESET_RESOURCE_RULES.add(name)
    return rule_resources(preset(), name).threads


def preset_resources(name):
    """Resources (mem_mb, runtime, gpu, slurm_extra) from the preset's `resources:` section, for the rule called
    `name`."""
    PRESET_RESOURCE_RULES.add(name)
    return rule_resources(preset(), name).snakemake()


def conda_env(name):
    """The conda environment (envs/) for the rule called `name`, with CUDA PyTorch where the preset gives it a GPU."""
    return CUDA_ENV if rule_resources(preset(), name).gpu else CPU_ENV


def check_preset_resources():
    """Once all rules exist, refuses entries of the preset's `resources:` section that no rule reads (a typo), and
    a GPU for a rule whose command takes no local GPU slot (it would run on a device that no slot reserves)."""
    check_rule_names(preset(), PRESET_RESOURCE_RULES)
    for name in sorted(PRESET_RESOURCE_RULES):
        if rule_resources(preset(), name).gpu and "pig.gpu_slots" not in (workflow.get_rule(name).shellcmd or ""):
            raise WorkflowError(
                f"{preset()['_path']}: section 'resources' gives rule {name} a GPU, which it does not use; "
                "expected gpu: 0 for it"
            )


# A job's stage ends with the job's shell (pig.job_lifetime) rather than run on as an orphan that holds its output lock
# against the rerun. The jobs inherit this process's environment; an environment variable, so nothing reruns.
os.environ[JOB_ENV] = "1"


# Local GPU slots (pig.gpu_slots). The command of every rule that may use a GPU starts with the slot launcher. On a
# local run (Snakemake's own test: no --jobs for a cluster executor, and not a job step on a cluster node) this
# process marks its jobs' environment, and there the launcher gives each job that asks for a GPU a free device of
# its own (CUDA_VISIBLE_DEVICES) or makes it wait; the machine's GPU count becomes the `gpu` resource unless
# `--resources gpu=K` sets it. Elsewhere (Slurm: sbatch --gpus gives each job its device) the launcher only runs
# the command. An environment variable, not the command's text or params, so that moving between a local and a
# cluster run reruns nothing.
def local_run():
    """Whether this Snakemake process runs its jobs on this machine (Snakemake's own test, as above)."""
    return workflow.resource_settings.nodes is None and workflow.exec_mode != ExecMode.REMOTE


@cache
def gpu_devices():
    """(device ids, where they came from) of this machine, read once per Snakemake run (nvidia-smi, no torch)."""
    return machine_devices()


def register_gpu_slots():
    """On a local run: marks the jobs' environment for the slot launcher and, with GPUs, makes the `gpu` resource
    their count unless the command line or a profile set it. Without GPUs it stays unset, so that a dry run lists
    the GPU jobs; a real run refuses them (refuse_gpu_jobs)."""
    if not local_run():
        return
    os.environ[LOCAL_SLOTS_ENV] = "1"
    devices, _ = gpu_devices()
    if devices and "gpu" not in workflow.global_resources:
        workflow.global_resources["gpu"] = len(devices)


def gpu_slot_count():
    """GPU jobs that may run at once: the `gpu` resource where set, else the machine's GPUs (0 without)."""
    if "gpu" in workflow.global_resources:
        return workflow.global_resources["gpu"].value
    return len(gpu_devices()[0])


def refuse_gpu_jobs():
    """Before a local run starts any job: refuses the run at once when jobs that the preset gives a GPU are to run
    on a machine without one, naming the preset, instead of running them on the CPU or failing hours later."""
    devices, source = gpu_devices()
    if not local_run() or devices or workflow.touch:
        return
    rules = sorted({job.rule.name for job in workflow.dag.needrun_jobs() if job.resources.get("gpu", 0) > 0})
    if rules:
        raise WorkflowError(
            f"the compute preset {config['preset']!r} ({preset()['_path']}) gives rules {', '.join(rules)} a GPU and "
            f"this machine has none ({source}); nothing was run. Use a preset without GPU jobs "
            "(e.g. --config preset=cpu-demo) or run on a machine with GPUs"
        )


def refuse_missing_loss_weights():
    """Before a run starts any fit: refuses it at once when a fit's LPIPS term (Eq. 15, the paper preset's) needs
    pretrained weights that are missing or fail their checksum, naming the command that fetches them, instead of
    fitting for hours without the term."""
    if workflow.touch:
        return
    variants = sorted({job.wildcards.variant for job in workflow.dag.needrun_jobs() if job.rule.name == "fit_avatar"})
    problems = {}
    for variant in variants:
        fit = {**(preset().get("fit") or {}), **variant_overrides(preset(), variant).get("fit", {})}
        for problem in loss_weight_problems(fit):
            problems.setdefault(problem, []).append(variant)
    if problems:
        lines = "; ".join(f"{problem} (variants {', '.join(names)})" for problem, names in problems.items())
        raise WorkflowError(
            f"the compute preset {config['preset']!r} ({preset()['_path']}) fits with the LPIPS term of Eq. 15, whose "
            f"weights are not usable: {lines}. Nothing was run. Fetch them with `{FETCH_COMMAND}` (or "
            "`snakemake --cores 1 fetch_weights`), or set fit.weight_lpips: 0 for a fit without the term"
        )


def dataset_config(name):
    """The dataset YAML named `name` in the config's `datasets`."""
    if name not in config["datasets"]:
        raise ValueError(f"unknown dataset {name!r}: configured datasets are {sorted(config['datasets'])}")
    safe_name(name, "dataset name", "config `datasets`")  # it names results/{dataset}/ and the tables
    dataset = load_yaml(config["datasets"][name])  # the stages' reader: ids such as 0102 stay strings
    # Rule inputs and outputs: Snakemake would expand <logs> in them to logs, another folder, or fail on {x}.
    for key in ("root", "body_model"):
        problem = isinstance(dataset.get(key), str) and snakemake_syntax(dataset[key])
        if problem:
            raise WorkflowError(
                f"{config['datasets'][name]}: `{key}` {dataset[key]!r} {problem}; rename that folder or file"
            )
    return dataset


def subjects(name, table="main"):
    """Subject names of one table of a dataset: `subjects` (main tables), else `<table>_subjects` (e.g.
    `ablation_subjects`, `noise_subjects`; none when absent), so a table's subjects never enter another's."""
    key = "subjects" if table == "main" else f"{table}_subjects"
    names = dataset_config(name).get(key, None if table == "main" else [])
    valid = isinstance(names, list) and all(isinstance(s, str) and s for s in names)
    if not valid or (table == "main" and not names):
        raise ValueError(
            f"{config['datasets'][name]}: `{key}` must be a non-empty list of subject names, found {names!r}"
        )
    for subject in names:  # each names results/{dataset}/{subject}/ and the raw folder under `root`
        safe_name(subject, "subject", f"{config['datasets'][name]}: `{key}`")
    return names


def raw_root(dataset, subject):
    """Where the raw capture of a subject lives (generated for the synthetic dataset): `root/<subject>`, or
    `root/<path>` where the dataset's `subject_paths` maps the subject to a nested folder (ActorsHQ's
    Actor01/Sequence1)."""
    data = dataset_config(dataset)
    return str(Path(data["root"]) / subject_path(data, subject, config["datasets"][dataset]))


def default_targets():
    """The config dataset's main table (and its regions table where it has ground truth, the region metrics'
    only table), a montage of each split of its runs and a short turntable of its first run for the report."""
    dataset = config["dataset"]
    runs = table_runs(dataset, "main")
    montages = [
        f"results/{dataset}/{subject}/{variant}/montage/{split}.png" for subject, variant in runs for split in SPLITS
    ]
    subject, variant = next((run for run in runs if run[1] == "pig"), runs[0])
    preview = f"results/{dataset}/{subject}/{variant}/animate/{PREVIEW_CLIP}.html"
    regions = [table_target(dataset, "regions")] if dataset_config(dataset).get("generated", False) else []
    return [table_target(dataset, "main"), *regions, *montages, preview]


def _canonical(value):
    """`value` with every mapping key a string, so that JSON can sort keys of mixed YAML types."""
    if isinstance(value, dict):
        return {str(key): _canonical(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_canonical(item) for item in value]
    return value


def settings_hash(settings):
    """16 hex digits of the SHA-256 of `settings` as canonical JSON.

    As a rule's params entry (not used by its command) it reruns the rule through Snakemake's `params`
    rerun trigger exactly when the settings its stage reads change; comments and key order do not count.
    """
    text = json.dumps(_canonical(settings), sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def preset_settings(*sections, variant=None):
    """Hash of the preset sections a stage reads, with all overrides of `variant` where the stage applies them."""
    settings = {section: preset().get(section) for section in sections}
    if variant is not None:
        settings["variant"] = variant_overrides(preset(), variant)
    return settings_hash(settings)


def file_manifest(paths):
    """Hash of (path, size, mtime) of every file at or under `paths` (folders recursively, hidden names skipped).

    Changes when a raw file is added, removed, rewritten or touched, even to an older time, which the input
    mtime trigger misses. Stats without reading: os.scandir lists a real subject's 10^5 frames in about a second.
    """
    entries = set()

    def add(path, stat):
        entries.add(f"{path}\0{stat.st_size}\0{stat.st_mtime_ns}")

    def visit(folder):
        with os.scandir(folder) as listing:
            for entry in listing:
                if entry.name.startswith("."):
                    continue
                if entry.is_dir():
                    visit(entry.path)
                else:
                    add(entry.path, entry.stat())

    for path in map(str, paths):
        if os.path.isdir(path):
            visit(path)
        elif os.path.exists(path):
            add(path, os.stat(path))
    return hashlib.sha256("\n".join(sorted(entries)).encode()).hexdigest()[:16]


def synthetic_config():
    """The preset's `synthetic` section: what the generate stage makes."""
    return load_section(preset(), "synthetic", SyntheticConfig)


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
        required = capture_format(dataset["format"]).required_files(root)
    except CaptureError as err:
        raise WorkflowError(f"dataset {wildcards.dataset!r} (root {dataset['root']!r} in {source}): {err}") from None
    inputs = {"raw": [str(p) for p in required]}
    body_model = dataset.get("body_model")
    if not body_model or not Path(body_model).is_file():
        found = f"{body_model!r} does not exist" if body_model else "it is not set"
        raise WorkflowError(
            f"dataset {wildcards.dataset!r}: `body_model` in {source} must name the SMPL-X model file ({found}); "
            "download SMPLX_NEUTRAL.npz (licensed, smpl-x.is.tue.mpg.de), put it e.g. at "
            "data/body_models/SMPLX_NEUTRAL.npz and set `body_model:` to that path"
        )
    inputs["body_model"] = body_model
    return inputs


def body_model_option(wildcards, input):
    """`--body-model FILE` for a real dataset, nothing for a generated one (its model is in the raw folder)."""
    return ["--body-model", input.body_model] if "body_model" in input.keys() else []


def preprocess_settings(wildcards):
    """Hash of what the stage reads besides the raw files: the preset's `preprocess` section with this dataset's
    entry of `preprocess.datasets`, and the dataset YAML's PREPROCESS_DATASET_KEYS."""
    dataset = dataset_config(wildcards.dataset)
    section = dict(preset().get("preprocess") or {})
    per_dataset = (section.pop("datasets", None) or {}).get(dataset.get("name"))
    return settings_hash(
        {
            "preprocess": section,
            "dataset_overrides": per_dataset,
            "dataset": {key: dataset.get(key) for key in PREPROCESS_DATASET_KEYS},
        }
    )


def raw_manifest(wildcards):
    """Hash of the sizes and mtimes of the subject's raw folder (images, masks, calibration, parameters), of the
    files its format requires and of the body model."""
    paths = [raw_root(wildcards.dataset, wildcards.subject)]
    if not dataset_config(wildcards.dataset).get("generated"):
        inputs = preprocess_inputs(wildcards)
        paths += [*inputs["raw"], inputs["body_model"]]
    return file_manifest(paths)


def lod_levels(variant):
    """LOD indices 0..L-1 of a variant: the preset's `avatar.levels` after the variant's overrides."""
    overrides = variant_overrides(preset(), variant).get("avatar")
    return list(range(load_section(preset(), "avatar", AvatarConfig, overrides).levels))


def table_target(dataset, table):
    """The CSV path of a table: results/tables/{dataset}.csv (main) or {dataset}_{table}.csv."""
    return f"results/tables/{dataset}.csv" if table == "main" else f"results/tables/{dataset}_{table}.csv"


def variant_names(table):
    """The variants named for a table: its entry of the config's `table_variants`, else `variants`."""
    return config["table_variants"].get(table, config["variants"])


def dataset_tables(dataset):
    """The tables that apply to a dataset: main (with LOD), ablation and noise where it names their subjects and
    the config names variants of theirs, regions where it has ground truth (generated)."""
    tables = ["main"]
    for table in ("ablation", "noise"):
        if subjects(dataset, table) and table_variants(preset(), variant_names(table), table):
            tables.append(table)
    if dataset_config(dataset).get("generated", False):
        tables.append("regions")
    return tables


def all_table_targets():
    """Every table file of the config's dataset (dataset_tables), the LOD table beside the main one."""
    dataset = config["dataset"]
    paths = [table_target(dataset, table) for table in dataset_tables(dataset)]
    return [*paths, f"results/tables/{dataset}_lod.csv"]


def planned_runs():
    """`--run SUBJECT VARIANT` for each fit of the config's dataset's tables, each once (quoted for the shell)."""
    dataset = config["dataset"]
    runs = dict.fromkeys(run for table in dataset_tables(dataset) for run in table_runs(dataset, table))
    return " ".join(f"--run {shlex.quote(subject)} {shlex.quote(variant)}" for subject, variant in runs)


def plan_rate_options():
    """`--render-ms-per-frame 30 ...` for each rate that the config's `plan_rates` sets (pig plan's options)."""
    rates = config.get("plan_rates") or {}
    return " ".join(f"--{name.replace('_', '-')} {float(value)!r}" for name, value in rates.items())


def table_runs(dataset, table):
    """(subject, variant) pairs of a table: its variants among the config's on the dataset's `subjects` (main and
    regions tables) or `<table>_subjects` (ablation, noise). Refused at once, naming the target, when it has none."""
    target = table_target(dataset, table)
    if table == "regions" and not dataset_config(dataset).get("generated", False):
        raise ValueError(
            f"{target}: region metrics need the ground-truth meshes that only generated datasets have "
            f"(`generated: true`, e.g. synthetic); {config['datasets'][dataset]} is a real capture"
        )
    for variant in variant_names(table):  # each names results/{dataset}/{subject}/{variant}/
        safe_name(variant, "variant", "config `variants`")
    names = table_variants(preset(), variant_names(table), table)
    if not names:
        raise ValueError(
            f"{target}: none of the variants {variant_names(table)} belongs to the {table} table; "
            "name them with --config 'variants=[pig,...]' (or the table's entry of `table_variants`)"
        )
    people = subjects(dataset, "main" if table in ("main", "regions") else table)
    if not people:
        raise ValueError(f"{target}: {config['datasets'][dataset]} names no `{table}_subjects`")
    return [(subject, variant) for subject in people for variant in names]


def table_passes(dataset, table):
    """The evaluate records of a table's runs, one per split: the jobs' outputs (table_summaries' files come with
    them)."""
    return [
        f"results/{dataset}/{subject}/{variant}/metrics/{split}.json"
        for subject, variant in table_runs(dataset, table)
        for split in SPLITS
    ]


def table_summaries(dataset, table):
    """The evaluate summaries a table reads: every split and LOD of its runs."""
    return [
        f"results/{dataset}/{subject}/{variant}/metrics/{split}_lod{lod}.json"
        for subject, variant in table_runs(dataset, table)
        for split in SPLITS
        for lod in lod_levels(variant)
    ]


def table_train_logs(wildcards):
    """The training logs of the main table's runs (its plot of held-out PSNR against time)."""
    return [
        f"results/{wildcards.dataset}/{subject}/{variant}/train_log.csv"
        for subject, variant in table_runs(wildcards.dataset, "main")
    ]


def motion_argument(wildcards):
    """`--motion FILE` for a shipped clip, nothing for a turntable (quoted for the shell)."""
    if wildcards.clip in ("turntable", PREVIEW_CLIP):
        return ""
    return f"--motion {shlex.quote(str(MOTIONS / f'{wildcards.clip}.npz'))}"


def animate_options(wildcards):
    """The animate stage's size and length options: the preview's (PREVIEW_OPTIONS) or the examples'."""
    return PREVIEW_OPTIONS if wildcards.clip == PREVIEW_CLIP else ANIMATE_OPTIONS


def animate_examples():
    """A turntable and the demo motion of the default dataset's first subject, full method."""
    subject = subjects(config["dataset"])[0]
    return [f"results/{config['dataset']}/{subject}/pig/animate/{clip}.html" for clip in ("turntable", "demo")]

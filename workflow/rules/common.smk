# Shared helpers: dataset lookup, preset, paths, and the settings hashes that make Snakemake rerun a rule when
# what its stage reads changes. Every rule calls a `python -m pig.stages.*` CLI.
import hashlib
import json
import os
from functools import cache
from pathlib import Path

from snakemake.exceptions import WorkflowError

from pig.avatar.variants import variant_overrides
from pig.config import load_preset, load_yaml
from pig.resources import check_rule_names, rule_resources


def check_renamed_config_keys():
    """Refuses the config key `profile`, which named the compute preset before `preset` did."""
    if "profile" in config:
        raise WorkflowError(
            f"config key `profile` is now `preset` (compute presets are config/presets/*.yaml, apart from "
            f"Snakemake's profiles): use --config preset={config['profile']} or `preset:` in your config file")


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


def check_preset_resources():
    """Once all rules exist, refuses entries of the preset's `resources:` section that no rule reads (a typo)."""
    check_rule_names(preset(), PRESET_RESOURCE_RULES)


def dataset_config(name):
    if name not in config["datasets"]:
        raise ValueError(f"unknown dataset {name!r}: configured datasets are {sorted(config['datasets'])}")
    return load_yaml(config["datasets"][name])  # the stages' reader: ids such as 0102 stay strings


def subjects(name, table="main"):
    """Subject names of one table of a dataset: `subjects` (main tables), else `<table>_subjects` (e.g.
    `ablation_subjects`, `noise_subjects`; none when absent), so a table's subjects never enter another's."""
    key = "subjects" if table == "main" else f"{table}_subjects"
    names = dataset_config(name).get(key, None if table == "main" else [])
    valid = isinstance(names, list) and all(isinstance(s, str) and s for s in names)
    if not valid or (table == "main" and not names):
        raise ValueError(f"{config['datasets'][name]}: `{key}` must be a non-empty list of subject names, found {names!r}")
    return names


def raw_root(dataset, subject):
    """Where the raw capture of a subject lives (generated for the synthetic dataset)."""
    return str(Path(dataset_config(dataset)["root"]) / subject)


def default_targets():
    return [f"results/tables/{config['dataset']}.csv"]


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

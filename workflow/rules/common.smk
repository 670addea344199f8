# Shared helpers: dataset lookup, profile, paths. Every rule calls a `python -m pig.stages.*` CLI.
import yaml
from pathlib import Path

PROFILE = config["profile"]


def dataset_config(name):
    if name not in config["datasets"]:
        raise ValueError(f"unknown dataset {name!r}: configured datasets are {sorted(config['datasets'])}")
    with open(config["datasets"][name]) as handle:
        return yaml.safe_load(handle)


def subjects(name, table="main"):
    """Subject names of one table of a dataset: `subjects` (main tables), else `<table>_subjects` (e.g.
    `ablation_subjects`, `noise_subjects`; none when absent), so a table's subjects never enter another's."""
    key = "subjects" if table == "main" else f"{table}_subjects"
    names = dataset_config(name).get(key, None if table == "main" else [])
    valid = isinstance(names, list) and all(isinstance(s, str) and s for s in names)
    if not valid or (table == "main" and not names):
        raise ValueError(f"{config['datasets'][name]}: `{key}` must be a list of subject names as quoted strings "
                         f"(YAML reads an unquoted 0102 as the number 66), found {names!r}")
    return names


def raw_root(dataset, subject):
    """Where the raw capture of a subject lives (generated for the synthetic dataset)."""
    return str(Path(dataset_config(dataset)["root"]) / subject)


def default_targets():
    return [f"results/tables/{config['dataset']}.csv"]

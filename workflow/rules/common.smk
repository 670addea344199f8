# Shared helpers: dataset lookup, profile, paths. Every rule calls a `python -m pig.stages.*` CLI.
import yaml
from pathlib import Path

PROFILE = config["profile"]


def dataset_config(name):
    if name not in config["datasets"]:
        raise ValueError(f"unknown dataset {name!r}: configured datasets are {sorted(config['datasets'])}")
    with open(config["datasets"][name]) as handle:
        return yaml.safe_load(handle)


def subjects(name):
    return dataset_config(name)["subjects"]


def raw_root(dataset, subject):
    """Where the raw capture of a subject lives (generated for the synthetic dataset)."""
    return str(Path(dataset_config(dataset)["root"]) / subject)


def default_targets():
    return [f"results/tables/{config['dataset']}.csv"]

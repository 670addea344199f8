"""What each workflow job asks of the machine, per rule, from a compute preset's `resources:` section.

Snakemake schedules local jobs on them (threads against `--cores`, gpu against `--resources gpu=N`) and its Slurm
executor turns them into sbatch options: threads -> --cpus-per-task, mem_mb -> --mem, runtime -> --time,
gpu -> --gpus, slurm_extra verbatim (e.g. `--gres=gpu:a100:1` where a cluster names its GPUs so).
The section maps rule names, and `default` for the rules it does not name, to these keys.
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass, fields
from typing import Any

from pig.config import ConfigError, from_dict

DEFAULT = "default"
# A GPU count in sbatch's --gres (`--gres=gpu:2`, `--gres=gpu:a100:2`), which must agree with the rule's gpu.
_GRES_GPUS = re.compile(r"--gres[= ]\S*?\bgpu(?::[A-Za-z0-9_.-]+)?:(\d+)")


@dataclass
class RuleResources:
    threads: int = 1
    mem_mb: int = 2000
    runtime: int = 60  # minutes
    gpu: int = 0
    slurm_extra: str | None = None

    def snakemake(self) -> dict[str, Any]:
        """The `resources:` of a rule (threads go to its `threads:`)."""
        values = {"mem_mb": self.mem_mb, "runtime": self.runtime, "gpu": self.gpu}
        if self.slurm_extra:
            values["slurm_extra"] = self.slurm_extra
        return values


_LEAST = {"threads": 1, "mem_mb": 1, "runtime": 1, "gpu": 0}


def _section(preset: dict[str, Any]) -> tuple[dict[str, Any], str]:
    where = f"{preset.get('_path', '<preset>')}: section 'resources'"
    section = preset.get("resources") or {}
    if not isinstance(section, dict):
        raise ConfigError(f"{where}: expected a mapping of rule names to resources, found {section!r}")
    return section, where


def rule_resources(preset: dict[str, Any], rule: str) -> RuleResources:
    """Resources of `rule`: its entry in the section over the `default` entry over RuleResources' defaults."""
    section, where = _section(preset)
    values = {}
    for name in (DEFAULT, rule):
        entry = section.get(name) or {}
        if not isinstance(entry, dict):
            raise ConfigError(f"{where}.{name}: expected a mapping of {[f.name for f in fields(RuleResources)]}, "
                              f"found {entry!r}")
        from_dict(RuleResources, entry, f"{where}.{name}")  # names the entry that holds a wrong key or type
        values.update(entry)
    resources = from_dict(RuleResources, values, f"{where}.{rule}")
    for key, least in _LEAST.items():
        if getattr(resources, key) < least:
            source = rule if key in (section.get(rule) or {}) else DEFAULT
            raise ConfigError(f"{where}.{source}.{key}: expected at least {least}, found {getattr(resources, key)}")
    gres = _GRES_GPUS.search(resources.slurm_extra or "")
    if gres and int(gres.group(1)) != resources.gpu:  # a fit with gpu: N starts N processes (pig fit --gpus N)
        raise ConfigError(f"{where}.{rule}: slurm_extra asks Slurm for {gres.group(1)} GPU(s) ({gres.group(0)}) and gpu "
                          f"is {resources.gpu}; expected the same count in both")
    return resources


def check_rule_names(preset: dict[str, Any], rules: set[str]) -> None:
    """Refuse entries of the section that name no rule among `rules` (those that take their resources from it)."""
    section, where = _section(preset)
    unknown = sorted(set(section) - set(rules) - {DEFAULT})
    if unknown:
        raise ConfigError(f"{where}: no rule named {unknown} takes its resources from here; "
                          f"expected `{DEFAULT}` or some of {sorted(rules)}")


def host_cores() -> int:
    """The cores this process may run on (its CPU affinity, where the platform tells it: a Slurm job's or a pinned
    rank's, not the machine's)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1

"""Job resources per rule from the compute preset's `resources:` section (pig.resources, workflow/rules/common.smk)."""
from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from pig.config import ConfigError, load_preset
from pig.resources import RuleResources, check_rule_names, rule_resources

REPO = Path(__file__).resolve().parent.parent
PRESET_RULES = {"preprocess_capture", "fit_avatar", "render_split", "evaluate", "montage_split", "make_tables",
                "make_table", "animate"}


def preset(section) -> dict:
    return {"_path": "my.yaml", "resources": section}


def test_rule_entry_over_default_over_built_in():
    section = {"default": {"mem_mb": 3000, "runtime": 20}, "fit_avatar": {"runtime": 600, "gpu": 1}}
    assert rule_resources(preset(section), "fit_avatar") == RuleResources(threads=1, mem_mb=3000, runtime=600, gpu=1)
    assert rule_resources(preset(section), "evaluate") == RuleResources(mem_mb=3000, runtime=20)
    assert rule_resources({}, "evaluate") == RuleResources()


def test_snakemake_resources_carry_slurm_extra_only_when_set():
    assert RuleResources(gpu=1).snakemake() == {"mem_mb": 2000, "runtime": 60, "gpu": 1}
    extra = RuleResources(slurm_extra="--gres=gpu:a100:1").snakemake()
    assert extra["slurm_extra"] == "--gres=gpu:a100:1"


@pytest.mark.parametrize("section, message", [
    ({"fit_avatar": {"mem": 100}}, r"my\.yaml: section 'resources'\.fit_avatar: unknown key\(s\) \['mem'\]"),
    ({"default": {"runtime": "1h"}}, r"my\.yaml: section 'resources'\.default\.runtime: expected an integer, "
                                     r"found the string '1h'"),
    ({"default": {"gpu": -1}}, r"my\.yaml: section 'resources'\.default\.gpu: expected at least 0, found -1"),
    ({"default": {"threads": 4}, "fit_avatar": {"threads": 0}},
     r"my\.yaml: section 'resources'\.fit_avatar\.threads: expected at least 1, found 0"),
    ({"fit_avatar": 16000}, r"my\.yaml: section 'resources'\.fit_avatar: expected a mapping of \['threads', "),
    ([1, 2], r"my\.yaml: section 'resources': expected a mapping of rule names to resources, found \[1, 2\]"),
])
def test_bad_entries_name_file_rule_and_key(section, message):
    with pytest.raises(ConfigError, match=message):
        rule_resources(preset(section), "fit_avatar")


@pytest.mark.parametrize("extra, gpu, refused", [
    ("--gres=gpu:a100:4", 4, False), ("--gres=gpu:4 --partition=gpu", 4, False), ("--gres=gpu:a100:1", 4, True),
    ("--gres=gpu:2", 1, True), ("--gres=shard:2,gpu:h100:2", 2, False), ("--partition=gpu", 4, False),
])
def test_slurm_gres_gpu_count_agrees_with_gpu(extra, gpu, refused):
    # A fit with gpu: N runs on N GPUs (pig fit --gpus N): a --gres asking Slurm for another count is refused.
    section = {"fit_avatar": {"gpu": gpu, "slurm_extra": extra}}
    if refused:
        with pytest.raises(ConfigError, match=rf"my\.yaml: section 'resources'\.fit_avatar: slurm_extra asks Slurm for "
                                              rf"\d GPU\(s\) \(--gres=.*\) and gpu is {gpu}"):
            rule_resources(preset(section), "fit_avatar")
    else:
        assert rule_resources(preset(section), "fit_avatar").gpu == gpu


def test_unknown_rule_names_are_refused():
    check_rule_names(preset({"default": {}, "fit_avatar": {}}), PRESET_RULES)
    with pytest.raises(ConfigError, match=r"my\.yaml: section 'resources': no rule named \['fit'\] takes its resources "
                                          r"from here; expected `default` or some of \['animate', "):
        check_rule_names(preset({"fit": {"gpu": 1}}), PRESET_RULES)


@pytest.mark.parametrize("name", ["test", "cpu-demo", "paper"])
def test_shipped_presets(name):
    """Every preset's section loads for every rule; CPU presets ask for no GPU (the Slurm test's node has
    none), the paper preset's GPU stages one GPU each."""
    preset = load_preset(name)
    check_rule_names(preset, PRESET_RULES)
    resources = {rule: rule_resources(preset, rule) for rule in PRESET_RULES}
    gpus = {rule for rule, r in resources.items() if r.gpu}
    assert gpus == (set() if name != "paper" else {"fit_avatar", "render_split", "evaluate", "animate"})
    assert all(r.gpu <= 1 for r in resources.values())


def dry_run(tmp_path: Path, resources: dict) -> tuple[int, str]:
    """(exit code, output) of a dry run of the default target with the test preset plus `resources` (Snakemake as
    test_workflow runs it)."""
    from test_workflow import snakemake_exit

    work = tmp_path / "work"
    work.mkdir()
    (work / "config").symlink_to(REPO / "config")
    preset = yaml.safe_load((REPO / "config" / "presets" / "test.yaml").read_text())
    preset["resources"] = resources
    (tmp_path / "preset.yaml").write_text(yaml.safe_dump(preset))
    return snakemake_exit(work, "--dry-run", "--cores", "4", "--config", f"preset={tmp_path / 'preset.yaml'}")


def job_settings(output: str, rule: str) -> dict[str, str]:
    """The threads and resources a dry run printed for the first job of `rule`."""
    block = output.split(f"rule {rule}:\n", 1)[1].splitlines()
    block = block[:next(i for i, line in enumerate(block) if not line.startswith("    "))]
    lines = dict(line.strip().split(": ", 1) for line in block)
    settings = dict(item.split("=", 1) for item in lines["resources"].split(", "))
    return {"threads": lines.get("threads", "1"), **settings}


def test_workflow_jobs_take_the_preset_resources(tmp_path):
    code, output = dry_run(tmp_path, {"default": {"mem_mb": 900, "runtime": 5},
                                      "fit_avatar": {"threads": 3, "mem_mb": 1234, "runtime": 7, "gpu": 1,
                                                     "slurm_extra": "--gres=gpu:a100:1"}})
    assert code == 0, output[-3000:]
    fit = job_settings(output, "fit_avatar")
    assert {key: fit[key] for key in ("threads", "mem_mb", "runtime", "gpu", "slurm_extra")} == {
        "threads": "3", "mem_mb": "1234", "runtime": "7", "gpu": "1", "slurm_extra": "--gres=gpu:a100:1"}
    tables = job_settings(output, "make_tables")
    assert (tables["threads"], tables["mem_mb"], tables["runtime"], tables["gpu"]) == ("1", "900", "5", "0")
    assert "slurm_extra" not in tables


def test_workflow_fit_on_several_gpus_asks_for_them_and_passes_them_to_the_fit(tmp_path):
    code, output = dry_run(tmp_path, {"fit_avatar": {"gpu": 2, "slurm_extra": "--gres=gpu:a100:2"}})
    assert code == 0, output[-3000:]
    assert job_settings(output, "fit_avatar")["gpu"] == "2"
    command = next(line for line in output.splitlines() if "python -m pig fit " in line)
    assert "python -m pig.gpu_slots --gpus 2 " in command and " --gpus 2 2>&1" in command  # 2 slots, 2 processes


def test_workflow_refuses_a_resources_entry_no_rule_reads(tmp_path):
    code, output = dry_run(tmp_path, {"fit": {"gpu": 1}})
    assert code != 0
    assert f"{tmp_path / 'preset.yaml'}: section 'resources': no rule named ['fit'] takes its resources" in output

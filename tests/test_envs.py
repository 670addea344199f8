"""The conda environments under envs/ (`snakemake --sdm conda`): what they install matches pyproject.toml, and
nothing in them is a path, which would point elsewhere once Snakemake copies the file into .snakemake/conda/."""
import tomllib
from pathlib import Path

import pytest
import yaml
from packaging.requirements import Requirement

REPO = Path(__file__).resolve().parent.parent
ENVS = sorted((REPO / "envs").glob("*.yaml"))


def pip_section(env: dict) -> list[str]:
    sections = [item["pip"] for item in env["dependencies"] if isinstance(item, dict)]
    assert len(sections) == 1
    return sections[0]


def test_both_builds_are_there():
    assert [path.name for path in ENVS] == ["pig-cuda.yaml", "pig.yaml"]


@pytest.mark.parametrize("path", ENVS, ids=lambda path: path.name)
def test_environment_installs_the_package_dependencies_and_no_path(path):
    env = yaml.safe_load(path.read_text())
    assert env["channels"] == ["conda-forge"]
    pip = pip_section(env)
    options = [line for line in pip if line.startswith("-")]
    assert all(line.startswith("--extra-index-url https://") for line in options), options
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    wanted = {Requirement(line) for line in project["dependencies"]}
    given = {Requirement(line.split("#")[0]) for line in pip if not line.startswith("-")}
    assert all(not requirement.url for requirement in given)
    # Snakemake runs outside the environment; torch is pinned to one build, within pyproject's range.
    assert {str(r) for r in given if r.name != "torch"} == {str(r) for r in wanted
                                                             if r.name not in ("torch", "snakemake")}
    (torch,) = [r for r in given if r.name == "torch"]
    (pinned,) = torch.specifier
    assert pinned.operator == "==" and next(r for r in wanted if r.name == "torch").specifier.contains(pinned.version)
    assert pinned.version.endswith("+cpu") == (path.name == "pig.yaml")


@pytest.mark.parametrize("preset, cuda_rules", [
    ("test", set()), ("cpu-demo", set()), ("paper", {"fit_avatar", "render_split", "evaluate", "animate"})])
def test_rules_take_the_cuda_environment_where_the_preset_gives_them_a_gpu(preset, cuda_rules):
    """workflow/rules/common.smk's `conda_env` (plain Python): its paths, relative to the rules' folder as Snakemake
    reads a rule's `conda:`, name the two files under envs/."""
    namespace = {"config": {"preset": preset}}
    exec(compile((REPO / "workflow" / "rules" / "common.smk").read_text(), "common.smk", "exec"), namespace)
    rules = {"preprocess_capture", "fit_avatar", "render_split", "evaluate", "montage_split", "make_tables", "animate"}
    envs = {rule: (REPO / "workflow" / "rules" / namespace["conda_env"](rule)).resolve() for rule in rules}
    assert {rule for rule, path in envs.items() if path.name == "pig-cuda.yaml"} == cuda_rules
    assert {path for path in envs.values()} <= set(ENVS)

"""The `pig` command: a subcommand per stage, the same option names everywhere, help on every option, an example
in every --help, and `--device auto|cpu|cuda|cuda:N` parsed alike by every stage that computes."""
import argparse
import importlib
import shlex
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from pig.cli import STAGES
from pig.progress import progress_bar
from pig._cli import device_name, run_cli

REPO = Path(__file__).resolve().parents[1]
PRESENT = [stage for stage in STAGES if (REPO / "pig" / "stages" / f"{stage}.py").is_file()]
COMPUTING = ["fit", "render", "evaluate", "animate", "export", "view"]  # the stages that run torch on a device


def _run(*argv):
    return subprocess.run([sys.executable, *argv], capture_output=True, text=True, cwd=REPO, timeout=120,
                          env={"PATH": "/usr/bin:/bin", "PYTHONPATH": str(REPO)})


class _Parsed(Exception):
    pass


def stage_parser(stage: str, monkeypatch) -> argparse.ArgumentParser:
    """The parser `pig.stages.<stage>.main` builds, caught at its parse_args."""
    caught = {}

    def catch(self, *args, **kwargs):
        caught["parser"] = self
        raise _Parsed

    with monkeypatch.context() as patch:
        patch.setattr(argparse.ArgumentParser, "parse_args", catch)
        with pytest.raises(_Parsed):
            importlib.import_module(f"pig.stages.{stage}").main([])
    return caught["parser"]


def test_pig_help_lists_every_stage_module_and_the_viewer():
    modules = {p.stem for p in (REPO / "pig" / "stages").glob("*.py") if not p.stem.startswith("_")}
    assert modules <= set(STAGES) and "view" in STAGES
    result = _run("-m", "pig", "--help")
    assert result.returncode == 0, result.stderr
    listed = [line.split()[0] for line in result.stdout.split("stages:\n")[1].split("\n\n")[0].splitlines()]
    assert listed == list(STAGES)
    assert "usage: pig STAGE" in result.stdout and "example:\n  pig fit " in result.stdout
    # The console script runs the same function.
    scripts = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts == {"pig": "pig.cli:main"}


def test_unknown_stage_and_no_stage_are_usage_errors(capsys):
    from pig.cli import main

    assert main(["fitt"]) == 2
    assert "pig: error: unknown stage 'fitt'; stages: generate, preprocess, fit" in capsys.readouterr().err
    assert main([]) == 2 and "usage: pig STAGE" in capsys.readouterr().err


@pytest.mark.parametrize("stage", ["export", "tables"])
def test_pig_stage_and_python_m_stage_are_the_same_command(stage):
    via_pig, via_module = _run("-m", "pig", stage, "--help"), _run("-m", f"pig.stages.{stage}", "--help")
    assert via_pig.returncode == via_module.returncode == 0
    assert via_pig.stdout == via_module.stdout and via_pig.stdout.startswith(f"usage: pig {stage} ")


def test_a_stage_error_through_pig_is_one_line(tmp_path, capsys, monkeypatch):
    from pig.cli import main

    monkeypatch.delenv("PIG_DEBUG", raising=False)
    missing = tmp_path / "none.pt"
    assert main(["export", "--checkpoint", str(missing), "--output", str(tmp_path / "out"), "--device", "cpu"]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"export: error: {missing}: avatar checkpoint not found") and err.count("\n") == 1


@pytest.mark.parametrize("stage", PRESENT)
def test_every_option_has_help_and_the_help_an_example_that_parses(stage, monkeypatch):
    parser = stage_parser(stage, monkeypatch)
    assert parser.prog == f"pig {stage}"
    for action in parser._actions:
        assert action.help and action.help.strip(), f"pig {stage} {action.option_strings or action.dest}: no help"
    options = {option for action in parser._actions for option in action.option_strings}
    assert {"--quiet", "--traceback"} <= options
    assert parser.epilog.startswith("example:\n  ") and parser.epilog.count("\n") == 1
    words = shlex.split(parser.epilog.split("\n  ", 1)[1])
    assert words[:2] == ["pig", stage]
    example = parser.parse_args(words[2:])  # a usage error would exit
    assert not example.quiet


@pytest.mark.parametrize("stage", COMPUTING)
def test_computing_stages_take_the_same_device_option(stage, monkeypatch):
    parser = stage_parser(stage, monkeypatch)
    device = next(action for action in parser._actions if "--device" in action.option_strings)
    assert device.type is device_name and device.metavar == "auto|cpu|cuda|cuda:N"
    required = [action for action in parser._actions if action.required]
    base = [word for action in required for word in (action.option_strings[0], "novel_view" if action.choices else "x")]
    for value, parsed in (("auto", "auto"), ("cpu", "cpu"), ("cuda", "cuda"), ("cuda:3", "cuda:3"), ("CUDA:0", "cuda:0")):
        assert parser.parse_args([*base, "--device", value]).device == parsed
    for value in ("gpu", "cuda:", "cuda:-1", "cuda:x", "mps", "cpu:0", "cuda:0:1", ""):
        with pytest.raises(SystemExit) as exit_:
            parser.parse_args([*base, "--device", value])
        assert exit_.value.code == 2


def test_device_name_messages():
    assert [device_name(v) for v in ("auto", " cpu ", "cuda", "cuda:12")] == ["auto", "cpu", "cuda", "cuda:12"]
    with pytest.raises(argparse.ArgumentTypeError, match=r"'gpu': expected auto, cpu, cuda or cuda:N"):
        device_name("gpu")


def test_a_device_this_machine_lacks_is_a_one_line_error(tmp_path, capsys, monkeypatch):
    """Parsing accepts cuda:N; whether the machine has it is checked when the stage starts (pig.config)."""
    import torch

    from pig.stages import export

    monkeypatch.delenv("PIG_DEBUG", raising=False)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert run_cli(export.main, ["--checkpoint", str(tmp_path / "a.pt"), "--output", str(tmp_path / "o"),
                                 "--device", "cuda:1"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("export: error: --device 'cuda:1': CUDA is not available") and err.count("\n") == 1


def test_quiet_silences_progress_until_the_next_parser(monkeypatch):
    from pig.stages import export

    parser = stage_parser("export", monkeypatch)
    assert not progress_bar(range(3)).disable
    parser.parse_args(["--checkpoint", "a", "--output", "b", "--quiet"])
    assert progress_bar(range(3)).disable
    stage_parser("export", monkeypatch)  # a new run starts loud
    assert not progress_bar(range(3)).disable
    assert export  # imported by stage_parser too

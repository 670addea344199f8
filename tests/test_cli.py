"""Command-line entry points: an error is one line on stderr (no traceback) unless --traceback or PIG_DEBUG=1."""
from __future__ import annotations

import argparse
import os
import runpy
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
import torch

from pig.config import ConfigError, resolve_device
from pig._cli import TRACEBACK_HINT, add_common_arguments, run_cli

REPO = Path(__file__).resolve().parent.parent


def _failing_main(err: BaseException):
    def main(argv=None):
        add_common_arguments(argparse.ArgumentParser(prog="demo")).parse_args(argv)
        raise err
    return main


def _error_lines(capsys) -> list[str]:
    return capsys.readouterr().err.splitlines()


@pytest.mark.parametrize("err, line", [
    (ConfigError("p.yaml: section 'fit'.iterations: expected an integer"), "p.yaml: section 'fit'.iterations: expected an integer"),
    (FileNotFoundError("x/avatar.pt: missing"), "x/avatar.pt: missing"),
    (ValueError("first line\n  second line"), "first line second line"),
    (KeyError("x/split.json: no split 'novel_view'"), "x/split.json: no split 'novel_view'"),
    (KeyError("psnr"), f"KeyError: 'psnr' {TRACEBACK_HINT}"),
    (IndexError("list index out of range"), f"IndexError: list index out of range {TRACEBACK_HINT}"),
    (AssertionError(), f"AssertionError {TRACEBACK_HINT}"),
])
def test_an_exception_becomes_one_line(capsys, monkeypatch, err, line):
    monkeypatch.delenv("PIG_DEBUG", raising=False)
    assert run_cli(_failing_main(err), []) == 1
    assert _error_lines(capsys) == [f"test_cli: error: {line}"]


def test_traceback_flag_and_pig_debug_let_the_exception_through(capsys, monkeypatch):
    monkeypatch.delenv("PIG_DEBUG", raising=False)
    main = _failing_main(ConfigError("bad"))
    with pytest.raises(ConfigError, match="bad"):
        run_cli(main, ["--traceback"])
    assert run_cli(main, []) == 1  # the flag of the previous run does not stick
    assert _error_lines(capsys) == ["test_cli: error: bad"]
    monkeypatch.setenv("PIG_DEBUG", "1")
    with pytest.raises(ConfigError, match="bad"):
        run_cli(main, [])
    monkeypatch.setenv("PIG_DEBUG", "0")
    assert run_cli(main, []) == 1


def test_interrupts_usage_errors_and_exit_codes_pass_through(monkeypatch):
    monkeypatch.delenv("PIG_DEBUG", raising=False)
    with pytest.raises(KeyboardInterrupt):
        run_cli(_failing_main(KeyboardInterrupt()), [])
    with pytest.raises(SystemExit) as exit_info:
        run_cli(_failing_main(ConfigError("unreached")), ["--no-such-option"])
    assert exit_info.value.code == 2
    assert run_cli(lambda argv: None, []) == 0
    assert run_cli(lambda argv: 3, []) == 3


def _entry_points(tmp: Path) -> dict[str, tuple[list[str], str]]:
    """module -> (arguments of a typical mistake: a path that does not exist, the path the message must name)."""
    missing = tmp / "missing"
    (tmp / "body.npz").write_bytes(b"")
    return {
        "pig.stages.fit": (["--capture", str(missing), "--output", str(tmp / "fit"), "--device", "cpu"], str(missing)),
        "pig.stages.render": (["--checkpoint", str(tmp / "avatar.pt"), "--capture", str(missing), "--split", "novel_view",
                               "--output", str(tmp / "renders")], str(missing)),
        "pig.stages.evaluate": (["--capture", str(missing), "--renders", str(tmp / "renders"), "--split", "novel_view",
                                 "--output", str(tmp / "metrics")], str(tmp / "renders")),
        "pig.stages.tables": (["--dataset", "x", "--summaries", str(missing / "s.json"), "--variants", "pig",
                               "--output", str(tmp / "tables")], str(missing / "s.json")),
        "pig.stages.preprocess": (["--input", str(missing), "--output", str(tmp / "capture")], str(missing)),
        "pig.stages.generate": (["--output", str(tmp / "raw"), "--preset", str(missing / "p.yaml")], str(missing / "p.yaml")),
        "pig.data.smc_writer": (["--format", "thuman4", "--input", str(missing), "--output", str(tmp / "smc"),
                                 "--body-model", str(tmp / "body.npz")], str(missing)),
    }


def _run_module(module: str, argv: list[str], monkeypatch) -> int:
    """Run `python -m module argv` in this process, through its `if __name__ == "__main__":` block."""
    monkeypatch.setattr(sys, "argv", [module, *argv])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # runpy: the module is already imported
        with pytest.raises(SystemExit) as exit_info:
            runpy.run_module(module, run_name="__main__", alter_sys=True)
    return exit_info.value.code


@pytest.mark.parametrize("module", list(_entry_points(Path("/"))))
def test_every_entry_point_reports_a_missing_input_in_one_line(tmp_path, capsys, monkeypatch, module):
    monkeypatch.delenv("PIG_DEBUG", raising=False)
    argv, named = _entry_points(tmp_path)[module]
    assert _run_module(module, argv, monkeypatch) in (1, 2)
    lines = _error_lines(capsys)
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"{module.rsplit('.', 1)[1]}: ") and named in lines[0], lines[0]


@pytest.mark.parametrize("module", ["pig.stages.fit", "pig.stages.render", "pig.stages.evaluate", "pig.stages.tables"])
def test_traceback_flag_of_an_entry_point_shows_the_exception(tmp_path, monkeypatch, module):
    monkeypatch.delenv("PIG_DEBUG", raising=False)
    argv, named = _entry_points(tmp_path)[module]
    monkeypatch.setattr(sys, "argv", [module, *argv, "--traceback"])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        with pytest.raises((ValueError, OSError), match=named):  # CaptureError, missing renders, the tables' ValueError
            runpy.run_module(module, run_name="__main__", alter_sys=True)


def test_device_cuda_without_cuda_is_one_line_before_any_work(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("PIG_DEBUG", raising=False)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    output = tmp_path / "fit"
    argv = ["--capture", str(tmp_path / "missing"), "--output", str(output), "--device", "cuda"]
    assert _run_module("pig.stages.fit", argv, monkeypatch) == 1
    lines = _error_lines(capsys)
    assert len(lines) == 1 and lines[0].startswith("fit: error: --device 'cuda': CUDA is not available ("), lines
    assert not output.exists()  # refused before the output folder or the capture is touched


def test_resolve_device(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == torch.device("cpu")
    assert resolve_device("cpu") == torch.device("cpu")
    with pytest.raises(ConfigError, match=r"^device 'cuda:0': CUDA is not available \("):
        resolve_device("cuda:0")
    with pytest.raises(ConfigError, match=r"^device 'gpu': expected auto, cpu, cuda or cuda:N$"):
        resolve_device("gpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert resolve_device("auto") == torch.device("cuda")
    with pytest.raises(ConfigError, match=r"^device 'cuda:1': only 1 CUDA device\(s\) are visible$"):
        resolve_device("cuda:1")


def _tables(tmp_path: Path, *extra: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    environment = {k: v for k, v in os.environ.items() if k != "PIG_DEBUG"} | {"PYTHONPATH": str(REPO)} | (env or {})
    command = [sys.executable, "-m", "pig.stages.tables", "--dataset", "x", "--summaries", str(tmp_path / "s.json"),
               "--variants", "pig", "--output", str(tmp_path / "tables"), *extra]
    return subprocess.run(command, capture_output=True, text=True, env=environment, timeout=120)


def test_a_real_process_prints_one_line(tmp_path):
    result = _tables(tmp_path)
    assert result.returncode == 1
    assert result.stderr.splitlines() == [f"tables: error: {tmp_path / 's.json'}: expected a summary at "
                                          ".../{subject}/{variant}/metrics/{split}_lod{l}.json"]


def test_a_real_process_with_pig_debug_prints_the_traceback(tmp_path):
    result = _tables(tmp_path, env={"PIG_DEBUG": "1"})
    assert result.returncode == 1
    assert result.stderr.startswith("Traceback (most recent call last):")
    assert result.stderr.splitlines()[-1].startswith(f"ValueError: {tmp_path / 's.json'}: expected a summary")


PRESET_STAGES = ["pig.stages.generate", "pig.stages.preprocess", "pig.stages.fit", "pig.stages.render",
                 "pig.stages.evaluate", "pig.stages.tables", "pig.stages.animate"]


@pytest.mark.parametrize("module", PRESET_STAGES)
def test_profile_option_still_names_the_preset_with_a_note(tmp_path, capsys, monkeypatch, module):
    """`--profile`, the option's name before compute presets were renamed apart from Snakemake's profiles, still
    chooses the preset (here one that does not exist, which the error names) and says once what to type now."""
    import importlib

    parser_of = importlib.import_module(module).main
    missing = str(tmp_path / "old.yaml")
    with pytest.raises(SystemExit):
        parser_of(["--profile", missing, "--help"])
    out = capsys.readouterr()
    note = f"{module.replace('pig.stages.', 'pig ')}: note: --profile is deprecated, use --preset " \
           "(compute presets are in config/presets/)"
    assert out.err.splitlines() == [note]
    assert "--profile" not in out.out and "--preset PRESET" in out.out


def test_deprecated_profile_option_chooses_the_preset(tmp_path, capsys, monkeypatch):
    from pig.stages import generate

    monkeypatch.delenv("PIG_DEBUG", raising=False)
    missing = tmp_path / "old.yaml"
    assert run_cli(generate.main, ["--output", str(tmp_path / "raw"), "--profile", str(missing)]) == 1
    assert capsys.readouterr().err.splitlines() == [
        "pig generate: note: --profile is deprecated, use --preset (compute presets are in "
        "config/presets/)",
        f"generate: error: preset file {missing} does not exist"]
    assert not (tmp_path / "raw").exists()

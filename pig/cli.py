"""The `pig` command: one subcommand per pipeline stage (`pig fit ...` runs `pig.stages.fit`), as nerfstudio's
`ns-*` commands; `python -m pig ...` is the same command, and `python -m pig.stages.<stage>` still works.

Stages are found by name in a fixed list and imported only when run, so `pig --help` starts in a fraction of a
second (no torch) and names each stage by the first line of its module's docstring, read without importing it.
"""
from __future__ import annotations

import ast
import importlib
import importlib.util
import sys
from pathlib import Path

# In pipeline order; `view` is the browser viewer (pig.stages.view).
STAGES = ("generate", "preprocess", "fit", "render", "evaluate", "tables", "montage", "animate", "export", "view", "plan",
          "weights", "doctor")
USAGE = "usage: pig STAGE [OPTIONS]   (pig STAGE --help: the stage's options and an example)"


def summary(stage: str) -> str:
    """The first line of `pig.stages.<stage>`'s docstring, its "<Stage> stage: " prefix dropped."""
    spec = importlib.util.find_spec(f"pig.stages.{stage}")
    if spec is None or spec.origin is None:
        return "(not in this installation)"
    doc = ast.get_docstring(ast.parse(Path(spec.origin).read_text(encoding="utf-8"))) or ""
    line = doc.strip().splitlines()[0] if doc.strip() else ""
    for prefix in (f"{stage.capitalize()} stage: ", f"Stage `{stage}`: "):
        line = line.removeprefix(prefix)
    return line


def help_text() -> str:
    width = max(map(len, STAGES))
    lines = [USAGE, "", "PiG-Avatar pipeline stages:"]
    lines += [f"  {stage:<{width}}  {summary(stage)}" for stage in STAGES]
    lines += ["", "options:", "  -h, --help  show this message and exit", "",
              "example:", "  pig fit --capture results/synthetic/subject00/capture --output /tmp/fit --device cpu"]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    """Run `pig STAGE ARGS...`; returns the exit status (`pig._cli.run_cli`'s)."""
    from pig._cli import run_cli

    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        (sys.stdout if argv else sys.stderr).write(help_text())
        return 0 if argv else 2
    stage, rest = argv[0], argv[1:]
    if stage not in STAGES:
        sys.stderr.write(f"{USAGE}\npig: error: unknown stage {stage!r}; stages: {', '.join(STAGES)}\n")
        return 2
    try:
        module = importlib.import_module(f"pig.stages.{stage}")
    except ModuleNotFoundError as err:
        if err.name != f"pig.stages.{stage}":
            raise
        sys.stderr.write(f"pig: error: the {stage} stage (pig.stages.{stage}) is not in this installation\n")
        return 1
    return run_cli(module.main, rest)


if __name__ == "__main__":
    raise SystemExit(main())

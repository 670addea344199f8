"""Command-line entry points: an error is one line on stderr, not a traceback, unless one is asked for.

Every stage builds its parser with `stage_parser` (prog `pig <stage>`, an example in its help), ends with
`raise SystemExit(run_cli(main))`, and adds the shared options with `add_common_arguments(parser)` (`--quiet`,
`--traceback`); a stage that reads a compute preset takes it with `add_preset_argument`, one that computes on a
device takes `--device auto|cpu|cuda|cuda:N` with `add_device_argument`. An exception from `main` becomes one
line, `<stage>: error: <message>`, and exit status 1:
- bad input or a bad environment prints its message as it is: the project's own errors (ConfigError,
  CaptureError, ... all ValueErrors), any other ValueError, OSError (a missing, unreadable or unwritable
  file), and a KeyError whose argument is a sentence (`raise KeyError(f"{path}: no split ...")`);
- anything else is more likely a bug than bad input (IndexError, TypeError, a KeyError of a bare key such as
  `KeyError: 'psnr'`): its type, its message and a pointer to `--traceback`.
`--traceback` or the environment variable PIG_DEBUG=1 lets the exception propagate with its full traceback.
KeyboardInterrupt and SystemExit (argparse's usage errors, exit status 2) pass through unchanged.
"""
from __future__ import annotations

import argparse
import os
import re
import sys
from collections.abc import Callable
from pathlib import Path

from pig.config import DEFAULT_PRESET
from pig.job_lifetime import end_with_parent
from pig.progress import set_quiet

DEBUG_VARIABLE = "PIG_DEBUG"
TRACEBACK_HINT = f"(run with --traceback or {DEBUG_VARIABLE}=1 for the full traceback)"

# Set by parsing --traceback; `run_cli` clears it before each run.
_traceback_requested = False


class _TracebackFlag(argparse.Action):
    """`--traceback`: a store-true flag that also tells `run_cli`, which never sees the parsed arguments."""

    def __init__(self, option_strings, dest, **kwargs):
        super().__init__(option_strings, dest, nargs=0, default=False, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        global _traceback_requested
        _traceback_requested = True
        setattr(namespace, self.dest, True)


class _QuietFlag(argparse.Action):
    """`--quiet`: a store-true flag that also silences pig.progress (bars and the fit's progress lines)."""

    def __init__(self, option_strings, dest, **kwargs):
        super().__init__(option_strings, dest, nargs=0, default=False, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        set_quiet(True)
        setattr(namespace, self.dest, True)


def stage_parser(stage: str, doc: str, example: str) -> argparse.ArgumentParser:
    """The parser of `pig <stage>`: the first line of the module docstring `doc` as its description, and
    `example` (a whole command line, `pig <stage> ...`) shown after the options."""
    return argparse.ArgumentParser(prog=f"pig {stage}", description=doc.strip().splitlines()[0],
                                   epilog=f"example:\n  {example}", formatter_class=argparse.RawDescriptionHelpFormatter)


def add_common_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the options every entry point shares: `--quiet` and `--traceback`. Progress is on until `--quiet`
    is parsed (a new parser is a new run)."""
    set_quiet(False)
    parser.add_argument("--quiet", action=_QuietFlag,
                        help="no progress output (bars, the fit's progress lines); results, warnings and errors still print")
    parser.add_argument("--traceback", action=_TracebackFlag,
                        help=f"on an error, show the full Python traceback instead of one line (or set {DEBUG_VARIABLE}=1)")
    return parser


DEVICE_FORM = "auto, cpu, cuda or cuda:N"


def device_name(text: str) -> str:
    """An argparse type: `text` if it is auto, cpu, cuda or cuda:N (N a visible CUDA device's index, counted
    among those CUDA_VISIBLE_DEVICES leaves), else an error naming the accepted forms. Whether this machine has
    that device is `pig.config.resolve_device`'s check, when the stage starts."""
    value = text.strip().lower()
    if not re.fullmatch(r"auto|cpu|cuda(:\d+)?", value):
        raise argparse.ArgumentTypeError(f"{text!r}: expected {DEVICE_FORM}")
    return value


def add_device_argument(parser: argparse.ArgumentParser, default: str | None = "auto",
                        default_note: str = "auto: CUDA when available, else the CPU") -> argparse.ArgumentParser:
    """Add `--device auto|cpu|cuda|cuda:N` (`default`; None: the stage takes it from its preset, `default_note`)."""
    parser.add_argument("--device", type=device_name, default=default, metavar="auto|cpu|cuda|cuda:N",
                        help=f"where to compute: {DEVICE_FORM} (default: {default_note})")
    return parser


class _DeprecatedProfile(argparse.Action):
    """`--profile`, the old name of `--preset` (renamed apart from Snakemake's profiles): works, with a note."""

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"{parser.prog}: note: --profile is deprecated, use --preset (compute presets are in config/presets/)",
              file=sys.stderr)
        setattr(namespace, self.dest, values)


def add_preset_argument(parser: argparse.ArgumentParser, reads: str) -> argparse.ArgumentParser:
    """Add `--preset NAME|PATH` (`reads`: what the stage takes from it) and its deprecated alias `--profile`."""
    parser.add_argument("--preset", default=DEFAULT_PRESET,
                        help=f"compute preset: a name in config/presets/ or a YAML path; {reads} (default: {DEFAULT_PRESET})")
    parser.add_argument("--profile", dest="preset", action=_DeprecatedProfile, help=argparse.SUPPRESS)
    return parser


def traceback_requested() -> bool:
    return _traceback_requested or os.environ.get(DEBUG_VARIABLE, "") not in ("", "0")


def error_line(err: Exception) -> str:
    """The one-line description of `err` that `run_cli` prints after `<stage>: error: `."""
    sentence = isinstance(err, KeyError) and len(err.args) == 1 and isinstance(err.args[0], str) and " " in err.args[0]
    message = re.sub(r"\s*\n\s*", " ", (err.args[0] if sentence else str(err)).strip())
    if sentence or isinstance(err, (ValueError, OSError)):
        return message or type(err).__name__
    described = f"{type(err).__name__}: {message}" if message else type(err).__name__
    return f"{described} {TRACEBACK_HINT}"


def run_cli(main: Callable[[list[str] | None], int | None], argv: list[str] | None = None) -> int:
    """Run `main(argv)` and return its exit status; on an exception print one error line and return 1. In a workflow
    job the process ends with the job's shell (pig.job_lifetime)."""
    global _traceback_requested
    _traceback_requested = False
    end_with_parent()
    try:
        return main(argv) or 0
    except Exception as err:
        if traceback_requested():
            raise
        print(f"{Path(main.__code__.co_filename).stem}: error: {error_line(err)}", file=sys.stderr)
        return 1

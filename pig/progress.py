"""Progress bars for a terminal and for a log file alike.

On a terminal a bar redraws as tqdm does by default; written to anything else (a Snakemake rule's log, a
cluster job's output file) it writes at most one update every LOG_INTERVAL_S seconds, plus its first and last.
`set_quiet(True)` (a stage's `--quiet`) turns every bar off.
"""
from __future__ import annotations

import sys

from tqdm import tqdm

LOG_INTERVAL_S = 30.0

# Set by the stages' `--quiet` (pig._cli): no bar, and no progress line of the fit.
_quiet = False


def set_quiet(quiet: bool) -> None:
    global _quiet
    _quiet = bool(quiet)


def quiet() -> bool:
    return _quiet


def _is_terminal(stream) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


def progress_bar(iterable=None, **kwargs) -> tqdm:
    """A tqdm bar over `iterable` (keyword arguments as tqdm's) that writes to a non-terminal at most every 30 s.

    tqdm's `mininterval` bounds the time between updates; its monitor thread also redraws a bar that has not
    been redrawn for `maxinterval` (10 s by default), so both are raised. Callers set `refresh=False` on
    `set_postfix`, which would otherwise redraw at once.
    """
    if _quiet:
        kwargs["disable"] = True
    if not _is_terminal(kwargs.get("file") or sys.stderr):
        kwargs.setdefault("mininterval", LOG_INTERVAL_S)
        kwargs.setdefault("maxinterval", max(LOG_INTERVAL_S, kwargs["mininterval"]))
    return tqdm(iterable, **kwargs)

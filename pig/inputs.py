"""Input files a read can finish: a regular file, never a FIFO (whose read waits for a writer forever) or a
device such as /dev/zero (whose read never ends); file handling, no paper equation.
"""
from __future__ import annotations

import os
import stat
from pathlib import Path

_KINDS = ((stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"), (stat.S_ISDIR, "a folder"))


def require_regular_file(path: str | Path, error: type[Exception], expected: str) -> None:
    """`error` naming `path` unless it is, or links to, a regular file; a missing file raises FileNotFoundError
    for the caller to word. Checked by stat, which never opens the file (opening a FIFO blocks)."""
    mode = os.stat(path).st_mode
    if stat.S_ISREG(mode):
        return
    kind = next((name for test, name in _KINDS if test(mode)), "not a regular file")
    target = os.path.realpath(path)
    via = f", reached through a link to {target}" if target != os.path.abspath(path) else ""
    raise error(f"{path}: is {kind}{via}, not a regular file; expected {expected}")

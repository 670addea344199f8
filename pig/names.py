"""Names that become parts of paths (camera, subject, dataset, variant, sequence ids): one safe path component each.

A camera id `../../victim` or `/home/user` in a capture file would otherwise send a stage's writes, and its
clean-up of hidden files, outside its folders. Snakemake reads two kinds of syntax in a rule's paths: `{name}` is a
wildcard and `<name>` a path variable (`<logs>`, `<results>`, ... expand to folders), so a subject `<logs>` would
silently become `logs`, another subject's raw folder and results. Names also become parts of longer file names
(`{dataset}_ablation.html` and its temporary), so their length is bounded below the file systems' 255 bytes. Readers
check each name where they read it, before anything is written.
"""
from __future__ import annotations

import unicodedata

NAME_MAX = 255  # bytes of one path component on Linux, macOS and Windows file systems
# The longest file name the workflow and its stages build from one name: the tables stage's temporary of a
# dataset's ablation page, `.{dataset}_ablation.{pid}.{random}.tmp.html` (pig._io; a Linux pid has at most 7
# digits, pid_max <= 2**22; the random part 8 hex digits). tests/test_safe_names.py checks this against every path of
# the workflow's rules.
LONGEST_ADDITION = len(".") + len("_ablation") + len(".4194304.01234567.tmp.html")
NAME_BYTES = NAME_MAX - LONGEST_ADDITION  # 219
# Snakemake's syntax in a path: `{wildcard}` and `<pathvar>` (snakemake.io, snakemake.pathvars).
SNAKEMAKE_SYNTAX = "{}<>"
# Unicode's bidirectional formatting characters: they make a name display as another (`abc\u202efed` shows as
# `abcdef`); C0, DEL and C1 controls are Unicode category Cc.
BIDI_CONTROLS = {"\u061c", "\u200e", "\u200f", *map(chr, range(0x202A, 0x202F)), *map(chr, range(0x2066, 0x206A))}


class UnsafeName(ValueError):
    """A name read from a file or the command line is not a safe single path component."""


def snakemake_syntax(value: str) -> str | None:
    """What in `value` Snakemake would read as syntax in a rule's path (`{`, `}`, `<`, `>`), for a message; None if
    nothing."""
    syntax = sorted({char for char in value if char in SNAKEMAKE_SYNTAX})
    if not syntax:
        return None
    return (f"contains {' '.join(map(repr, syntax))}, which Snakemake reads in a path ({{wildcard}} and "
            "<path variable>, e.g. <logs> becomes logs)")


def _problem(value: str) -> str | None:
    if not value:
        return "is empty"
    if "/" in value or "\\" in value:
        return "contains a path separator"
    if any(unicodedata.category(char) == "Cc" for char in value):
        return "contains a control character"
    if any(char in BIDI_CONTROLS for char in value):
        return "contains a bidirectional formatting character (it would display as another name)"
    if value.startswith("."):
        return "starts with '.' (a hidden name, or a step up the folder tree)"
    if snakemake_syntax(value):
        return snakemake_syntax(value)
    size = len(value.encode("utf-8", "surrogateescape"))
    if size > NAME_BYTES:
        return (f"is {size} bytes long, more than {NAME_BYTES} (the workflow builds file names up to "
                f"{LONGEST_ADDITION} bytes longer from a name, and a file name holds at most {NAME_MAX})")
    return None


def safe_name(value, what: str, where: str, error: type[ValueError] = UnsafeName) -> str:
    """`value` if it is a safe single path component, else `error` naming `where` (the file or option it came
    from), `what` it is ("camera id", "subject", ...) and the value; `error` is the reader's own error class.

    Safe: a non-empty string of at most NAME_BYTES bytes without a path separator (`/`, `\\`), control character
    (C0, DEL, C1), bidirectional formatting character or Snakemake path syntax (`{`, `}`, `<`, `>`), that is not
    `.` or `..` and does not start with `.` (hidden names are the stages' temporaries)."""
    if not isinstance(value, str):
        raise error(f"{where}: {what} {value!r} must be a string (a file or folder name)")
    problem = _problem(value)
    if problem is not None:
        # A path is shown whole, so that the user finds it in the file; an over-long name by its start.
        long = len(value.encode("utf-8", "surrogateescape")) > NAME_BYTES
        limit = 80 if long else 4 * NAME_MAX
        shown = repr(value) if len(value) <= limit else repr(value[:limit - 3]) + "..."
        raise error(f"{where}: {what} {shown} {problem}; it becomes a file or folder name, so it must be "
                    "one plain path component (letters, digits, '_', '-', ...)")
    return value

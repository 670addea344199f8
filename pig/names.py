"""Names that become parts of paths (camera, subject, dataset, variant, sequence ids): one safe path component each.

A camera id `../../victim` or `/home/user` in a capture file would otherwise send a stage's writes, and its
clean-up of hidden files, outside its folders. Readers check each name where they read it, before anything is written.
"""
from __future__ import annotations

NAME_MAX = 255  # bytes of one path component on Linux, macOS and Windows file systems


class UnsafeName(ValueError):
    """A name read from a file or the command line is not a safe single path component."""


def safe_name(value, what: str, where: str, error: type[ValueError] = UnsafeName) -> str:
    """`value` if it is a safe single path component, else `error` naming `where` (the file or option it came
    from), `what` it is ("camera id", "subject", ...) and the value; `error` is the reader's own error class.

    Safe: a non-empty string of at most NAME_MAX bytes without a path separator (`/`, `\\`), NUL or other control
    character, that is not `.` or `..` and does not start with `.` (hidden names are the stages' temporaries)."""
    if not isinstance(value, str):
        raise error(f"{where}: {what} {value!r} must be a string (a file or folder name)")
    problem = None
    if not value:
        problem = "is empty"
    elif "/" in value or "\\" in value:
        problem = "contains a path separator"
    elif any(ord(char) < 32 or ord(char) == 127 for char in value):
        problem = "contains a control character"
    elif value.startswith("."):
        problem = "starts with '.' (a hidden name, or a step up the folder tree)"
    elif len(value.encode("utf-8", "surrogateescape")) > NAME_MAX:
        problem = f"is longer than {NAME_MAX} bytes"
    if problem is not None:
        # A path is shown whole, so that the user finds it in the file; an over-long name by its start.
        limit = 80 if len(value.encode("utf-8", "surrogateescape")) > NAME_MAX else 4 * NAME_MAX
        shown = repr(value) if len(value) <= limit else repr(value[:limit - 3]) + "..."
        raise error(f"{where}: {what} {shown} {problem}; it becomes a file or folder name, so it must be "
                    "one plain path component (letters, digits, '_', '-', ...)")
    return value

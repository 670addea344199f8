"""The `test` compute preset with overrides, written where a test's fit reads it."""
from pathlib import Path

from pig.config import derive_preset


def write_test_preset(folder: Path, avatar: dict | None = None, precond: dict | None = None, **fit) -> str:
    """`folder`/preset.yaml: the `test` preset with `fit`, `avatar` and `precond` keys overridden; its path."""
    return str(derive_preset(Path(folder) / "preset.yaml", "test", fit=fit, avatar=avatar or {}, precond=precond or {}))

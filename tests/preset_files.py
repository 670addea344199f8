"""The `test` compute preset with overrides, written where a test's fit reads it."""
from pathlib import Path

import yaml

from pig.config import load_preset


def write_test_preset(folder: Path, avatar: dict | None = None, precond: dict | None = None, **fit) -> str:
    """`folder`/preset.yaml: the `test` preset with `fit`, `avatar` and `precond` keys overridden; its path."""
    preset = load_preset("test")
    preset.pop("_path")
    preset["fit"].update(fit)
    preset["avatar"].update(avatar or {})
    preset["precond"].update(precond or {})
    path = Path(folder) / "preset.yaml"
    path.write_text(yaml.safe_dump(preset))
    return str(path)

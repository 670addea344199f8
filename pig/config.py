"""Typed configuration: compute presets are YAML files whose sections load into dataclasses.

Each module owns the dataclass of its section; `load_section` fills it from a preset, rejecting
unknown keys and wrong types with the file and key named, so a typo never silently uses a default.
YAML numbers follow YAML 1.2 (`1e8` and `1.0e8` are floats) rather than PyYAML's YAML 1.1, and digit strings
with a leading zero (`0165_01`, `0206`) stay strings, as sequence and camera ids do. A field annotated with
`Bounds` (`Annotated[int, Bounds(gt=0)]`) is range-checked on load, NaN and infinities refused; a document
whose aliases expand beyond `MAX_YAML_NODES` values (a "billion laughs" file) is refused before it is built.
"""
from __future__ import annotations

import dataclasses
import math
import re
import types
import typing
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import yaml

from pig.inputs import require_regular_file

if TYPE_CHECKING:
    import torch

REPO_ROOT = Path(__file__).resolve().parent.parent
DEFAULT_PRESET = "cpu-demo"  # config/presets/cpu-demo.yaml: the whole default target on two CPU cores in minutes

T = TypeVar("T")
MAX_YAML_NODES = 100_000  # values of a YAML document with its aliases expanded; a preset holds a few hundred


class ConfigError(ValueError):
    """A configuration file or value is not what the pipeline expects."""


@dataclasses.dataclass(frozen=True)
class Bounds:
    """The range of a numeric config field, for `Annotated[int, Bounds(gt=0)]`; NaN and infinities never pass."""

    gt: float | None = None
    ge: float | None = None
    le: float | None = None

    def check(self, value: float, where: str) -> None:
        ok = math.isfinite(value) and (self.gt is None or value > self.gt) and (self.ge is None or value >= self.ge) \
            and (self.le is None or value <= self.le)
        if not ok:
            wanted = [f"{op} {limit:,}" for op, limit in (("above", self.gt), ("at least", self.ge),
                                                          ("at most", self.le)) if limit is not None]
            kind = "an integer" if isinstance(value, int) else "a finite number"
            raise ConfigError(f"{where}: expected {kind} {' and '.join(wanted)}, found {value!r}")


class _Loader(yaml.SafeLoader):
    """SafeLoader whose implicit ints and floats are YAML 1.2's, except that a leading zero keeps digits a string.

    PyYAML resolves YAML 1.1, where `1e8` and `1.0e8` are strings (the exponent needs a dot and a sign), `0165`
    is octal 117, `0165_01` is 7489, `1_000` is 1000 and `1:30` is 90; here the last four are strings.
    The composed document's size with aliases expanded is bounded (`MAX_YAML_NODES`).
    """

    def compose_document(self):
        node = super().compose_document()
        size = _expanded_size(node, {})
        if size > MAX_YAML_NODES:
            raise ConfigError(f"YAML aliases expand the document to {size:,} values, more than the "
                              f"{MAX_YAML_NODES:,} allowed (an alias bomb?); refused")
        return node


def _expanded_size(node: yaml.Node, sizes: dict[int, int]) -> int:
    """Values in `node` with every alias expanded, counted once per node (linear time); a recursive alias
    counts once."""
    if id(node) not in sizes:
        sizes[id(node)] = 1
        if isinstance(node, yaml.SequenceNode):
            sizes[id(node)] = 1 + sum(_expanded_size(child, sizes) for child in node.value)
        elif isinstance(node, yaml.MappingNode):
            sizes[id(node)] = 1 + sum(_expanded_size(k, sizes) + _expanded_size(v, sizes) for k, v in node.value)
    return sizes[id(node)]


_INT, _FLOAT = "tag:yaml.org,2002:int", "tag:yaml.org,2002:float"
_Loader.yaml_implicit_resolvers = {
    first: [(tag, regexp) for tag, regexp in resolvers if tag not in (_INT, _FLOAT)]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
_Loader.add_implicit_resolver(_INT, re.compile(r"^(?:[-+]?(?:0|[1-9][0-9]*)|0x[0-9a-fA-F]+|0o[0-7]+)$"),
                              list("-+0123456789"))
_Loader.add_implicit_resolver(_FLOAT, re.compile(r"""^(?:[-+]?(?:[0-9]+\.[0-9]*|\.[0-9]+)(?:[eE][-+]?[0-9]+)?
    |[-+]?[0-9]+[eE][-+]?[0-9]+
    |[-+]?\.(?:inf|Inf|INF)
    |\.(?:nan|NaN|NAN))$""", re.X), list("-+0123456789."))


def config_dirs(kind: str) -> list[Path]:
    """The existing `config/<kind>/` folders where a named file (a preset, a dataset) is sought, in order.

    First the working directory's, where the workflow runs every rule (locally and on cluster nodes), so that a
    non-editable install (`pip install .`, a Snakemake conda environment) finds the checkout's files; then the
    one beside this package, which an editable install finds from anywhere.
    """
    folders = dict.fromkeys(folder.resolve() for folder in (Path.cwd() / "config" / kind, REPO_ROOT / "config" / kind))
    return [folder for folder in folders if folder.is_dir()]


def named_config(kind: str, name: str) -> Path:
    """`config/<kind>/<name>.yaml` from the first of `config_dirs(kind)` that has it."""
    folders = config_dirs(kind)
    for folder in folders:
        if (folder / f"{name}.yaml").is_file():
            return folder / f"{name}.yaml"
    singular = kind.rstrip("s")
    if not folders:
        raise ConfigError(f"unknown {singular} {name!r}: no config/{kind}/ in the working directory {Path.cwd()} or "
                          f"beside the package ({REPO_ROOT}); run from the pig checkout or give a path to a .yaml file")
    known = sorted({path.stem for folder in folders for path in folder.glob("*.yaml")})
    where = " and ".join(str(folder) for folder in folders)
    raise ConfigError(f"unknown {singular} {name!r}: expected one of {known} (in {where}) or a path to a .yaml file")


def preset_path(name_or_path: str | Path) -> Path:
    """Resolve a preset name (`cpu-demo`) or a path to a preset YAML file."""
    candidate = Path(name_or_path)
    if candidate.suffix in (".yaml", ".yml"):
        if not candidate.exists():
            raise ConfigError(f"preset file {candidate} does not exist")
        return candidate
    return named_config("presets", str(name_or_path))


def parse_yaml(text: str) -> Any:
    """Parse YAML text safely (no tags that construct objects) with YAML 1.2 numbers."""
    return yaml.load(text, Loader=_Loader)


def load_yaml(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    try:
        require_regular_file(path, ConfigError, "a YAML file")
        data = parse_yaml(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{path}: file not found") from None
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: not valid YAML: {err}") from None
    except ConfigError as err:  # the loader's refusal does not know the file
        if str(err).startswith(f"{path}:"):
            raise
        raise ConfigError(f"{path}: {err}") from None
    except RecursionError:
        raise ConfigError(f"{path}: values nested too deeply to read (thousands of levels); refused") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level, found {type(data).__name__}")
    return data


def load_preset(name_or_path: str | Path) -> dict[str, Any]:
    """The raw preset mapping, with its source path under the key `_path`."""
    path = preset_path(name_or_path)
    data = load_yaml(path)
    data["_path"] = str(path)
    return data


def derive_preset(path: str | Path, base: str | Path, **sections: dict[str, Any]) -> Path:
    """`base` (a preset name or path) with the keys of each section given replaced (`fit={"iterations": 3}`; a
    section it lacks is added), written to `path` as YAML for a stage or fit to read; `path`."""
    preset = load_preset(base)
    preset.pop("_path")
    for section, values in sections.items():
        preset.setdefault(section, {}).update(values)
    path = Path(path)
    path.write_text(yaml.safe_dump(preset))
    return path


def resolve_device(name: str, source: str = "device") -> torch.device:
    """A torch device from a `--device` or preset value (`source` names it): "auto" is CUDA when available.

    A CUDA device that this machine cannot provide is refused here, before any work, in one line instead of
    torch's assertion from deep inside the first transfer.
    """
    import torch  # here, not at the top: the workflow's rules import this module and need no torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ConfigError(f"{source} {name!r}: expected auto, cpu, cuda or cuda:N") from None
    if device.type == "cuda":
        if not torch.cuda.is_available():
            why = (f"this torch {torch.__version__} is built without CUDA" if torch.version.cuda is None
                   else "no CUDA GPU is visible")
            raise ConfigError(f"{source} {name!r}: CUDA is not available ({why}); use cpu")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise ConfigError(f"{source} {name!r}: only {torch.cuda.device_count()} CUDA device(s) are visible")
    return device


def load_section(preset: dict[str, Any], section: str, cls: type[T], overrides: dict[str, Any] | None = None) -> T:
    """Build dataclass `cls` from `preset[section]` (missing section -> all defaults)."""
    where = f"{preset.get('_path', '<preset>')}: section '{section}'"
    values = dict(preset.get(section) or {})
    values.update(overrides or {})
    return from_dict(cls, values, where)


def from_dict(cls: type[T], values: dict[str, Any], where: str = "config") -> T:
    """Strictly convert a mapping into dataclass `cls` (nested dataclasses included)."""
    if not isinstance(values, dict):
        raise ConfigError(f"{where}: expected a mapping, found {type(values).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - set(fields))
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown}; expected some of {sorted(fields)}")
    hints = typing.get_type_hints(cls, include_extras=True)
    kwargs = {name: _coerce(hints[name], value, f"{where}.{name}") for name, value in values.items()}
    return cls(**kwargs)


def _coerce(hint: Any, value: Any, where: str) -> Any:
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if hint is Any:
        return value
    if origin is typing.Annotated:
        value = _coerce(args[0], value, where)
        for bounds in (a for a in hint.__metadata__ if isinstance(a, Bounds)):
            if value is not None:
                bounds.check(value, where)
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for option in (a for a in args if a is not type(None)):
            try:
                return _coerce(option, value, where)
            except ConfigError as err:
                errors.append(str(err))
        raise ConfigError("; ".join(errors))
    if origin is typing.Literal:
        if value not in args:
            raise ConfigError(f"{where}: expected one of {list(args)}, found {value!r}")
        return value
    if dataclasses.is_dataclass(hint):
        return from_dict(hint, value, where)
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, found {value!r}")
        item = args[0] if args else Any
        items = [_coerce(item, v, f"{where}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a mapping, found {value!r}")
        return dict(value)
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, found {_found(value)}")
        return float(value)
    if hint is int:
        # An integral float is exact as an int: `iterations: 1e5` means 100000.
        if isinstance(value, float) and value.is_integer():
            return int(value)
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, found {_found(value)}")
        return value
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true or false, found {value!r}")
        return value
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, found {value!r}")
        return value
    return value


def _found(value: Any) -> str:
    """How a wrong value reads in an error: a quoted number gets a hint, as it is the common slip."""
    if isinstance(value, str):
        try:
            float(value)
        except ValueError:
            return f"the string {value!r}"
        return f"the string {value!r} (a number in quotes: write it without quotes)"
    return repr(value)

"""YAML loading (YAML 1.2 numbers, ids with leading zeros stay strings) and typed sections of pig.config."""
from __future__ import annotations

import math
import re
from dataclasses import dataclass

import pytest

from pig.config import ConfigError, derive_preset, load_preset, load_section, load_yaml


@dataclass
class Section:
    weight: float = 1.0
    iterations: int = 10
    name: str = ""


def _yaml(tmp_path, text: str):
    path = tmp_path / "preset.yaml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("text, value", [
    ("1e8", 1e8), ("1.0e8", 1e8), ("1.0e+8", 1e8), ("-3E-2", -0.03), ("+2.5e-3", 2.5e-3), (".5", 0.5), ("1.", 1.0),
    ("-.inf", -math.inf), ("12", 12), ("-7", -7), ("0", 0), ("0x1F", 31),
    ("'1e8'", "1e8"), ('"2.5"', "2.5"), ("0165_01", "0165_01"), ("0165", "0165"), ("012", "012"),
    ("1_000", "1_000"), ("1:30", "1:30"), ("1e", "1e"), ("1.2.3", "1.2.3"), ("e5", "e5"),
])
def test_yaml_numbers_are_yaml_1_2_and_ids_stay_strings(tmp_path, text, value):
    loaded = load_yaml(_yaml(tmp_path, f"key: {text}\n"))["key"]
    assert type(loaded) is type(value) and loaded == value


def test_yaml_nan_and_nested_values(tmp_path):
    data = load_yaml(_yaml(tmp_path, "a: .nan\nb: [1e-3, '0206_03', 0206_03]\nc: {lambda: 1.0e8, flag: true, none: null}\n"))
    assert math.isnan(data["a"])
    assert data["b"] == [1e-3, "0206_03", "0206_03"]
    assert data["c"] == {"lambda": 1e8, "flag": True, "none": None}


def test_yaml_loading_runs_no_code(tmp_path):
    with pytest.raises(ConfigError, match=r"preset\.yaml: not valid YAML: could not determine a constructor"):
        load_yaml(_yaml(tmp_path, "x: !!python/object/apply:os.system ['true']\n"))


def test_section_takes_exponent_numbers(tmp_path):
    preset = load_preset(_yaml(tmp_path, "fit:\n  weight: 1.0e8\n  iterations: 1e5\n  name: '1e8'\n"))
    section = load_section(preset, "fit", Section)
    assert section == Section(weight=1e8, iterations=100_000, name="1e8")
    assert type(section.weight) is float and type(section.iterations) is int


@pytest.mark.parametrize("text, message", [
    ("weight: '1.0e8'", r"section 'fit'\.weight: expected a number, found the string '1\.0e8' \(a number in quotes: write it without quotes\)$"),
    ("iterations: '100'", r"section 'fit'\.iterations: expected an integer, found the string '100' \(a number in quotes"),
    ("iterations: 2.5", r"section 'fit'\.iterations: expected an integer, found 2\.5$"),
    ("weight: heavy", r"section 'fit'\.weight: expected a number, found the string 'heavy'$"),
    ("weight: true", r"section 'fit'\.weight: expected a number, found True$"),
])
def test_a_wrong_number_names_the_file_and_key(tmp_path, text, message):
    path = _yaml(tmp_path, f"fit:\n  {text}\n")
    with pytest.raises(ConfigError, match=f"^{re.escape(str(path))}: {message}"):
        load_section(load_preset(path), "fit", Section)


def test_written_preset_replaces_only_the_keys_given(tmp_path):
    from pig.avatar.training import FitConfig

    path = derive_preset(tmp_path / "p.yaml", "test", fit={"iterations": 7, "weight_lpips": 1e-5},
                         extra={"subjects": ["0165_01"]})
    written, base = load_preset(path), load_preset("test")
    assert "_path" not in load_yaml(path)  # where it came from is not a key of the preset
    cfg = load_section(written, "fit", FitConfig)
    assert (cfg.iterations, cfg.weight_lpips) == (7, 1e-5)
    assert {k: v for k, v in written["fit"].items() if k not in ("iterations", "weight_lpips")} == \
        {k: v for k, v in base["fit"].items() if k not in ("iterations", "weight_lpips")}
    assert all(written[s] == base[s] for s in base if s not in ("fit", "_path"))
    assert written["extra"] == {"subjects": ["0165_01"]}  # a leading-zero id stays a string
    assert load_preset("test") == base  # the named preset itself untouched


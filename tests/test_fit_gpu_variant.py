"""benchmarks/fit_gpu.py's `NAME:section.key=value,...` overrides, as the benchmarks and GPU holds pass them."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from fit_gpu import parse_variant  # noqa: E402


def test_values_are_yaml_and_a_list_keeps_its_commas():
    name, overrides = parse_variant("l5:field.resolutions=[8,16,24, 32,40],fit.iterations=1800,precond.adam_eps=1.0e-15,"
                                    "precond.form=filter,fit.shard_solves=true")
    assert name == "l5"
    assert overrides == {"field": {"resolutions": [8, 16, 24, 32, 40]},
                         "fit": {"iterations": 1800, "shard_solves": True},
                         "precond": {"adam_eps": 1e-15, "form": "filter"}}


def test_a_name_alone_overrides_nothing():
    assert parse_variant("pig:") == ("pig", {})
    assert parse_variant("pig") == ("pig", {})

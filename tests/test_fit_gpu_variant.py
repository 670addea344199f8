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


def test_cpu_default_candidate_names_pick_the_presets_method_variant():
    """benchmarks/cpu_default.py fits a candidate as the longest `_`-bounded prefix of its name that is a variant."""
    from cpu_default import method_variant

    from pig.config import load_preset

    variants = load_preset("cpu-demo")["variants"]
    assert method_variant("no_precond_eps", variants) == "no_precond"
    assert method_variant("no_precond", variants) == "no_precond"
    assert method_variant("noise_0.1_b", variants) == "noise_0.1"
    assert method_variant("pig_uniform", variants) == "pig"
    assert method_variant("lod_1of1", variants) == "lod_1of1"
    assert method_variant("default", variants) == method_variant("no", variants) == "pig"


def test_capture_only_makes_the_subject_without_a_gpu(tmp_path, monkeypatch):
    """`--capture-only` generates and preprocesses the subject, which needs no GPU (a CPU machine prepares it)."""
    import torch
    from fit_gpu import main

    from pig.data.capture import Capture

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert main(["--workdir", str(tmp_path), "--preset", "test", "--frames", "2", "--cameras", "3", "--capture-only"]) == 0
    capture = Capture.load(tmp_path / "capture", cache_mb=0)
    assert len(capture.cameras) == 3
    assert main(["--workdir", str(tmp_path), "--preset", "test", "--frames", "2", "--reuse-capture"]) == 1  # a fit does


def test_an_override_wins_over_the_variants_own_key():
    """`no_precond:precond.optimizer=uniform_adam` fits no_precond with uniform Adam: the variant's own
    `precond.optimizer: adam` does not undo it (issue 38's levers go on every variant)."""
    from fit_gpu import variant_preset

    from pig.avatar.variants import variant_overrides
    from pig.config import load_preset, load_section
    from pig.field.precondition import PrecondConfig

    profile = load_preset("paper")
    for spec, form, optimizer, eps in (("no_precond:precond.optimizer=uniform_adam,precond.adam_eps=1.0e-15", "none",
                                        "uniform_adam", 1e-15),
                                       ("pig:precond.form=filter,precond.optimizer=uniform_adam", "filter", "uniform_adam", 1e-8),
                                       ("no_precond:precond.adam_eps=1.0e-15", "none", "adam", 1e-15)):
        name, overrides = parse_variant(spec)
        preset = variant_preset(profile, name, overrides)
        cfg = load_section(preset, "precond", PrecondConfig, variant_overrides(preset, name).get("precond"))
        assert (cfg.form, cfg.optimizer, cfg.adam_eps) == (form, optimizer, eps), spec
    assert profile["variants"]["no_precond"]["precond"]["optimizer"] == "adam"  # the caller's preset untouched


def test_a_key_given_again_later_wins():
    """equal_time_hold.sh writes `NAME:$RATES,LEVER`: a lever's fit.lr_decoders after the rates' replaces it (hold
    E1's paper rates), and the rates' other keys stay."""
    rates = "fit.lr_decoders=3.0e-3,precond.grid_lr=3.0e-2,fit.weight_lpips=0"
    name, overrides = parse_variant(f"pig:{rates},fit.lr_decoders=1.0e-3,precond.grid_lr=1.0e-2")
    assert overrides == {"fit": {"lr_decoders": 1e-3, "weight_lpips": 0}, "precond": {"grid_lr": 1e-2}}

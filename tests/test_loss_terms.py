"""The LPIPS term of Eq. 15 as a fit had it: its record in avatar.pt and checkpoint.pt, the train log's column,
the note in every table row of the fit, the refused resume when it changed; and the seeded random LPIPS that
times the term where the pretrained weights are absent."""
import json
import math
import re

import pandas as pd
import pytest
import torch
import yaml

from pig.avatar.checkpoint import CheckpointError, loss_terms
from pig.avatar.losses import fit_note, lpips_term
from pig.config import ConfigError, derive_preset, load_preset, load_section
from pig.metrics.lpips import LPIPS
from pig.avatar.training import FitConfig

ABSENT_VGG = "fit without the LPIPS term of Eq. 15 (VGG weights absent)"
ABSENT_ALEX = "fit without the LPIPS term of Eq. 15 (AlexNet weights absent)"


@pytest.fixture
def empty_hub(tmp_path, monkeypatch):
    """An empty torch hub cache, so no real weights on this machine leak into the tests."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch_home"))
    monkeypatch.setattr("pig.metrics.weights.lpips_package_weights", lambda: None)
    return tmp_path / "torch_home" / "hub" / "checkpoints"


def _write_weights(net: LPIPS, hub) -> None:
    """`net`'s weights as torchvision's backbone file and the lpips package's linear file, in the hub cache."""
    hub.mkdir(parents=True, exist_ok=True)
    torch.save({f"features.{k}": v for k, v in net.features.state_dict().items()},
               hub / {"alex": "alexnet-owt-7be5be79.pth", "vgg": "vgg16-397923af.pth"}[net.net])
    torch.save({f"lin{k}.model.1.weight": lin.weight for k, lin in enumerate(net.lins)}, hub / f"{net.net}.pth")


# ---- the random LPIPS ----


def test_random_lpips_is_seeded_reads_no_file_and_is_a_distance(monkeypatch):
    def no_lookup(*args):
        raise AssertionError("random LPIPS looked up a weights file")

    monkeypatch.setattr("pig.metrics.lpips.locate", no_lookup)
    torch.manual_seed(1)
    a = LPIPS("vgg", weights="random", seed=3)
    torch.manual_seed(2)  # the global RNG has no say
    b = LPIPS("vgg", weights="random", seed=3)
    other = LPIPS("vgg", weights="random", seed=4)
    assert a.state_dict().keys() == b.state_dict().keys()
    assert all(torch.equal(b.state_dict()[key], value) for key, value in a.state_dict().items())
    assert not torch.equal(a.features[0].weight, other.features[0].weight)
    assert not torch.equal(a.lins[4].weight, other.lins[4].weight)
    for lin in a.lins:  # non-negative, as LPIPS's linear layers; mean 1/C
        assert (lin.weight >= 0).all() and lin.weight.mean().item() == pytest.approx(1 / lin.in_channels, rel=0.15)
    # He-normal, not nn.Conv2d's own init (std 1/sqrt(3 fan_in), 2.4x smaller), with zero biases.
    last = a.features[28]
    assert last.weight.std().item() == pytest.approx(math.sqrt(2 / (512 * 9)), rel=0.01)
    assert not last.bias.any() and not any(p.requires_grad for p in a.parameters())

    x, y = torch.rand(2, 3, 24, 20, generator=torch.Generator().manual_seed(0)).unbind(0)
    x, y = x[None], y[None]
    distance = a(x, y)
    assert torch.isfinite(distance).all() and (distance > 0).all()
    assert torch.equal(a(x, x), torch.zeros(1))
    assert torch.equal(distance, b(x, y))


def test_random_lpips_gradient_matches_finite_differences():
    """float64, central differences along a random direction of the rendered image."""
    net = LPIPS("vgg", weights="random", seed=0).double()
    generator = torch.Generator().manual_seed(1)
    x = torch.rand(1, 3, 16, 18, generator=generator, dtype=torch.float64)
    y = torch.rand(1, 3, 16, 18, generator=generator, dtype=torch.float64)
    direction = torch.randn(x.shape, generator=generator, dtype=torch.float64)
    x.requires_grad_()
    net(x, y).sum().backward()
    assert x.grad.abs().sum() > 0
    h = 1e-6
    with torch.no_grad():
        numeric = (net(x + h * direction, y) - net(x - h * direction, y)).item() / (2 * h)
    assert (x.grad * direction).sum().item() == pytest.approx(numeric, rel=1e-5)


# ---- the record and its note ----


def test_lpips_term_records_each_state_and_its_note(tmp_path, empty_hub, capsys):
    net, record = lpips_term(FitConfig())
    assert net is None and {k: v for k, v in record.items() if k != "detail"} == {"weight": 2.0, "net": "vgg",
                                                                                 "state": "weights absent"}
    assert record["detail"].startswith("LPIPS vgg backbone: weights file vgg16-397923af.pth not found (searched ")
    assert capsys.readouterr().err == f"fit: LPIPS term left out of the loss ({record['detail']})\n"
    assert fit_note(record) == ABSENT_VGG
    assert lpips_term(FitConfig(), notify=False)[1] == record  # a data-parallel fit's other ranks: the same, silent
    assert capsys.readouterr().err == ""

    net, record = lpips_term(FitConfig(weight_lpips=0.0))
    assert net is None and record == {"weight": 0.0, "net": "vgg", "state": "weight 0", "detail": ""}
    assert fit_note(record) == "fit without the LPIPS term (weight 0)"

    net, record = lpips_term(FitConfig(lpips_net="alex", lpips_weights="random", seed=5))
    assert record == {"weight": 2.0, "net": "alex", "state": "random weights", "detail": ""}
    reference = LPIPS("alex", weights="random", seed=5)
    assert all(torch.equal(net.state_dict()[key], value) for key, value in reference.state_dict().items())
    assert "randomly initialised alex weights (seed 5; for timing only)" in capsys.readouterr().err
    assert fit_note(record) == "fit with a randomly initialised LPIPS (timing only)"
    assert lpips_term(FitConfig(lpips_net="alex", lpips_weights="random", seed=5), notify=False)[1] == record
    assert capsys.readouterr().err == ""

    _write_weights(reference, empty_hub)  # pretrained weights on disk: the paper's term
    net, record = lpips_term(FitConfig(lpips_net="alex"))
    assert record == {"weight": 2.0, "net": "alex", "state": "on", "detail": ""} and fit_note(record) == ""
    assert all(torch.equal(net.state_dict()[key], value) for key, value in reference.state_dict().items())

    assert fit_note({"state": "unknown"}) == ("fit's LPIPS term unknown (avatar.pt written before fits recorded it, "
                                              "re-run the fit)")
    with pytest.raises(ValueError, match="LPIPS term state 'off': expected one of"):
        fit_note({"state": "off"})


def test_lpips_weights_option_is_checked(tmp_path):
    with pytest.raises(ConfigError, match=r"^fit\.lpips_weights must be 'pretrained' or 'random', found 'randm'$"):
        FitConfig(lpips_weights="randm")
    path = tmp_path / "preset.yaml"
    path.write_text(yaml.safe_dump({"fit": {"lpips_weights": "randm"}}))
    with pytest.raises(ConfigError, match=r"preset\.yaml: section 'fit'\.lpips_weights: expected one of "
                                          r"\['pretrained', 'random'\], found 'randm'"):
        load_section(load_preset(path), "fit", FitConfig)
    with pytest.raises(ConfigError, match="fit.lpips_weights is 'random', which reads no weights file, but "
                                          "fit.lpips_backbone_weights or fit.lpips_linear_weights is set"):
        FitConfig(lpips_weights="random", lpips_linear_weights="vgg.pth")


# ---- through the fit, render, evaluate and tables stages ----


def _preset(tmp_path, **fit) -> str:
    return str(derive_preset(tmp_path / "preset.yaml", "test", fit=fit, avatar={"num_anchors": 300},
                             evaluate={"device": "cpu", "timing_frames": 1}, rasterizer={"backend": "cpu"}))


class _Killed(Exception):
    pass


def _kill_at(at: int):
    def on_iteration(iteration):
        if iteration == at:
            raise _Killed

    return on_iteration


@pytest.mark.slow
def test_fit_without_the_weights_records_it_and_every_table_row_says_so(small_capture, tmp_path, empty_hub, capsys):
    """A fit whose LPIPS weights are absent: the state in checkpoint.pt, avatar.pt and on every log row; a
    resume after the weights appeared is refused; the note reaches the summaries and each table row."""
    from pig.render.api import RasterizerConfig
    from pig.stages.evaluate import EvaluateConfig, evaluate_split
    from pig.avatar.training import fit
    from pig.stages.render import render_split
    from pig.stages.tables import make_tables

    preset = _preset(tmp_path, iterations=3, eval_every=3, checkpoint_minutes=0.0, weight_lpips=2.0, lpips_net="alex")
    variant = tmp_path / "results" / "synthetic" / "subject00" / "pig"
    with pytest.raises(_Killed):
        fit(small_capture, variant, preset, on_iteration=_kill_at(2))
    state = variant / "checkpoint.pt"
    [record] = loss_terms(state).values()
    assert record["state"] == "weights absent" and record["net"] == "alex" and record["weight"] == 2.0
    assert "alexnet-owt-7be5be79.pth not found" in record["detail"]
    assert f"fit: LPIPS term left out of the loss ({record['detail']})" in capsys.readouterr().err

    _write_weights(LPIPS("alex", weights="random"), empty_hub)  # the weights appear before the resume
    written = state.read_bytes()
    with pytest.raises(CheckpointError) as err:
        fit(small_capture, variant, preset)
    assert str(err.value) == (f"{state}: checkpoint of another fit, not resumed: the LPIPS term differs "
                              "('weights absent', now 'on'); delete it to start the fit over, or point --output elsewhere")
    assert state.read_bytes() == written

    for path in empty_hub.iterdir():
        path.unlink()
    avatar = fit(small_capture, variant, preset)
    assert loss_terms(avatar) == {"lpips": record}
    log = pd.read_csv(variant / "train_log.csv")
    assert log["iteration"].tolist() == [0, 1, 2, 3] and (log["lpips_term"] == "weights absent").all()
    assert log["lpips"].isna().all() and log["loss"].iloc[1:].notna().all()

    renders = variant / "renders" / "novel_view"
    cfg = EvaluateConfig(device="cpu", timing_frames=1)
    render_split(avatar, small_capture, "novel_view", renders, cfg, RasterizerConfig(backend="cpu"))
    assert json.loads((renders / "lod1" / "timing.json").read_text())["fit_note"] == ABSENT_ALEX
    evaluate_split(small_capture, renders, "novel_view", variant / "metrics", cfg)
    summaries = [variant / "metrics" / f"novel_view_lod{level}.json" for level in (0, 1)]
    assert [json.loads(p.read_text())["fit_note"] for p in summaries] == [ABSENT_ALEX, ABSENT_ALEX]

    tables = tmp_path / "results" / "tables"
    make_tables("synthetic", summaries, [variant / "train_log.csv"], ["pig"], tables)
    main = pd.read_csv(tables / "synthetic.csv").set_index("variant")
    assert ABSENT_ALEX in main.loc["pig", "notes"].split("; ")
    assert ABSENT_ALEX not in main.loc["blank (black image)", "notes"]
    lod = pd.read_csv(tables / "synthetic_lod.csv")
    assert len(lod) == 2 and all(ABSENT_ALEX in notes.split("; ") for notes in lod["notes"])
    assert re.search(rf"^\d+\. {re.escape(ABSENT_ALEX)}$", (tables / "synthetic.md").read_text(), flags=re.M)  # a footnote

    # Renders of a render stage that did not pass the note on: said so, not left blank.
    timing = renders / "lod0" / "timing.json"
    timing.write_text(json.dumps({k: v for k, v in json.loads(timing.read_text()).items() if k != "fit_note"}))
    evaluate_split(small_capture, renders, "novel_view", variant / "metrics", cfg, [0])
    assert json.loads(summaries[0].read_text())["fit_note"] == (
        "fit's LPIPS term unknown (renders written before the render stage recorded it, re-run render)")


def test_fit_with_random_lpips_trains_with_the_term(small_capture, tmp_path, empty_hub):
    from pig.avatar.training import fit

    preset = _preset(tmp_path, iterations=2, eval_every=2, weight_lpips=2.0, lpips_net="alex", lpips_weights="random")
    avatar = fit(small_capture, tmp_path / "pig", preset)
    assert loss_terms(avatar)["lpips"] == {"weight": 2.0, "net": "alex", "state": "random weights", "detail": ""}
    log = pd.read_csv(tmp_path / "pig" / "train_log.csv")
    assert (log["lpips_term"] == "random weights").all()
    steps = log.iloc[1:]
    assert (steps["lpips"] > 0).all() and steps["loss"].tolist() == pytest.approx(
        (8 * steps["l1"] + 2 * steps["ssim"] + 2 * steps["lpips"]).tolist(), rel=1e-5)

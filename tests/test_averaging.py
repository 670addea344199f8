"""Weight averaging (pig.avatar.averaging): the EMA against its closed form in float64, the swap in and out, its
state, and a fit that evaluates and saves the average (and its last iterate beside it), restarts it where the grid is
re-based, and resumes it."""
import math

import numpy as np
import pytest
import torch

from pig.avatar.averaging import WeightAverage


def _optimizers(rng):
    a = torch.nn.Parameter(torch.from_numpy(rng.normal(size=(3, 4))).float())
    b = torch.nn.Parameter(torch.from_numpy(rng.normal(size=(5,))).float())
    return [a, b], [torch.optim.SGD([a], lr=0.1), torch.optim.Adam([{"params": [b]}])]


def _closed_form(history: list[list[np.ndarray]], decay: float) -> list[np.ndarray]:
    """a_n = decay^(n-1) p_1 + sum_{k=2..n} (1 - decay) decay^(n-k) p_k, in float64."""
    n = len(history)
    weights = [decay ** (n - 1)] + [(1 - decay) * decay ** (n - k) for k in range(2, n + 1)]
    return [sum(w * values[i] for w, values in zip(weights, history)) for i in range(len(history[0]))]


@pytest.mark.parametrize("decay", [1e-9, 0.5, 0.99, 1 - 1e-9])
def test_average_matches_its_closed_form(decay, rng):
    params, optimizers = _optimizers(rng)
    average = WeightAverage(optimizers, decay)
    assert not average.started and average.params == params
    history = []
    for _ in range(7):
        with torch.no_grad():
            for p in params:
                p.copy_(torch.from_numpy(rng.normal(size=p.shape) * 10))
        history.append([p.detach().double().numpy().copy() for p in params])
        average.update()
    expected = _closed_form(history, decay)
    for got, want in zip(average.averages, expected):
        np.testing.assert_allclose(got.double().numpy(), want, rtol=1e-5, atol=1e-5)
    # The extremes: the last iterate, and the first one.
    if decay < 1e-6:
        np.testing.assert_allclose(average.averages[0].numpy(), history[-1][0], atol=1e-5)
    if decay > 1 - 1e-6:
        np.testing.assert_allclose(average.averages[0].numpy(), history[0][0], atol=1e-5)


@pytest.mark.parametrize("decay", [0.0, 1.0, -0.1, math.nan])
def test_decay_outside_the_open_interval_is_refused(decay, rng):
    _, optimizers = _optimizers(rng)
    with pytest.raises(ValueError, match="decay must lie in"):
        WeightAverage(optimizers, decay)


def test_applied_swaps_in_the_average_and_restores_the_weights_even_on_error(rng):
    params, optimizers = _optimizers(rng)
    average = WeightAverage(optimizers, 0.9)
    own = [p.detach().clone() for p in params]
    with average.applied():  # not started: nothing to apply
        assert all(torch.equal(p, o) for p, o in zip(params, own))
    average.update()
    with torch.no_grad():
        for p in params:
            p.add_(1.0)
    average.update()
    iterate = [p.detach().clone() for p in params]
    storage = [p.data_ptr() for p in params]
    with pytest.raises(RuntimeError, match="inside"):
        with average.applied():
            assert all(torch.allclose(p, o + 0.1) for p, o in zip(params, own))  # 0.9 own + 0.1 (own + 1)
            raise RuntimeError("inside")
    assert all(torch.equal(p, i) for p, i in zip(params, iterate))
    assert [p.data_ptr() for p in params] == storage  # copied in place: compiled graphs keep their inputs
    assert all(p.requires_grad for p in params)


def test_restart_and_state_round_trip(rng):
    params, optimizers = _optimizers(rng)
    average = WeightAverage(optimizers, 0.8)
    average.update()
    with torch.no_grad():
        params[0].mul_(3)
    average.update()
    state = average.state_dict()
    other = WeightAverage(optimizers, 0.8)
    other.load_state_dict(state)
    assert other.updates == 2 and all(torch.equal(a, b) for a, b in zip(other.averages, average.averages))
    average.restart()
    assert not average.started and average.updates == 0
    average.update()  # starts again from the weights of now
    assert all(torch.equal(a, p) for a, p in zip(average.averages, params))
    wrong = {"averages": [torch.zeros(2, 2), torch.zeros(5)], "updates": 1}
    with pytest.raises(ValueError, match="shapes"):
        other.load_state_dict(wrong)
    other.load_state_dict({"averages": None, "updates": 0})
    assert not other.started


def _preset(tmp_path, **fit):
    from pig.config import derive_preset

    return str(derive_preset(tmp_path / "preset.yaml", "test", fit=fit, avatar={"num_anchors": 300},
                             precond={"grid_delay": 6}))


class _Killed(Exception):
    pass


@pytest.mark.slow
def test_fit_evaluates_and_saves_the_average_restarts_it_at_the_grid_switch_and_resumes_it(small_capture, tmp_path,
                                                                                          monkeypatch):
    import pandas as pd

    import pig.avatar.training as training
    from pig.avatar.checkpoint import load_avatar

    decay, iterations = 0.7, 14
    # The average starts at iteration 3 (progress 0.2), and restarts where the grid's preconditioning begins (6).
    preset = _preset(tmp_path, iterations=iterations, eval_every=5, checkpoint_minutes=0.0, average_decay=decay,
                     average_start=0.2)
    models, averages, history = [], [], []
    original_build, original_update, original_restart = training.build_avatar, WeightAverage.update, WeightAverage.restart

    def build(spec):
        models.append(original_build(spec))
        return models[-1]

    def update(self):
        averages.append(self)
        history.append([p.detach().double().clone() for p in self.params])
        original_update(self)

    def restart(self):
        history.append("restart")
        original_restart(self)

    monkeypatch.setattr(training, "build_avatar", build)
    monkeypatch.setattr(WeightAverage, "update", update)
    monkeypatch.setattr(WeightAverage, "restart", restart)
    reference = training.fit(small_capture, tmp_path / "full", preset)

    # Updates after iterations 3, 4, 5 (progress >= 0.2), the restart at 6, then updates after 6 ... 13.
    assert len(history) == iterations - 3 + 1 and history[3] == "restart"
    since = history[4:]
    names = {id(p): name for name, p in models[0].named_parameters()}
    trained = [names[id(p)] for p in models[0].parameters() if p.requires_grad]
    order = [names[id(p)] for p in averages[0].params]
    assert sorted(order) == sorted(trained)  # every optimised tensor is averaged
    expected = dict(zip(order, _closed_form([[t.numpy() for t in step] for step in since], decay)))
    saved = torch.load(reference, weights_only=True)["model"]
    last_iterate = dict(models[0].named_parameters())
    differs = 0
    for name, value in expected.items():
        np.testing.assert_allclose(saved[name].double().numpy(), value, rtol=1e-5, atol=1e-6, err_msg=name)
        differs += not torch.allclose(saved[name], last_iterate[name].detach().cpu())
    assert differs > len(expected) // 2  # the file holds the average, not the last iterate
    iterate_file = torch.load(tmp_path / "full" / training.ITERATE_FILE, weights_only=True)["model"]
    assert all(torch.equal(iterate_file[name], value.detach().cpu()) for name, value in last_iterate.items())

    log = pd.read_csv(tmp_path / "full" / "train_log.csv")
    evaluated = log.dropna(subset=["heldout_psnr"])
    assert evaluated["iteration"].tolist() == [0, 5, 10, 14]
    # Before the average starts the iterate is evaluated alone; afterwards both, and they differ.
    assert evaluated["heldout_psnr_iterate"].isna().tolist() == [True, False, False, False]
    late = evaluated.iloc[1:]
    assert (late["heldout_psnr"] != late["heldout_psnr_iterate"]).all()

    # Killed after iteration 9 (3 updates since the restart), resumed: the same file, bit for bit.
    monkeypatch.setattr(WeightAverage, "update", original_update)
    monkeypatch.setattr(WeightAverage, "restart", original_restart)

    def kill_at_9(iteration):
        if iteration == 9:
            raise _Killed

    with pytest.raises(_Killed):
        training.fit(small_capture, tmp_path / "resumed", preset, on_iteration=kill_at_9)
    assert torch.load(tmp_path / "resumed" / "checkpoint.pt", weights_only=True)["average"]["updates"] == 3
    resumed = training.fit(small_capture, tmp_path / "resumed", preset)
    a, b = load_avatar(reference).state_dict(), load_avatar(resumed).state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[key], b[key]) for key in a)
    a, b = (load_avatar(root / training.ITERATE_FILE).state_dict() for root in (tmp_path / "full", tmp_path / "resumed"))
    assert all(torch.equal(a[key], b[key]) for key in a)

    # The average does not feed back into the training: the same fit without it ends at the same iterate, bit for
    # bit (what lets benchmarks/equal_time.py count an averaged fit's iterate as a plain fit).
    plain = training.fit(small_capture, tmp_path / "plain", _preset(tmp_path, iterations=iterations, eval_every=5,
                                                                     checkpoint_minutes=0.0))
    a, b = load_avatar(tmp_path / "full" / training.ITERATE_FILE).state_dict(), load_avatar(plain).state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[key], b[key]) for key in a)

    # A fit without an average in the same folder leaves no iterate of the earlier fit beside its avatar.pt.
    training.fit(small_capture, tmp_path / "full", _preset(tmp_path, iterations=2, eval_every=5), overwrite=True)
    assert not (tmp_path / "full" / training.ITERATE_FILE).exists()


@pytest.mark.slow
def test_fit_gpu_evaluates_the_average_and_its_last_iterate(small_capture, tmp_path):
    # benchmarks/fit_gpu.py --evaluate-iterate: the budget mode's render and evaluate of both files of one averaged
    # fit, on the CPU: each split rendered from its own file (the render manifests' checksums) and scored apart.
    import argparse
    import hashlib
    import json
    import sys
    from pathlib import Path

    from pig.avatar.training import ITERATE_FILE, fit

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from fit_gpu import evaluate_budget_run

    preset = _preset(tmp_path, iterations=8, eval_every=100, checkpoint_minutes=0.0, average_decay=0.5,
                     average_start=0.0)
    fit_dir = tmp_path / "fit"
    fit(small_capture, fit_dir, preset)
    args = argparse.Namespace(workdir=tmp_path / "work", finest_only=True)
    average = evaluate_budget_run(args, "v", fit_dir, Path(preset), small_capture)
    iterate = evaluate_budget_run(args, "v_iterate", fit_dir, Path(preset), small_capture, ITERATE_FILE)
    assert average["iterations"] == iterate["iterations"] == 8
    for split in ("novel_view", "novel_pose"):
        (lod,) = average[split]
        assert average[split][lod]["psnr"] != iterate[split][lod]["psnr"]
    for folder, name in (("renders_v", "avatar.pt"), ("renders_v_iterate", ITERATE_FILE)):
        manifest = json.loads((tmp_path / "work" / folder / "novel_view" / "manifest.json").read_text())
        assert manifest["checkpoint_sha256"] == hashlib.sha256((fit_dir / name).read_bytes()).hexdigest()

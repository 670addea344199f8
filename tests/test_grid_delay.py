"""Delayed and ramped grid preconditioning (precond.grid_delay, precond.grid_ramp): plain grid steps first, then the
Sobolev-smoothed ones, at once or in stages; and the anchors' learning-rate warm-up (precond.anchor_warmup)."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch

from pig.avatar.checkpoint import load_avatar
from pig.config import ConfigError, derive_preset, load_preset, load_section
from pig.field.latent_grid import LatentGrid
from pig.field.optim import Adam
from pig.field.precondition import PrecondConfig

RESOLUTIONS = [3, 5]
LAMBDAS = [2.0, 1e4]  # a mild and a stiff level


def _grid(form: str, lambdas: list[float], seed: int = 0) -> LatentGrid:
    generator = torch.Generator().manual_seed(seed)
    return LatentGrid(RESOLUTIONS, 2, [-1.0, -1.0, -1.0], [1.0, 1.0, 1.0], 0.0, lambdas=lambdas, form=form,
                      init_std=0.5, generator=generator)


def _loss(grid: LatentGrid) -> torch.Tensor:
    points = torch.linspace(-1, 1, 7)[:, None].expand(7, 3) * torch.tensor([1.0, -0.5, 0.3])
    target = torch.sin(3 * points[:, :2])
    return ((grid(points) - target) ** 2).sum()


def _step(grid: LatentGrid, optimizer: torch.optim.Optimizer) -> None:
    optimizer.zero_grad()
    _loss(grid).backward()
    optimizer.step()


@pytest.mark.parametrize("form", ["substitute", "filter"])
def test_switching_lambdas_keeps_the_values_and_then_smooths_like_a_grid_built_with_them(form):
    """A grid trained under lambda 0, switched to the preset's lambdas, keeps every value bit for bit; its next
    Adam step (fresh moments) equals that of a grid built with those lambdas and set to the same values."""
    delayed = _grid(form, [0.0, 0.0])
    optimizer = Adam([level.param for level in delayed.levels], lr=0.05)
    for _ in range(3):
        _step(delayed, optimizer)
    before = [v.detach().clone() for v in delayed.volumes()]
    assert not torch.equal(before[1], _grid(form, [0.0, 0.0]).volumes()[1])  # the plain steps moved the grid
    delayed.set_lambdas(LAMBDAS)
    assert all(torch.equal(a, b) for a, b in zip(before, delayed.volumes()))

    reference = _grid(form, LAMBDAS, seed=1)
    for level, value in zip(reference.levels, before):
        level.set_value(value)
    fresh = [Adam([level.param for level in g.levels], lr=0.05) for g in (delayed, reference)]
    for grid, opt in zip((delayed, reference), fresh):
        _step(grid, opt)
    for a, b, start in zip(delayed.volumes(), reference.volumes(), before):
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-7)
        assert not torch.equal(a, start)
    # The stiff level's step is nearly constant over the grid (lambda 1e4 passes only the mean), the plain one not.
    stiff_change = delayed.volumes()[1].detach() - before[1]
    assert float(stiff_change.std(dim=(1, 2, 3)).max()) < 1e-2 * float(stiff_change.abs().mean())


def test_switching_without_keeping_values_reads_the_stored_parameters_under_the_new_lambdas():
    """keep_values=False: the substitution's (u, origin) keep their meaning, x = origin + A^-1 u, as a grid built
    with the new lambdas and given the same state dict computes it."""
    grid = _grid("substitute", [0.0, 0.0])
    optimizer = Adam([level.param for level in grid.levels], lr=0.05)
    _step(grid, optimizer)
    state = {k: v.clone() for k, v in grid.state_dict().items()}
    grid.set_lambdas(LAMBDAS, keep_values=False)
    reference = _grid("substitute", LAMBDAS, seed=1)
    reference.load_state_dict(state)
    for a, b in zip(grid.volumes(), reference.volumes()):
        assert torch.equal(a, b)


def test_set_lambdas_refuses_a_plain_grid_and_a_wrong_count():
    with pytest.raises(ValueError, match="form 'none'"):
        _grid("none", LAMBDAS).set_lambdas(LAMBDAS)
    with pytest.raises(ValueError, match="expected 2 lambdas"):
        _grid("substitute", LAMBDAS).set_lambdas([1.0])


@pytest.mark.parametrize("key", ["grid_delay", "grid_ramp", "anchor_warmup"])
def test_negative_schedule_lengths_are_refused_with_the_key_named(key):
    with pytest.raises(ConfigError, match=f"precond.{key} must be at least 0, found -1"):
        load_section({"precond": {key: -1}}, "precond", PrecondConfig)
    with pytest.raises(ConfigError, match="precond.grid_ramp_stages must be at least 1, found 0"):
        load_section({"precond": {"grid_ramp_stages": 0}}, "precond", PrecondConfig)


@pytest.mark.parametrize("delay, ramp, stages, expected", [
    (0, 0, 4, [1.0] * 6),  # the paper's schedule
    (3, 0, 4, [0, 0, 0, 1, 1, 1]),  # grid_delay alone: one switch
    (0, 8, 4, [0, 0, 0.25, 0.25, 0.5, 0.5, 0.75, 0.75, 1, 1]),
    (2, 6, 3, [0, 0, 0, 0, 1 / 3, 1 / 3, 2 / 3, 2 / 3, 1, 1]),
    (1, 3, 4, [0, 0, 0.25, 0.5, 1, 1]),  # more stages than iterations: a stage per iteration, the last ones skipped
    (0, 5, 1, [0, 0, 0, 0, 0, 1, 1]),  # one stage: the delay by another name
])
def test_grid_lambda_scale_follows_the_delay_then_the_ramps_stages(delay, ramp, stages, expected):
    cfg = PrecondConfig(grid_delay=delay, grid_ramp=ramp, grid_ramp_stages=stages)
    assert [cfg.grid_lambda_scale(i) for i in range(len(expected))] == pytest.approx(expected, abs=0)
    assert cfg.grid_lambda_scale(10**6) == 1.0


def test_anchor_lr_scale_ramps_linearly_to_one():
    assert [PrecondConfig(anchor_warmup=4).anchor_lr_scale(i) for i in range(6)] == [0.25, 0.5, 0.75, 1, 1, 1]
    assert PrecondConfig().anchor_lr_scale(0) == 1.0


def _preset(tmp_path, name: str, iterations: int, **precond) -> str:
    return str(derive_preset(tmp_path / f"{name}.yaml", "test", avatar={"num_anchors": 300}, precond=precond,
                             fit={"iterations": iterations, "eval_every": 100, "eval_frames": 1,
                                  "checkpoint_minutes": 0.0, "prefetch": 1, "loader_workers": 1}))


class Killed(Exception):
    pass


def _killed_at(stop: int):
    def callback(iteration: int) -> None:
        if iteration == stop:
            raise Killed

    return callback


def _same_state(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[key], b[key]) for key in a)


def _assert_plain_until(small_capture, tmp_path, name: str, preset: str, stop: int) -> None:
    """`preset`'s fit killed after `stop` iterations has the checkpoint of a fit with grid lambda 0 (and the same
    iteration count, which the schedule follows), bit for bit."""
    from pig.avatar.training import fit

    plain = _preset(tmp_path, "plain", load_preset(preset)["fit"]["iterations"], grid_lambda=0.0)
    for folder, spec in ((name, preset), ("plain", plain)):
        with pytest.raises(Killed):
            fit(small_capture, tmp_path / folder, spec, on_iteration=_killed_at(stop))
    states = [torch.load(tmp_path / folder / "checkpoint.pt", weights_only=True) for folder in (name, "plain")]
    assert states[0]["iteration"] == states[1]["iteration"] == stop
    assert _same_state(states[0]["model"], states[1]["model"])


def _field_steps(checkpoint: Path) -> dict[str, int]:
    """Adam's step count of each field optimiser group in a checkpoint."""
    state = torch.load(checkpoint, weights_only=True)["optimizers"][0]
    return {group["name"]: int(state["state"][group["params"][0]]["step"]) for group in state["param_groups"]}


@pytest.mark.slow
def test_delayed_fit_trains_the_grid_plainly_first_and_resumes_across_the_switch(small_capture, tmp_path):
    """grid_delay 3 of 6 iterations:
    - its checkpoint after 3 iterations equals that of a fit with grid lambda 0 (plain grid steps), bit for bit;
    - killed there (the switch not yet made) or after 5 (made) and resumed, it ends as the uninterrupted fit;
    - avatar.pt reads back under the preset's lambdas."""
    from pig.avatar.training import fit

    delayed = _preset(tmp_path, "delayed", 6, grid_delay=3)
    reference = fit(small_capture, tmp_path / "full", delayed)
    _assert_plain_until(small_capture, tmp_path, "delayed", delayed, 3)

    resumed_at_3 = fit(small_capture, tmp_path / "delayed", delayed)
    with pytest.raises(Killed):
        fit(small_capture, tmp_path / "late", delayed, on_iteration=_killed_at(5))
    # The switch restarted the grid levels' Adam moments (2 steps since) and not the anchors' (5 steps).
    assert _field_steps(tmp_path / "late" / "checkpoint.pt") == {"grid0": 2, "grid1": 2, "anchors": 5}
    resumed_at_5 = fit(small_capture, tmp_path / "late", delayed)
    final = load_avatar(reference).state_dict()
    for resumed in (resumed_at_3, resumed_at_5):
        assert _same_state(final, load_avatar(resumed).state_dict())

    assert load_avatar(reference).grid.levels[0].system.lam == load_preset(delayed)["precond"]["grid_lambda"]


@pytest.mark.slow
def test_fit_stopped_before_the_switch_stores_its_grid_under_the_preset_lambdas(small_capture, tmp_path):
    """Two iterations of a fit delayed by 5: avatar.pt, built with the preset's lambdas when read, gives the grid
    values of the two plain steps, which the fit with grid lambda 0 reaches too."""
    from pig.avatar.training import fit

    stopped = load_avatar(fit(small_capture, tmp_path / "stopped", _preset(tmp_path, "stopped", 2, grid_delay=5)))
    plain = load_avatar(fit(small_capture, tmp_path / "plain", _preset(tmp_path, "plain", 2, grid_lambda=0.0)))
    assert stopped.grid.levels[-1].system.lam > 0 == plain.grid.levels[-1].system.lam
    for a, b in zip(stopped.grid.volumes(), plain.grid.volumes()):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-6)


@pytest.mark.slow
def test_ramped_fit_moves_through_its_stages_and_resumes_inside_one(small_capture, tmp_path):
    """grid_ramp 4 in 2 stages over 6 iterations (lambda scale 0, 0, 0.5, 0.5, 1, 1):
    - its checkpoint after 2 iterations equals that of a fit with grid lambda 0, bit for bit;
    - killed inside the half stage (after 3) or after the last switch (5) and resumed, it ends as the uninterrupted
      fit; the last switch restarted the grid levels' moments (1 step since) and not the anchors' (5);
    - avatar.pt reads back under the preset's lambdas."""
    from pig.avatar.training import fit

    ramped = _preset(tmp_path, "ramped", 6, grid_ramp=4, grid_ramp_stages=2)
    reference = fit(small_capture, tmp_path / "full", ramped)
    _assert_plain_until(small_capture, tmp_path, "ramped", ramped, 2)

    final = load_avatar(reference).state_dict()
    for name, stop in (("mid", 3), ("late", 5)):
        with pytest.raises(Killed):
            fit(small_capture, tmp_path / name, ramped, on_iteration=_killed_at(stop))
        if stop == 5:
            assert _field_steps(tmp_path / name / "checkpoint.pt") == {"grid0": 1, "grid1": 1, "anchors": 5}
        assert _same_state(final, load_avatar(fit(small_capture, tmp_path / name, ramped)).state_dict()), name
    assert load_avatar(reference).grid.levels[0].system.lam == load_preset(ramped)["precond"]["grid_lambda"]


@pytest.mark.slow
def test_anchor_warmup_scales_the_anchors_rate_alone(small_capture, tmp_path):
    """anchor_warmup 4: after 3 iterations the anchors' rate is 3/4 of the fit's schedule times their base rate,
    every other group's the schedule times its base rate (the checkpoint's optimiser groups)."""
    from pig.avatar.training import fit

    preset = _preset(tmp_path, "warm", 6, anchor_warmup=4)
    with pytest.raises(Killed):
        fit(small_capture, tmp_path / "warm", preset, on_iteration=_killed_at(3))
    groups = torch.load(tmp_path / "warm" / "checkpoint.pt", weights_only=True)["optimizers"][0]["param_groups"]
    cfg = load_section(load_preset(preset), "precond", PrecondConfig)
    base = {f"grid{g}": lr for g, lr in enumerate(cfg.grid_lrs(len(groups) - 1))} | {"anchors": cfg.anchor_lr}
    factors = {group["name"]: group["lr"] / base[group["name"]] for group in groups}
    assert factors["anchors"] == pytest.approx(0.75 * factors["grid0"], rel=1e-12)
    assert factors["grid0"] == pytest.approx(factors["grid1"], rel=1e-12) and 0 < factors["grid0"] <= 1

"""Delayed grid preconditioning (precond.grid_delay): plain grid steps first, then the Sobolev-smoothed ones."""
from __future__ import annotations

import pytest
import torch
import yaml

from pig.avatar.checkpoint import load_avatar
from pig.config import ConfigError, load_preset, load_section
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


def test_negative_delay_is_refused_with_the_key_named():
    with pytest.raises(ConfigError, match="precond.grid_delay must be at least 0"):
        load_section({"precond": {"grid_delay": -1}}, "precond", PrecondConfig)


def _preset(tmp_path, name: str, iterations: int, **precond) -> str:
    preset = load_preset("test")
    preset.pop("_path")
    preset["avatar"].update(num_anchors=300)
    preset["precond"].update(precond)
    preset["fit"].update(iterations=iterations, eval_every=100, eval_frames=1, checkpoint_minutes=0.0, prefetch=1,
                         loader_workers=1)
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(preset))
    return str(path)


class Killed(Exception):
    pass


def _killed_at(stop: int):
    def callback(iteration: int) -> None:
        if iteration == stop:
            raise Killed

    return callback


def _same_state(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[key], b[key]) for key in a)


@pytest.mark.slow
def test_delayed_fit_trains_the_grid_plainly_first_and_resumes_across_the_switch(small_capture, tmp_path):
    """grid_delay 3 of 6 iterations:
    - its checkpoint after 3 iterations equals that of a fit with grid lambda 0 (plain grid steps), bit for bit;
    - killed there (the switch not yet made) or after 5 (made) and resumed, it ends as the uninterrupted fit;
    - avatar.pt reads back under the preset's lambdas."""
    from pig.avatar.training import fit

    delayed = _preset(tmp_path, "delayed", 6, grid_delay=3)
    reference = fit(small_capture, tmp_path / "full", delayed)
    plain = _preset(tmp_path, "plain", 6, grid_lambda=0.0)
    for name, preset in (("delayed", delayed), ("plain", plain)):
        with pytest.raises(Killed):
            fit(small_capture, tmp_path / name, preset, on_iteration=_killed_at(3))
    at_3 = [torch.load(tmp_path / name / "checkpoint.pt", weights_only=True) for name in ("delayed", "plain")]
    assert at_3[0]["iteration"] == at_3[1]["iteration"] == 3
    assert _same_state(at_3[0]["model"], at_3[1]["model"])

    resumed_at_3 = fit(small_capture, tmp_path / "delayed", delayed)
    with pytest.raises(Killed):
        fit(small_capture, tmp_path / "late", delayed, on_iteration=_killed_at(5))
    # The switch restarted the grid levels' Adam moments (2 steps since) and not the anchors' (5 steps).
    field_state = torch.load(tmp_path / "late" / "checkpoint.pt", weights_only=True)["optimizers"][0]
    steps = {group["name"]: int(field_state["state"][group["params"][0]]["step"]) for group in field_state["param_groups"]}
    assert steps == {"grid0": 2, "grid1": 2, "anchors": 5}, steps
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

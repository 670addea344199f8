"""Eqs. 4-5 where they act in the fit (issue 38): the `paper` preset's preconditioning as pig.avatar.training.fit
builds and steps it, for `pig`, `no_precond` and `fixed_anchors`, against float64 references of the same graphs.

Per grid level g (0 coarsest): the system is I + lambda_g L_g on the level's 6-neighbour lattice, lambda_g =
2 * 1.25^g, stepped at eta_g = 1e-2 * 1.5^g; the anchors' system is I + 8 L_knn on the k = 8 graph of the initial
anchors, fixed for the whole fit; nothing else is preconditioned, and `no_precond` preconditions nothing. One
plain gradient step of the fit moves x by -eta (I + lambda L)^-2 dL/dx (Eqs. 4-5 verbatim); under the preset's
Adam, x - x0 = (I + lambda L)^-1 u with u Adam's iterate on the gradient (I + lambda L)^-1 dL/dx (the substitution
form: Adam normalises u's step, so x moves by A^-1 of a normalised step, not by A^-2 dL/dx).
"""
from __future__ import annotations

import numpy as np
import pytest
import scipy.fft
import scipy.sparse as sp
import torch

from pig.config import ConfigError
from pig.field.knn_solve import CGSystem
from pig.field.lattice_solve import LatticeSystem
from pig.field.optim import build_optimizer
from pig.field.precondition import PrecondConfig, PreconditionedTensor

from precond_fit_fixture import observe_fit, paper_test_preset

RESOLUTIONS = [8, 24, 40, 56, 72, 88]  # the paper's G = 6 levels, coarsest first (Sec. 3.6)
GRID = [f"grid{g}" for g in range(6)]


@pytest.fixture(scope="module")
def fits(small_capture, tmp_path_factory):
    """{name: FitRecord} of short fits of the small capture with the `paper` preset's preconditioning."""
    root = tmp_path_factory.mktemp("precond_in_fit")
    # name: (variant, iterations, precond overrides); 0 iterations: the fit as built, stopped before its first step.
    runs = {"pig_sgd": ("pig", 1, {"optimizer": "sgd"}), "pig": ("pig", 3, None), "no_precond": ("no_precond", 0, None),
            "fixed_anchors": ("fixed_anchors", 0, None)}
    out = {}
    for name, (variant, iterations, precond) in runs.items():
        preset = paper_test_preset(root / f"{name}.yaml", max(iterations, 1), precond)
        out[name] = observe_fit(small_capture, root / name, preset, variant, build_only=iterations == 0)
    return out


def lattice_matrix(n: int, lam: float) -> sp.csr_matrix:
    """I + lam L of the n^3 lattice with unit edges to the 6 neighbours (free boundary), assembled from its edges."""
    path = sp.diags([np.r_[1.0, 2.0 * np.ones(n - 2), 1.0], -np.ones(n - 1), -np.ones(n - 1)], [0, 1, -1])
    eye = sp.identity(n)
    laplacian = sp.kron(sp.kron(path, eye), eye) + sp.kron(sp.kron(eye, path), eye) + sp.kron(sp.kron(eye, eye), path)
    return (sp.identity(n**3) + lam * laplacian).tocsr()


def lattice_solve(b: np.ndarray, lam: float) -> np.ndarray:
    """(I + lam L)^-1 b channel-wise for b (C, n, n, n) in float64 by scipy's DCT, checked against the assembled
    matrix (so the reference is a solve of that graph whatever the transform)."""
    n = b.shape[-1]
    mu = 4 * np.sin(np.pi * np.arange(n) / (2 * n)) ** 2
    eig = mu[:, None, None] + mu[None, :, None] + mu[None, None, :]
    x = scipy.fft.idctn(scipy.fft.dctn(b, type=2, norm="ortho", axes=(1, 2, 3)) / (1 + lam * eig), type=2, norm="ortho",
                        axes=(1, 2, 3))
    a = lattice_matrix(n, lam)
    residual = np.linalg.norm(a @ x.reshape(len(b), -1).T - b.reshape(len(b), -1).T)
    assert residual <= 1e-12 * np.linalg.norm(b)
    return x


def knn_matrix(points: np.ndarray, k: int, lam: float) -> np.ndarray:
    """Dense I + lam L_knn of the symmetrised k-nearest-neighbour graph (unit edges), by brute force."""
    dist = np.linalg.norm(points[:, None] - points[None], axis=-1)
    np.fill_diagonal(dist, np.inf)
    nearest = np.argsort(dist, axis=1)[:, :k]
    w = np.zeros_like(dist)
    w[np.repeat(np.arange(len(points)), k), nearest.ravel()] = 1.0
    w = np.maximum(w, w.T)
    return np.eye(len(points)) + lam * (np.diag(w.sum(1)) - w)


def solver(record, name: str):
    """float64 A^-1 for the tensor `name` of a fit: the lattice of its level, or the dense KNN system of the fit's
    initial anchors."""
    if name == "anchors":
        a = knn_matrix(record.model.x_init.double().numpy(), 8, 8.0)
        return lambda b: np.linalg.solve(a, b)
    lam = 2.0 * 1.25 ** int(name[4:])
    return lambda b: lattice_solve(b, lam)


def close(actual: torch.Tensor | np.ndarray, expected: np.ndarray) -> float:
    """Relative error |actual - expected| / |expected| (asserting expected is not zero)."""
    actual = np.asarray(actual, dtype=np.float64)
    assert np.linalg.norm(expected) > 0
    return float(np.linalg.norm(actual - expected) / np.linalg.norm(expected))


def assert_moved(record, step, name: str, expected: np.ndarray, rtol: float) -> None:
    """x after `step` minus x0 is `expected` within `rtol` (relative norm); for the anchors, elementwise within rtol
    of the largest move plus one float32 spacing of x0 (their float32 metre-sized positions round a 1e-8..1e-5 m
    move). CG's stopping rule bounds the error against the whole vector, not each element: a move 500 times smaller
    than the largest carried 4.8e-3 of its own size (3.5e-10 m)."""
    moved = (step["x"][name] - record.x0[name]).numpy()
    if name == "anchors":
        ulp = np.abs(np.spacing(record.x0[name].float().numpy())).astype(np.float64)
        assert np.all(np.abs(moved - expected) <= np.abs(expected).max() * rtol + ulp)
    else:
        assert close(moved, expected) < rtol


@pytest.mark.parametrize("name", ["pig", "fixed_anchors", "no_precond"])
def test_each_level_has_lambda_g_and_eta_g_and_only_the_grid_and_anchors_are_preconditioned(fits, name):
    record = fits[name]
    model, (field_opt, decoder_opt) = record.model, record.optimizers
    smoothed = name != "no_precond"
    levels = list(model.grid.levels)
    assert [tuple(level.param.shape) for level in levels] == [(16, r, r, r) for r in RESOLUTIONS]
    for g, level in enumerate(levels):
        if smoothed:
            assert level.form == "substitute" and isinstance(level.system, LatticeSystem)
            assert level.system.shape == (RESOLUTIONS[g],) * 3
            assert level.system.lam == pytest.approx(2.0 * 1.25**g, rel=1e-12)
        else:
            assert level.form == "none" and level.system is None
        assert field_opt.param_groups[g]["params"] == [level.param]
        assert field_opt.param_groups[g]["lr"] == pytest.approx(1e-2 * 1.5**g, rel=1e-12)
    anchors = model.anchors
    if name == "fixed_anchors":
        assert anchors is None
    else:
        assert anchors.form == ("substitute" if smoothed else "none")
        assert field_opt.param_groups[-1]["params"] == [anchors.param]
        assert field_opt.param_groups[-1]["lr"] == pytest.approx(2e-5, rel=1e-12)
    # Exactly the grid levels and the anchors are preconditioned tensors; the field optimiser holds exactly their
    # variables, the other optimiser every other trainable parameter.
    tensors = [m for m in model.modules() if isinstance(m, PreconditionedTensor)]
    expected = levels + ([] if anchors is None else [anchors])
    assert {id(m) for m in tensors} == {id(m) for m in expected}
    assert sum(m.form != "none" for m in tensors) == (len(expected) if smoothed else 0)
    field_params = [p for group in field_opt.param_groups for p in group["params"]]
    other = [p for group in decoder_opt.param_groups for p in group["params"]]
    assert {id(p) for p in field_params} == {id(m.param) for m in expected} and len(field_params) == len(expected)
    trainable = {id(p) for p in model.parameters() if p.requires_grad}
    assert {id(p) for p in other} == trainable - {id(p) for p in field_params} and len(other) == len(set(map(id, other)))
    # The rates the fit stepped with: the paper preset's schedule is constant (warm-up 0, final factor 1).
    for step in record.steps:
        assert step["lr"] == {group["name"]: group["lr"] for group in field_opt.param_groups}


def test_the_anchor_graph_is_the_k8_graph_of_the_initial_anchors_and_stays_fixed(fits):
    record = fits["pig"]
    anchors = record.model.anchors
    assert isinstance(anchors.system, CGSystem) and anchors.system.lam == 8.0
    x_init = record.model.x_init.double().numpy()
    expected = knn_matrix(x_init, 8, 1.0) - np.eye(len(x_init))
    np.testing.assert_array_equal(anchors.system.laplacian.toarray(), expected)
    # Three steps later the anchors moved, and the fit still solves with the graph built on the initial ones.
    assert anchors.system is record.systems["anchors"]
    np.testing.assert_array_equal(anchors.system.laplacian.toarray(), expected)
    assert float((record.steps[-1]["x"]["anchors"] - record.x0["anchors"]).abs().max()) > 0
    assert all(level.system is record.systems[f"grid{g}"] for g, level in enumerate(record.model.grid.levels))


@pytest.mark.parametrize("name", GRID + ["anchors"])
def test_one_gradient_step_of_the_fit_is_eq_4_and_eq_5(fits, name):
    """precond.optimizer sgd: x moves by -eta (I + lambda L)^-2 dL/dx, and the optimiser saw (I + lambda L)^-1 dL/dx."""
    record = fits["pig_sgd"]
    step = record.steps[0]
    solve = solver(record, name)
    g = step["dx"][name].numpy()
    seen = solve(g)
    # The lattice solve is float32 (~5e-7 relative); CG stops at 1e-5 of each right-hand side, two solves.
    rtol = 1e-5 if name != "anchors" else 1e-4
    assert close(step["grad"][name], seen) < rtol
    # The substitution's variable u = A (x - x0) took the step -eta A^-1 dL/dx ...
    assert close(step["param"][name], -step["lr"][name] * seen) < rtol
    # ... so x moved by -eta A^-2 dL/dx, up to float32 rounding of x0 + (x - x0): at 2e-5 per step the anchors' move
    # (~1e-8 m) is below the rounding of metre-sized positions, which a single plain step cannot resolve.
    assert_moved(record, step, name, -step["lr"][name] * solve(seen), rtol)


@pytest.mark.parametrize("name", GRID + ["anchors"])
def test_adam_steps_of_the_fit_are_adam_on_u_seeing_a_inverse_g(fits, name):
    """The preset's Adam (substitution form, fused): after each of three steps x - x0 = A^-1 u, u being Adam's
    iterate (betas 0.9 / 0.999, eps 1e-8, bias-corrected) on the gradients A^-1 dL/dx, all in float64."""
    record = fits["pig"]
    solve = solver(record, name)
    b1, b2, eps = 0.9, 0.999, 1e-8
    u = m = v = 0.0
    for t, step in enumerate(record.steps, start=1):
        q = solve(step["dx"][name].numpy())
        m = b1 * m + (1 - b1) * q
        v = b2 * v + (1 - b2) * q**2
        u = u - step["lr"][name] * (m / (1 - b1**t)) / (np.sqrt(v / (1 - b2**t)) + eps)
        assert_moved(record, step, name, solve(u), 1e-4)
    # Not Eq. 4's power: the last x differs from the same rates' plain steps -eta sum_t A^-2 dL/dx in direction.
    sgd = sum(-step["lr"][name] * solve(solve(step["dx"][name].numpy())) for step in record.steps)
    moved = (record.steps[-1]["x"][name] - record.x0[name]).numpy().ravel()
    cosine = moved @ sgd.ravel() / (np.linalg.norm(moved) * np.linalg.norm(sgd))
    assert cosine < 0.99


@pytest.mark.parametrize("kind", ["adam", "uniform_adam"])
def test_adam_eps_of_the_field_optimiser_is_configurable_and_damps_steps_of_gradients_near_it(kind):
    """precond.adam_eps (default 1e-8, torch's) sets the field optimiser's eps: a first step on gradients of 1e-9
    (the size of the fine grid levels' in the fit) is lr g / (|g| + eps): ~0.09 lr at 1e-8, ~lr at 1e-15."""
    assert PrecondConfig().adam_eps == 1e-8
    moved = {}
    for eps in (1e-8, 1e-15):
        p = torch.nn.Parameter(torch.zeros(4, dtype=torch.float64))
        opt = build_optimizer(kind, [{"params": [p], "lr": 0.1}], eps)
        p.grad = torch.full((4,), -1e-9, dtype=torch.float64)
        opt.step()
        moved[eps] = float(p.detach()[0])
    assert moved[1e-8] == pytest.approx(0.1 * 1e-9 / (1e-9 + 1e-8), rel=1e-9)
    assert moved[1e-15] == pytest.approx(0.1, rel=1e-5)
    with pytest.raises(ConfigError, match="precond.adam_eps"):
        PrecondConfig(adam_eps=0.0)


def test_the_fit_builds_its_fused_field_adam_with_precond_adam_eps(small_capture, tmp_path):
    preset = paper_test_preset(tmp_path / "eps.yaml", 1, {"adam_eps": 1e-15})
    record = observe_fit(small_capture, tmp_path / "fit", preset, build_only=True)
    field_opt, decoder_opt = record.optimizers
    assert isinstance(field_opt, torch.optim.Adam) and all(group["fused"] for group in field_opt.param_groups)
    assert {group["eps"] for group in field_opt.param_groups} == {1e-15}
    assert {group["eps"] for group in decoder_opt.param_groups} == {1e-8}

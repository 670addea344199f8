"""The two application forms against the closed-form update x - lr A^-2 g (up to lambda = 1e8); the solve's gradient;
the substitution's exact origin and state dict; Adam and UniformAdam."""
import numpy as np
import pytest
import torch

from pig.config import load_preset, load_section
from pig.field.knn_graph import knn_laplacian
from pig.field.knn_solve import CGSystem, FactorizedSystem
from pig.field.latent_grid import FieldConfig, LatentGrid
from pig.field.lattice_solve import LatticeSystem
from pig.field.optim import Adam, UniformAdam, build_optimizer, field_param_groups
from pig.field.precondition import (
    FilteredGradient,
    PrecondConfig,
    PreconditionedTensor,
    SubstitutionSolve,
    precondition_anchors,
)


def lattice_case():
    shape = (3, 4, 2)
    return LatticeSystem(shape, 1.3), torch.randn(2, *shape, dtype=torch.float64, generator=torch.Generator().manual_seed(0))


def knn_case():
    points = np.random.default_rng(0).normal(size=(30, 3))
    return FactorizedSystem(knn_laplacian(points, 4), 2.0), torch.randn(30, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))


def dense_operator(system, like: torch.Tensor) -> torch.Tensor:
    """A as a dense matrix over flattened tensors shaped like `like`, by applying it to unit vectors."""
    n = like.numel()
    eye = torch.eye(n, dtype=torch.float64)
    return torch.stack([system.apply(e.reshape(like.shape)).reshape(-1) for e in eye], dim=1)


CASES = {"lattice": lattice_case, "knn": knn_case}


@pytest.mark.parametrize("case", CASES)
def test_substitution_solve_gradcheck(case):
    system, u = CASES[case]()
    u.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: SubstitutionSolve.apply(t, system), (u,), eps=1e-6, atol=1e-8)


@pytest.mark.parametrize("case", CASES)
def test_filtered_gradient_is_a_inverse_squared(case):
    system, x = CASES[case]()
    x.requires_grad_(True)
    g = torch.randn_like(x)
    (FilteredGradient.apply(x, system) * g).sum().backward()
    a = dense_operator(system, x)
    ref = torch.linalg.solve(a @ a, g.reshape(-1)).reshape(x.shape)
    assert ((x.grad - ref).norm() / ref.norm()).item() < 1e-10


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("form", ["filter", "substitute"])
def test_gradient_descent_follows_eq4(case, form):
    """Three SGD steps on a quadratic match x <- x - lr A^-2 (x - t) computed densely."""
    system, x0 = CASES[case]()
    target = torch.randn_like(x0)
    a = dense_operator(system, x0)
    a2 = a @ a
    lr = 0.3
    p = PreconditionedTensor(x0, system, form)
    opt = build_optimizer("sgd", [{"params": [p.param], "lr": lr}])
    ref = x0.reshape(-1).clone()
    for _ in range(3):
        opt.zero_grad()
        (0.5 * (p() - target).square().sum()).backward()
        opt.step()
        ref = ref - lr * torch.linalg.solve(a2, ref - target.reshape(-1))
        with torch.no_grad():
            assert ((p().reshape(-1) - ref).norm() / ref.norm()).item() < 1e-10


def test_uniform_adam_keeps_the_filtered_direction_and_adam_does_not():
    system, x0 = knn_case()
    g = torch.randn(x0.shape, dtype=x0.dtype, generator=torch.Generator().manual_seed(1))
    a = dense_operator(system, x0)
    filtered = torch.linalg.solve(a @ a, g.reshape(-1)).reshape(x0.shape)
    steps = {}
    for kind in ("uniform_adam", "adam"):
        p = PreconditionedTensor(x0, system, "filter")
        opt = build_optimizer(kind, [{"params": [p.param], "lr": 1e-2}])
        (p() * g).sum().backward()
        opt.step()
        steps[kind] = (p.param.detach() - x0).reshape(-1)
    cosine = lambda u, v: (u @ v / (u.norm() * v.norm())).item()  # noqa: E731
    # First Adam step: -lr m / sqrt(v) with m = filtered, v = max filtered^2 (uniform) or filtered^2.
    assert cosine(steps["uniform_adam"], -filtered.reshape(-1)) > 1 - 1e-12
    torch.testing.assert_close(steps["uniform_adam"].abs().max(), torch.tensor(1e-2, dtype=torch.float64), rtol=1e-6, atol=0)
    f = filtered.reshape(-1)
    torch.testing.assert_close(steps["adam"], -1e-2 * f / (f.abs() + 1e-8), rtol=1e-10, atol=0)
    # Adam's step is sign(filtered): its cosine with the filtered direction is |f|_1 / (sqrt(n) |f|_2) < 1.
    expected_cosine = (f.abs().sum() / (f.numel() ** 0.5 * f.norm())).item()
    assert cosine(steps["adam"], -f) == pytest.approx(expected_cosine, rel=1e-6)  # eps=1e-8 in the denominator
    assert expected_cosine < 0.99


def test_adam_matches_torch_adam():
    gen = torch.Generator().manual_seed(4)
    p_ours = torch.randn(5, 7, dtype=torch.float64, generator=gen, requires_grad=True)
    p_ref = p_ours.detach().clone().requires_grad_(True)
    ours = Adam([p_ours], lr=3e-2, betas=(0.8, 0.99), eps=1e-6)
    ref = torch.optim.Adam([p_ref], lr=3e-2, betas=(0.8, 0.99), eps=1e-6)
    for _ in range(6):
        g = torch.randn(5, 7, dtype=torch.float64, generator=gen)
        p_ours.grad, p_ref.grad = g.clone(), g.clone()
        ours.step()
        ref.step()
    torch.testing.assert_close(p_ours, p_ref, rtol=1e-12, atol=1e-14)


def test_uniform_adam_matches_a_float64_reference_loop():
    gen = torch.Generator().manual_seed(5)
    x = torch.randn(4, 3, dtype=torch.float64, generator=gen, requires_grad=True)
    grads = [torch.randn(4, 3, dtype=torch.float64, generator=gen) * s for s in (1.0, 10.0, 0.1, 3.0)]
    lr, b1, b2, eps = 1e-2, 0.9, 0.999, 1e-8
    ref, m, v = x.detach().numpy().copy(), np.zeros((4, 3)), 0.0
    for t, g in enumerate(grads, start=1):
        g = g.numpy()
        m = b1 * m + (1 - b1) * g
        v = b2 * v + (1 - b2) * np.max(g**2)
        ref = ref - lr * (m / (1 - b1**t)) / (np.sqrt(v / (1 - b2**t)) + eps)
    opt = UniformAdam([x], lr=lr)
    for g in grads:
        x.grad = g.clone()
        opt.step()
    np.testing.assert_allclose(x.detach().numpy(), ref, rtol=1e-12, atol=1e-14)
    assert opt.state[x]["exp_avg_sq"].ndim == 0


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("form", ["filter", "substitute"])
def test_deferred_solves_follow_eq4(case, form):
    """The solves taken out of the autograd pass (a data-parallel fit's sharded solves: the offset given to the
    forward, the gradient preconditioned after the backward) make the same SGD steps as the dense update."""
    system, x0 = CASES[case]()
    target = torch.randn_like(x0)
    a = dense_operator(system, x0)
    lr = 0.3
    p = PreconditionedTensor(x0, system, form)
    p.defer_gradient = True
    opt = build_optimizer("sgd", [{"params": [p.param], "lr": lr}])
    ref = x0.reshape(-1).clone()
    for _ in range(3):
        opt.zero_grad()
        if form == "substitute":
            p.give(p.solve_offset())
        (0.5 * (p() - target).square().sum()).backward()
        raw = (p().detach() - target).reshape(-1)
        assert torch.allclose(p.param.grad.reshape(-1), raw)  # the backward left dL/dx unsolved
        p.param.grad.copy_(p.precondition_gradient(p.param.grad))
        opt.step()
        ref = ref - lr * torch.linalg.solve(a @ a, ref - target.reshape(-1))
        with torch.no_grad():
            assert ((p().reshape(-1) - ref).norm() / ref.norm()).item() < 1e-10


def test_a_given_offset_serves_only_the_u_it_was_solved_for():
    system, x0 = lattice_case()
    p = PreconditionedTensor(x0, system, "substitute")
    p.defer_gradient = True
    marker = torch.full_like(x0, 7.0)
    p.give(marker)  # returned as given, not solved
    assert torch.equal(p().detach(), x0 + marker)
    assert torch.equal(p().detach(), x0)  # once: the next forward solves
    p.give(marker)
    with torch.no_grad():
        p.param.add_(1.0)  # u changed since (an optimiser step): the given offset is stale
    assert torch.allclose(p().detach(), x0 + system.solve(torch.ones_like(x0)), rtol=0, atol=1e-12)


def test_preconditioned_tensor_stores_and_returns_values():
    system, x0 = lattice_case()
    sub = PreconditionedTensor(x0, system, "substitute")
    assert torch.equal(sub.param.detach(), torch.zeros_like(x0)) and torch.equal(sub.origin, x0)
    assert torch.equal(sub().detach(), x0)
    new = torch.randn_like(x0)
    sub.set_value(new)
    assert torch.equal(sub().detach(), new)
    plain = PreconditionedTensor(x0, None, "none")
    assert plain() is plain.param
    with pytest.raises(ValueError, match="needs a linear system"):
        PreconditionedTensor(x0, None, "filter")
    with pytest.raises(ValueError, match="form"):
        PreconditionedTensor(x0, system, "sobolev")


# Stiff cases: (dense float64 Laplacian, system for a lambda, initial value x0 in float32, solver accuracy).
# x0 holds metres with an offset, as the anchors' initial positions do.
def _knn_laplacian_dense():
    return knn_laplacian(np.random.default_rng(2).normal(size=(40, 3)), 6)


def _lattice_laplacian_dense(shape):
    """(A - I) of the lattice stencil at lambda = 1, column by column: the integer Laplacian, exactly."""
    n = int(np.prod(shape))
    system = LatticeSystem(shape, 1.0)
    eye = torch.eye(n, dtype=torch.float64)
    return (torch.stack([system.apply(e.reshape(shape)).reshape(-1) for e in eye], dim=1) - eye).numpy()


STIFF = {
    "knn_factorized": lambda lam: (FactorizedSystem(_knn_laplacian_dense(), lam), (40, 3), 1e-7),
    "knn_cg": lambda lam: (CGSystem(_knn_laplacian_dense(), lam, tol=1e-6, max_iter=2000), (40, 3), 1e-6),
    "lattice": lambda lam: (LatticeSystem((3, 4, 2), lam), (2, 3, 4, 2), 1e-6),
}


def _stiff_case(name, lam):
    system, shape, accuracy = STIFF[name](lam)
    lap = _lattice_laplacian_dense(shape[-3:]) if name == "lattice" else _knn_laplacian_dense().toarray()
    gen = torch.Generator().manual_seed(3)
    x0 = (torch.randn(shape, generator=gen, dtype=torch.float64) + torch.tensor([0.5, 1.0, -2.0])[: shape[-1]]).float()
    return system, lap, x0, accuracy


def _eigen_inverse_power(lap: np.ndarray, lam: float, b: torch.Tensor, power: int) -> torch.Tensor:
    """A^-power b in float64 from L's eigendecomposition (accurate for any lambda); A acts on the leading
    anchor axis of (N, C) tensors, or on the last three axes of (C, X, Y, Z) lattice tensors."""
    mu, v = np.linalg.eigh(lap)
    mu = np.where(mu < 1e-9, 0.0, mu)
    lattice = b.dim() == 4
    cols = b.double().reshape(b.shape[0], -1).T.numpy() if lattice else b.double().numpy()
    out = v @ ((v.T @ cols) / ((1.0 + lam * mu) ** power)[:, None])
    return torch.from_numpy(out.T.reshape(b.shape) if lattice else out)


@pytest.mark.parametrize("case", STIFF)
@pytest.mark.parametrize("lam", [0.0, 1.0, 8.0, 1e6, 1e8])
def test_initial_value_is_exact_for_any_lambda(case, lam):
    system, _, x0, _ = _stiff_case(case, lam)
    p = PreconditionedTensor(x0, system, "substitute")
    with torch.no_grad():
        assert torch.equal(p(), x0)


@pytest.mark.parametrize("solver", ["factorized", "cg"])
def test_configured_anchors_start_exactly_at_their_initial_positions(solver):
    """The fit's path (precondition_anchors from the preset section) at anchor lambda 1e8, float32 metres."""
    x_init = (torch.rand(300, 3, generator=torch.Generator().manual_seed(5)) * torch.tensor([0.6, 1.8, 0.3])).float()
    cfg = PrecondConfig(anchor_lambda=1e8, knn_solver=solver)
    anchors = precondition_anchors(x_init, cfg)
    with torch.no_grad():
        assert torch.equal(anchors(), x_init)


@pytest.mark.parametrize("case", STIFF)
@pytest.mark.parametrize("form", ["substitute", "filter"])
@pytest.mark.parametrize("lam", [0.0, 8.0, 1e6, 1e8])
def test_sgd_update_is_a_inverse_squared_g_up_to_lambda_1e8(case, form, lam):
    """One float32 SGD step moves x by -lr (I + lambda L)^-2 g, against a float64 eigendecomposition.

    Bound: each of the two solves errs by at most `accuracy` times its right-hand side (every eigenvalue of
    A is >= 1), plus float32 rounding of x0 + dx."""
    system, lap, x0, accuracy = _stiff_case(case, lam)
    g = torch.randn(x0.shape, generator=torch.Generator().manual_seed(4)).float()
    lr = 0.1
    p = PreconditionedTensor(x0, system, form)
    opt = build_optimizer("sgd", [{"params": [p.param], "lr": lr}])
    (p() * g).sum().backward()
    opt.step()
    with torch.no_grad():
        dx = p().double() - x0.double()
    ref = -lr * _eigen_inverse_power(lap, lam, g, 2)
    eps = torch.finfo(torch.float32).eps
    bound = 2 * accuracy * lr * g.double().norm() + 4 * eps * (x0.double().norm() + lr * g.double().norm())
    assert (dx - ref).norm() <= bound
    assert ref.norm() > 10 * bound  # the update itself is resolved, not lost in the bound


@pytest.mark.parametrize("case", ["lattice", "knn"])
@pytest.mark.parametrize("lam", [0.0, 1.0, 8.0])
def test_adam_path_equals_the_absolute_substitution(case, lam):
    """Adam on u = A (x - x0) takes the same steps as the predecessor's u = A x (only u's gradients reach
    Adam): five steps on a quadratic against that form computed densely in float64."""
    base, x0 = CASES[case]()
    system = LatticeSystem(base.shape, lam) if case == "lattice" else FactorizedSystem(base.laplacian, lam)
    target = torch.randn(x0.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(6))
    a = dense_operator(system, x0)
    lr, b1, b2, eps = 0.05, 0.9, 0.999, 1e-8
    u = a @ x0.reshape(-1)
    m, v = torch.zeros_like(u), torch.zeros_like(u)
    p = PreconditionedTensor(x0, system, "substitute")
    opt = build_optimizer("adam", [{"params": [p.param], "lr": lr}])
    for t in range(1, 6):
        opt.zero_grad()
        (0.5 * (p() - target).square().sum()).backward()
        opt.step()
        grad_u = torch.linalg.solve(a, torch.linalg.solve(a, u) - target.reshape(-1))
        m = b1 * m + (1 - b1) * grad_u
        v = b2 * v + (1 - b2) * grad_u.square()
        u = u - lr * (m / (1 - b1**t)) / ((v / (1 - b2**t)).sqrt() + eps)
        with torch.no_grad():
            torch.testing.assert_close(p().reshape(-1), torch.linalg.solve(a, u), rtol=1e-9, atol=1e-12)


def test_state_dict_round_trip_and_origin_free_state_dicts():
    system, x0 = knn_case()
    p = PreconditionedTensor(x0, system, "substitute")
    with torch.no_grad():
        p.param.add_(torch.randn(x0.shape, dtype=x0.dtype, generator=torch.Generator().manual_seed(7)))
        value = p().clone()
    state = p.state_dict()
    assert set(state) == {"param", "origin"}
    other = PreconditionedTensor(torch.zeros_like(x0), system, "substitute")  # a zero start keeps no origin ...
    assert set(other.state_dict()) == {"param"} and other.origin is None
    other.load_state_dict(state)  # ... and adopts the stored one
    assert torch.equal(other().detach(), value)
    # A state dict without an origin (zero start, or written when u = A x was stored) means x = A^-1 u.
    old = {"param": system.apply(value)}
    p.load_state_dict(old)
    assert p.origin is None
    torch.testing.assert_close(p().detach(), value, rtol=1e-12, atol=1e-12)


def test_bake_freezes_the_current_value():
    system, x0 = knn_case()
    p = PreconditionedTensor(x0, system, "substitute")
    with torch.no_grad():
        p.param.add_(0.1)
        value = p().clone()
    p.bake()
    assert p.form == "none" and p.origin is None and not p.param.requires_grad
    assert set(p.state_dict()) == {"param"}
    assert torch.equal(p(), value)


def test_cg_substitution_uses_separate_warm_starts():
    points = np.random.default_rng(1).normal(size=(200, 3))
    system = CGSystem(knn_laplacian(points, 6), 8.0, tol=1e-10, max_iter=500)
    p = PreconditionedTensor(torch.randn(200, 3, dtype=torch.float64), system, "substitute")
    target = torch.randn(200, 3, dtype=torch.float64)
    (p() - target).square().sum().backward()
    first_backward = system.last_iterations
    p.param.grad = None
    with torch.no_grad():
        p.param.sub_(1e-4)  # a small step: the next forward starts from the last forward solution
    (p() - target).square().sum().backward()
    assert 0 < system.last_iterations < first_backward


def test_param_groups_follow_the_paper_schedule():
    cfg = load_section(load_preset("paper"), "precond", PrecondConfig)
    field_cfg = load_section(load_preset("paper"), "field", FieldConfig)
    assert field_cfg.resolutions == [8, 24, 40, 56, 72, 88] and field_cfg.features == 16
    np.testing.assert_allclose(cfg.grid_lambdas(6), [2 * 1.25**g for g in range(6)])
    small = FieldConfig(resolutions=[2, 3, 4], features=2)
    grid = LatentGrid.from_config(small, cfg, [0, 0, 0], [1, 1, 1])
    anchors = precondition_anchors(torch.rand(50, 3, generator=torch.Generator().manual_seed(0)), cfg)
    groups = field_param_groups(grid, anchors, cfg)
    assert [g["name"] for g in groups] == ["grid0", "grid1", "grid2", "anchors"]
    np.testing.assert_allclose([g["lr"] for g in groups], [1e-2, 1.5e-2, 2.25e-2, 2e-5])
    assert groups[3]["params"][0] is anchors.param
    assert [level.system.lam for level in grid.levels] == pytest.approx([2.0, 2.5, 3.125])
    assert isinstance(build_optimizer("uniform_adam", groups), UniformAdam)
    with pytest.raises(ValueError, match="kind"):
        build_optimizer("lbfgs", groups)

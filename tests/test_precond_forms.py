"""The two application forms against the closed-form update x - lr A^-2 g; the solve's gradient; Adam and UniformAdam."""
import numpy as np
import pytest
import torch

from pig.config import load_profile, load_section
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


def test_preconditioned_tensor_stores_and_returns_values():
    system, x0 = lattice_case()
    sub = PreconditionedTensor(x0, system, "substitute")
    torch.testing.assert_close(sub.param.detach(), system.apply(x0))
    torch.testing.assert_close(sub().detach(), x0, rtol=1e-12, atol=1e-12)
    new = torch.randn_like(x0)
    sub.set_value(new)
    torch.testing.assert_close(sub().detach(), new, rtol=1e-12, atol=1e-12)
    plain = PreconditionedTensor(x0, None, "none")
    assert plain() is plain.param
    with pytest.raises(ValueError, match="needs a linear system"):
        PreconditionedTensor(x0, None, "filter")
    with pytest.raises(ValueError, match="form"):
        PreconditionedTensor(x0, system, "sobolev")


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
    cfg = load_section(load_profile("paper"), "precond", PrecondConfig)
    field_cfg = load_section(load_profile("paper"), "field", FieldConfig)
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

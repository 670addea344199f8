"""The DCT lattice solve against scipy's DCT and a dense float64 solve of an independently built Laplacian."""
import itertools

import numpy as np
import pytest
import scipy.fft
import torch

from pig.field.lattice_solve import LatticeSystem, dct_iii, dct_ii, dct_matrix

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
METHODS = ["matmul", "fft"]


def dense_lattice_laplacian(shape) -> np.ndarray:
    """Free-boundary 6-neighbour Laplacian, built by visiting every vertex and its in-grid neighbours."""
    n = int(np.prod(shape))
    lap = np.zeros((n, n))
    for idx in itertools.product(*(range(s) for s in shape)):
        i = np.ravel_multi_index(idx, shape)
        for axis, step in itertools.product(range(3), (-1, 1)):
            nb = list(idx)
            nb[axis] += step
            if 0 <= nb[axis] < shape[axis]:
                lap[i, i] += 1.0
                lap[i, np.ravel_multi_index(nb, shape)] -= 1.0
    return lap


def dense_solve(shape, lam, b: np.ndarray) -> np.ndarray:
    """Solve channel-wise for b (C, *shape) with the dense system in float64."""
    a = np.eye(int(np.prod(shape))) + lam * dense_lattice_laplacian(shape)
    return np.linalg.solve(a, b.reshape(b.shape[0], -1).T).T.reshape(b.shape)


@pytest.mark.parametrize("n", [1, 2, 3, 4, 7, 8, 17])
@pytest.mark.parametrize("dim", [0, 1, -1])
def test_dct_matches_scipy(n, dim, rng):
    x = rng.normal(size=(3, n, 5)) if dim != -1 else rng.normal(size=(3, 5, n))
    axis = 1 if dim == 0 else dim
    xt = torch.from_numpy(x).movedim(axis, 0) if dim == 0 else torch.from_numpy(x)
    x_np = xt.numpy()
    ref2 = scipy.fft.dct(x_np, type=2, norm="ortho", axis=dim)
    ref3 = scipy.fft.dct(x_np, type=3, norm="ortho", axis=dim)
    torch.testing.assert_close(dct_ii(xt, dim), torch.from_numpy(ref2), rtol=0, atol=1e-13)
    torch.testing.assert_close(dct_iii(xt, dim), torch.from_numpy(ref3), rtol=0, atol=1e-13)
    mat = dct_matrix(n)
    torch.testing.assert_close(mat, torch.from_numpy(scipy.fft.dct(np.eye(n), type=2, norm="ortho", axis=0)), rtol=0, atol=1e-14)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("shape", [(1, 1, 1), (2, 3, 1), (4, 4, 4), (8, 24, 5)])
@pytest.mark.parametrize("lam", [0.0, 0.5, 2.0, 37.0])
def test_solve_matches_dense_float64(method, shape, lam, rng):
    b = rng.normal(size=(2, *shape))
    x = LatticeSystem(shape, lam, method).solve(torch.from_numpy(b)).numpy()
    ref = dense_solve(shape, lam, b)
    assert np.linalg.norm(x - ref) / np.linalg.norm(ref) < 1e-10


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape", [(1, 1, 1), (2, 1, 1), (5, 3, 2)])
@pytest.mark.parametrize("lam", [0.0, 1.0, 8.0, 1e6, 1e8])
def test_solve_is_exact_to_rounding_for_any_lambda(method, dtype, shape, lam, rng):
    """Against L's float64 eigendecomposition (whose accuracy, unlike a dense solve's, does not depend on
    lambda): the DCT solve is orthogonal transforms and a diagonal <= 1, so its error is a few eps |b|."""
    b = rng.normal(size=(2, *shape)) + 3.0  # a mean, as features and positions have
    mu, v = np.linalg.eigh(dense_lattice_laplacian(shape))
    mu = np.where(mu < 1e-9, 0.0, mu)
    cols = b.reshape(2, -1).T
    ref = (v @ ((v.T @ cols) / (1.0 + lam * mu)[:, None])).T.reshape(b.shape)
    x = LatticeSystem(shape, lam, method).solve(torch.from_numpy(b).to(dtype))
    assert x.dtype == dtype
    error = np.linalg.norm((x.double().numpy() - ref).reshape(2, -1), axis=1)
    assert np.all(error <= 20 * torch.finfo(dtype).eps * np.linalg.norm(b.reshape(2, -1), axis=1))


@pytest.mark.parametrize("shape", [(1, 1, 1), (3, 1, 2), (5, 4, 3)])
def test_apply_matches_dense(shape, rng):
    x = rng.normal(size=(3, *shape))
    lam = 1.7
    dense = np.eye(int(np.prod(shape))) + lam * dense_lattice_laplacian(shape)
    ref = (dense @ x.reshape(3, -1).T).T.reshape(x.shape)
    np.testing.assert_allclose(LatticeSystem(shape, lam).apply(torch.from_numpy(x)).numpy(), ref, rtol=0, atol=1e-12)


@pytest.mark.parametrize("method", METHODS)
def test_lambda_zero_is_identity(method):
    b = torch.randn(4, 6, 7, 3)
    assert torch.equal(LatticeSystem((6, 7, 3), 0.0, method).solve(b), b)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_huge_lambda_projects_onto_the_mean(device, method, dtype):
    shape = (8, 24, 5)
    gen = torch.Generator().manual_seed(1)
    b = torch.randn(3, *shape, generator=gen, dtype=torch.float64)
    x = LatticeSystem(shape, 1e8, method).solve(b.to(device=device, dtype=dtype)).double().cpu()
    assert torch.isfinite(x).all()
    mean = b.mean(dim=(-3, -2, -1), keepdim=True).expand_as(b)
    # Every non-constant mode is damped at least by 1 / (1 + 1e8 mu_min), mu_min = 4 sin^2(pi / 48).
    damping = 1.0 / (1.0 + 1e8 * 4 * np.sin(np.pi / 48) ** 2)
    rounding = (1e-6 if dtype == torch.float32 else 1e-13) * b.norm()
    assert (x - mean).norm() <= (b - mean).norm() * damping * (1 + 1e-6) + rounding


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("lam", [2.0, 1e4, 1e8])
def test_float32_agrees_with_float64(device, method, lam):
    shape = (9, 6, 11)
    b = torch.randn(16, *shape, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    system = LatticeSystem(shape, lam, method)
    x64 = system.solve(b.to(device)).cpu()
    x32 = system.solve(b.to(device=device, dtype=torch.float32)).double().cpu()
    assert torch.isfinite(x32).all()
    assert ((x32 - x64).norm() / x64.norm()).item() < 1e-5


def test_methods_agree_on_a_level_sized_grid():
    b = torch.randn(16, 24, 24, 24, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    x_mm = LatticeSystem((24, 24, 24), 2.5, "matmul").solve(b)
    x_fft = LatticeSystem((24, 24, 24), 2.5, "fft").solve(b)
    assert ((x_mm - x_fft).norm() / x_mm.norm()).item() < 1e-13
    residual = LatticeSystem((24, 24, 24), 2.5).apply(x_mm) - b
    assert (residual.norm() / b.norm()).item() < 1e-13


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="grid shape"):
        LatticeSystem((4, 4, 4), 1.0).solve(torch.zeros(2, 4, 4, 5))
    with pytest.raises(ValueError, match="lambda"):
        LatticeSystem((4, 4, 4), -1.0)
    with pytest.raises(ValueError, match="method"):
        LatticeSystem((4, 4, 4), 1.0, "cholesky")

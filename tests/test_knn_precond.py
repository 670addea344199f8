"""KNN graph against brute force; factorised and CG solves against a dense float64 solve; stiff and degenerate graphs."""
import warnings

import numpy as np
import pytest
import torch

from pig.field.knn_graph import graph_laplacian, knn_adjacency, knn_laplacian
from pig.field.knn_solve import CGNotConverged, CGSystem, FactorizedSystem
from pig.field.precondition import PrecondConfig, knn_system

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


def brute_force_adjacency(points: np.ndarray, k: int) -> np.ndarray:
    """Dense symmetrised KNN adjacency from all pairwise distances (points in general position)."""
    d = np.linalg.norm(points[:, None] - points[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    adj = np.zeros_like(d)
    for i, row in enumerate(d):
        adj[i, np.argsort(row)[: min(k, len(points) - 1)]] = 1.0
    return np.maximum(adj, adj.T)


def dense_system(laplacian, lam) -> np.ndarray:
    return np.eye(laplacian.shape[0]) + lam * laplacian.toarray()


def two_clusters(rng, n=60):
    a = rng.normal(size=(n, 3)) * 0.1
    return np.concatenate([a, a[: n // 2] + np.array([50.0, 0, 0])])


def eigen_solve(laplacian, lam, b: np.ndarray) -> np.ndarray:
    """A^-1 b from the eigendecomposition of L in float64: unlike a dense solve of I + lambda L, its error
    does not grow with lambda (the null space, the components' indicators, is kept exactly at eigenvalue 0)."""
    mu, v = np.linalg.eigh(laplacian.toarray())
    mu = np.where(mu < 1e-9, 0.0, mu)  # a graph's nonzero eigenvalues here are > 1e-3
    return v @ ((v.T @ b) / (1.0 + lam * mu)[:, None])


# Graphs at the extremes: generic, disconnected, two anchors, one anchor (L = 0), and positions-like
# right-hand sides (a mean of metres, as the anchors' u has).
EXTREME_GRAPHS = {
    "random": lambda rng: rng.normal(size=(150, 3)),
    "two_clusters": two_clusters,
    "two_anchors": lambda rng: rng.normal(size=(2, 3)),
    "one_anchor": lambda rng: rng.normal(size=(1, 3)),
}
LAMBDAS = [0.0, 1.0, 8.0, 1e6, 1e8]


@pytest.mark.parametrize("k", [1, 3, 7])
def test_adjacency_matches_brute_force(k, rng):
    points = rng.normal(size=(80, 3))
    np.testing.assert_array_equal(knn_adjacency(points, k).toarray(), brute_force_adjacency(points, k))


def test_duplicates_are_neighbours_without_self_loops(rng):
    base = rng.normal(size=(20, 3))
    points = np.concatenate([base, base[:5], base[:5], base[:1], base[:1], base[:1]])  # point 0 appears 6 times
    k = 4
    adj = knn_adjacency(points, k).toarray()
    assert np.all(np.diag(adj) == 0)
    np.testing.assert_array_equal(adj, adj.T)
    assert set(np.unique(adj)) <= {0.0, 1.0}
    assert np.all(adj.sum(axis=1) >= k)
    copies = np.flatnonzero(np.all(points == points[0], axis=1))
    assert len(copies) == 6
    for i in copies:  # the five other copies at distance 0 outrank every other point
        assert adj[i, copies].sum() >= k


@pytest.mark.parametrize("k", [5, 6, 50])
def test_k_at_least_n_gives_the_complete_graph(k, rng):
    points = rng.normal(size=(6, 3))
    np.testing.assert_array_equal(knn_adjacency(points, k).toarray(), 1.0 - np.eye(6))


def test_single_point_and_k_zero_give_the_empty_graph(rng):
    assert knn_laplacian(rng.normal(size=(1, 3)), 8).nnz == 0
    assert knn_laplacian(rng.normal(size=(10, 3)), 0).nnz == 0


def test_laplacian_rows_sum_to_zero_and_is_psd(rng):
    lap = knn_laplacian(two_clusters(rng), 5).toarray()
    np.testing.assert_allclose(lap.sum(axis=1), 0.0, atol=0)
    assert np.linalg.eigvalsh(lap).min() > -1e-10
    np.testing.assert_array_equal(graph_laplacian(np.array([[0.0, 1.0], [1.0, 0.0]])).toarray(), [[1.0, -1.0], [-1.0, 1.0]])


def test_disconnected_clusters_have_no_cross_edges(rng):
    points = two_clusters(rng)
    adj = knn_adjacency(points, 5).toarray()
    assert adj[:60, 60:].sum() == 0
    # Two components: the Laplacian has a two-dimensional null space.
    eig = np.linalg.eigvalsh(graph_laplacian(adj).toarray())
    assert np.sum(eig < 1e-9) == 2


@pytest.mark.parametrize("lam", [0.0, 0.3, 8.0, 1e3])
def test_factorized_matches_dense_float64(lam, rng):
    lap = knn_laplacian(two_clusters(rng), 6)
    b = rng.normal(size=(lap.shape[0], 3))
    ref = np.linalg.solve(dense_system(lap, lam), b)
    x = FactorizedSystem(lap, lam).solve(torch.from_numpy(b)).numpy()
    assert np.linalg.norm(x - ref) / np.linalg.norm(ref) < 1e-10


def test_apply_matches_dense(rng):
    lap = knn_laplacian(rng.normal(size=(40, 3)), 5)
    x = rng.normal(size=(40, 2))
    ref = dense_system(lap, 3.0) @ x
    for system in (FactorizedSystem(lap, 3.0), CGSystem(lap, 3.0)):
        np.testing.assert_allclose(system.apply(torch.from_numpy(x)).numpy(), ref, rtol=0, atol=1e-12)


@pytest.mark.parametrize("graph", EXTREME_GRAPHS)
@pytest.mark.parametrize("lam", LAMBDAS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_solvers_meet_their_tolerance_up_to_lambda_1e8(graph, lam, dtype, rng):
    """CG: error <= tol |b| per column (every eigenvalue of A is >= 1, so error <= residual); factorised:
    float64 rounding, which grows like eps lambda |L| (1e-15 lambda |b|). float32 adds the rounding of the returned x."""
    points = EXTREME_GRAPHS[graph](rng)
    lap = knn_laplacian(points, 8)
    b = points + 0.1 * rng.normal(size=points.shape) + np.array([0.5, 1.0, -2.0])
    ref = eigen_solve(lap, lam, b)
    rounding = 2 * torch.finfo(dtype).eps * np.linalg.norm(ref, axis=0)
    tol = 1e-5
    cg = CGSystem(lap, lam, tol=tol, max_iter=2000)
    with warnings.catch_warnings():
        warnings.simplefilter("error", CGNotConverged)
        x_cg = cg.solve(torch.from_numpy(b).to(dtype))
    x_fact = FactorizedSystem(lap, lam).solve(torch.from_numpy(b).to(dtype))
    assert x_cg.dtype == x_fact.dtype == dtype
    error = lambda x: np.linalg.norm(x.double().numpy() - ref, axis=0)  # noqa: E731
    b_norm = np.linalg.norm(b, axis=0)
    assert np.all(error(x_cg) <= tol * b_norm + rounding)
    assert cg.last_residual <= tol
    assert np.all(error(x_fact) <= (1e-14 + 1e-15 * lam) * b_norm + rounding)


def test_cg_apply_is_exact_where_assembled_float32_loses_the_identity(rng):
    """A x = x + lambda (L x) in float64: at lambda = 1e8, 1 + lambda d_i is not a float32 number."""
    points = rng.normal(size=(40, 3))
    lap = knn_laplacian(points, 5)
    x = torch.from_numpy(rng.normal(size=(40, 3))).float()
    for system in (CGSystem(lap, 1e8), FactorizedSystem(lap, 1e8)):
        ax = system.apply(x)
        assert ax.dtype == torch.float32
        ref = dense_system(lap, 1e8) @ x.double().numpy()  # exact up to float64 rounding of integers < 2^53
        np.testing.assert_allclose(ax.double().numpy(), ref, rtol=2 * np.finfo(np.float32).eps, atol=0)


def test_cg_warns_when_float64_rounding_bars_its_tolerance(rng):
    """At lambda = 1e8 the float64 residual cannot drop much below 1e-7 |b|: a tol of 1e-12 is unreachable."""
    lap = knn_laplacian(rng.normal(size=(100, 3)), 8)
    system = CGSystem(lap, 1e8, tol=1e-12, max_iter=150)
    with pytest.warns(CGNotConverged, match="iteration cap"):
        system.solve(torch.from_numpy(rng.normal(size=(100, 3))))
    assert system.last_iterations == 150 and system.last_residual > 1e-12


def test_cg_warm_start_saves_iterations_per_slot(rng):
    lap = knn_laplacian(rng.normal(size=(400, 3)), 8)
    system = CGSystem(lap, 8.0, tol=1e-8, max_iter=1000)
    b = torch.from_numpy(rng.normal(size=(400, 3)))
    system.solve(b, slot="forward")
    cold = system.last_iterations
    system.solve(b, slot="forward")
    assert system.last_iterations == 0
    system.solve(b + 1e-3 * torch.from_numpy(rng.normal(size=(400, 3))), slot="forward")
    assert 0 < system.last_iterations < cold
    system.solve(-b, slot="backward")  # another slot starts cold
    assert system.last_iterations == cold


def test_cg_cap_is_reported(rng):
    lap = knn_laplacian(rng.normal(size=(300, 3)), 8)
    system = CGSystem(lap, 100.0, tol=1e-12, max_iter=3)
    with pytest.warns(CGNotConverged, match="iteration cap"):
        system.solve(torch.from_numpy(rng.normal(size=(300, 2))))
    assert system.last_iterations == 3 and system.last_residual > 1e-12
    # Every miss is reported: each message carries its residual, so Python's once-per-message filter never hides one.
    with warnings.catch_warnings(record=True) as caught:
        for _ in range(3):
            system.solve(torch.from_numpy(rng.normal(size=(300, 2))))
    assert sum(issubclass(w.category, CGNotConverged) for w in caught) == 3


def test_cg_zero_column_is_zero_without_warning(rng):
    lap = knn_laplacian(rng.normal(size=(50, 3)), 4)
    system = CGSystem(lap, 8.0, tol=1e-10, max_iter=500)
    b = torch.zeros(50, 2, dtype=torch.float64)
    b[:, 0] = torch.from_numpy(rng.normal(size=50))
    system.solve(b)  # leaves a nonzero warm start for column 1 ...
    b[:, 1] = 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        x = system.solve(b)  # ... which must not stop column 1 from being exactly zero
    assert torch.equal(x[:, 1], torch.zeros(50, dtype=torch.float64))


def test_huge_lambda_projects_onto_component_means(rng):
    points = two_clusters(rng)
    lap = knn_laplacian(points, 5)
    b = rng.normal(size=(len(points), 3))
    x = FactorizedSystem(lap, 1e8).solve(torch.from_numpy(b)).numpy()
    proj = np.concatenate([np.repeat(b[:60].mean(0, keepdims=True), 60, 0), np.repeat(b[60:].mean(0, keepdims=True), 30, 0)])
    assert np.linalg.norm(x - proj) / np.linalg.norm(proj) < 1e-5


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("solver", ["factorized", "cg"])
def test_float32_configured_systems_are_accurate_up_to_lambda_1e8(device, solver, rng):
    points = rng.normal(size=(200, 3))
    b = torch.from_numpy(rng.normal(size=(200, 3)) + 1.0).float().to(device)
    b64 = b.double().cpu().numpy()
    lap = knn_laplacian(points, 8)
    for lam in (1.0, 1e4, 1e6, 1e8):
        cfg = PrecondConfig(anchor_lambda=lam, knn_solver=solver, knn_k=8, cg_tol=1e-5, cg_max_iter=300)
        system = knn_system(torch.from_numpy(points), cfg)
        with warnings.catch_warnings():
            warnings.simplefilter("error", CGNotConverged)
            x = system.solve(b)
        assert x.dtype == torch.float32 and x.device == b.device
        error = np.linalg.norm(x.double().cpu().numpy() - eigen_solve(lap, lam, b64), axis=0)
        assert np.all(error <= 1.1e-5 * np.linalg.norm(b64, axis=0))


def test_bad_input_is_named(rng):
    lap = knn_laplacian(rng.normal(size=(10, 3)), 3)
    with pytest.raises(ValueError, match="10 rows"):
        FactorizedSystem(lap, 1.0).solve(torch.zeros(9, 3))
    with pytest.raises(ValueError, match="lambda"):
        CGSystem(lap, -2.0)
    with pytest.raises(ValueError, match="finite points"):
        knn_adjacency(np.full((4, 3), np.nan), 2)

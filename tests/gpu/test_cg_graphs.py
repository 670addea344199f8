"""`precond.cg_graphs`: CG blocks replayed as CUDA graphs give the iterates of the launched path.

Run on the GPU machine (skipped without CUDA). The graph replays the same kernels on the same values, so the
solution and the iteration count must match the launched path exactly up to reduction order (bound 1e-12).
"""
import numpy as np
import pytest
import torch

from pig.field.knn_graph import knn_laplacian
from pig.field.knn_solve import CGSystem

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA"),
]


@pytest.mark.parametrize("compiled", [False, True])
@pytest.mark.parametrize("lam", [0.0, 8.0, 1e4])
def test_graph_replayed_cg_matches_launched_cg_and_dense_solve(compiled, lam):
    rng = np.random.default_rng(0)
    points = rng.normal(size=(300, 3))
    lap = knn_laplacian(points, 6)
    exact_system = np.eye(300) + lam * lap.toarray()
    launched = CGSystem(lap, lam, tol=1e-9, max_iter=200, check_every=8, compiled=compiled)
    graphed = CGSystem(lap, lam, tol=1e-9, max_iter=200, check_every=8, compiled=compiled, graphs=True)
    for step in range(3):  # warm starts: later solves begin from the graph's previous (cloned) solution
        b = torch.tensor(rng.normal(size=(300, 3)), device="cuda")
        b[:, 2] = 0 if step == 1 else b[:, 2]
        x_launched, x_graphed = launched.solve(b, slot="s"), graphed.solve(b, slot="s")
        assert graphed.last_iterations == launched.last_iterations
        torch.testing.assert_close(x_graphed, x_launched, rtol=1e-12, atol=1e-12 * float(x_launched.abs().max()))
        error = np.linalg.norm(x_graphed.cpu().numpy() - np.linalg.solve(exact_system, b.cpu().numpy()), axis=0)
        assert (error <= 1e-9 * np.linalg.norm(b.cpu().numpy(), axis=0) + 1e-14).all()
    assert len(graphed._graphs) == 1  # one capture per right-hand-side shape and block length

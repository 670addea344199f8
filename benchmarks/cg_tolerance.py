"""CG iterations and error against its tolerance on the anchors' KNN system (I + lambda L_knn, Eq. 5), the paper's size.

    python benchmarks/cg_tolerance.py [--anchors 100000] [--k 8] [--lam 8]

Body-like surface points (benchmarks/precond.py); right-hand sides of unit normal entries, solved cold and then
warm-started on the same right-hand side moved by 5 % (the fit's slots reuse the last solution). Error is relative to
the sparse factorisation's solve. Iteration counts do not depend on the machine: they say what a looser
`precond.cg_tol` saves on the GPU, where the anchors' solves cost most of `pig`'s extra time a step (run28).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

from pig.field.knn_graph import knn_laplacian
from pig.field.knn_solve import CGSystem, FactorizedSystem

sys.path.insert(0, str(Path(__file__).parent))
from precond import body_surface  # noqa: E402


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--anchors", type=int, default=100_000)
    parser.add_argument("--k", type=int, default=8)
    parser.add_argument("--lam", type=float, default=8.0)
    parser.add_argument("--tols", type=float, nargs="+", default=[1e-5, 1e-4, 1e-3, 1e-2])
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    laplacian = knn_laplacian(body_surface(args.anchors, rng).astype(np.float64), args.k)
    exact = FactorizedSystem(laplacian, args.lam)
    print(f"{args.anchors} anchors, k = {args.k}, lambda = {args.lam}")
    print("| tol | cold iterations | cold rel. error | warm iterations | warm rel. error |\n|---|---|---|---|---|")
    for tol in args.tols:
        cg = CGSystem(laplacian, args.lam, tol=tol, max_iter=1000)
        row = []
        b = torch.from_numpy(rng.normal(size=(args.anchors, 3)).astype(np.float32))
        for rhs in (b, b + 0.05 * torch.from_numpy(rng.normal(size=b.shape).astype(np.float32))):
            x, reference = cg.solve(rhs, "anchors"), exact.solve(rhs)
            row += [str(cg.last_iterations), f"{float((x - reference).norm() / reference.norm()):.1e}"]
        print(f"| {tol:g} | " + " | ".join(row) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

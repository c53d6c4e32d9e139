"""Benchmarks of prtlab.pca: least-squares weight solves and reconstruction (Iwasaki 2007, Sec. 5.2)."""

from __future__ import annotations

import numpy as np

from prtlab.bench import case
from prtlab.pca import WeightSolver


@case("pca.weights.50k_vertices.N16")
def weights_50k(quick: bool) -> dict:
    """Weights of a batch of intensity distributions with the precomputed A^-1, then reconstruction."""
    n_vertices, n_basis = 50_000, 16
    batch = 16 if quick else 64
    rng = np.random.default_rng(0)
    basis = rng.normal(size=(n_basis, n_vertices))
    solver = WeightSolver.from_basis(basis)
    values = rng.normal(size=(batch, n_vertices))

    def run():
        w = solver.solve(values)
        return w @ basis

    def peer():
        w = np.linalg.lstsq(basis.T, values.T, rcond=None)[0]
        return w.T @ basis

    return {
        "run": run,
        "gflop": 4.0 * n_basis * n_vertices * batch / 1e9,  # P L (2 N S B) + w Psi (2 N S B)
        "items": batch,
        "peer": ("numpy lstsq", peer),
    }

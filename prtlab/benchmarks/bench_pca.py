"""Benchmarks of prtlab.pca: least-squares weight solves and reconstruction (Iwasaki 2007, Sec. 5.2).

Two cases, each timing the same work on both sides: per frame, the weights of a batch of intensity
distributions from a projector precomputed outside the timer (ours ``P = A^-1 Psi``, the peer numpy's
``pinv``), then the reconstruction; and a one-off solve that builds its solver inside the timer (ours
``WeightSolver.from_basis`` then ``solve``, the peer ``numpy.linalg.lstsq``).
"""

from __future__ import annotations

import numpy as np

from prtlab.bench import case, check_same_work, floor
from prtlab.pca import WeightSolver

N_VERTICES, N_BASIS = 50_000, 16


def _inputs(quick: bool):
    batch = 16 if quick else 64
    rng = np.random.default_rng(0)
    basis = rng.normal(size=(N_BASIS, N_VERTICES))
    values = rng.normal(size=(batch, N_VERTICES))
    return basis, values


@case("pca.weights.50k_vertices.N16")
def weights_50k(quick: bool) -> dict:
    """Per frame: weights with a precomputed projector, then the reconstruction ``w Psi``."""
    basis, values = _inputs(quick)
    solver = WeightSolver.from_basis(basis)
    projector_t = np.ascontiguousarray(np.linalg.pinv(basis.T).T)  # (S, N): w = L @ pinv(Psi^T)^T

    def run():
        return solver.solve(values) @ basis

    def peer():
        return (values @ projector_t) @ basis

    check_same_work(run(), peer(), "pca.weights", rtol=1e-8, atol=1e-10)
    return {
        "run": run,
        "gflop": 4.0 * N_BASIS * N_VERTICES * len(values) / 1e9,  # P L (2 N S B) + w Psi (2 N S B)
        "items": len(values),
        "peer": ("numpy pinv projector (precomputed) GEMM", peer),
        # floor: the two products (4 N S B flops); the projector and the basis read once, the intensities read
        # and the reconstruction written (8 (2 N S + 2 B S) bytes)
        "floor": floor(4.0 * N_BASIS * N_VERTICES * len(values), 8.0 * (2 * N_BASIS + 2 * len(values)) * N_VERTICES,
                       "4 N S B flops; 8 (2 N S + 2 B S) bytes"),
    }


@case("pca.solve_once.50k_vertices.N16")
def solve_once_50k(quick: bool) -> dict:
    """One solve from scratch: the solver built from the basis inside the timer, then the weights."""
    basis, values = _inputs(quick)

    def run():
        return WeightSolver.from_basis(basis).solve(values)

    def peer():
        return np.linalg.lstsq(basis.T, values.T, rcond=None)[0].T

    check_same_work(run(), peer(), "pca.solve_once", rtol=1e-8, atol=1e-10)
    return {"run": run, "gflop": None, "items": len(values), "peer": ("numpy lstsq", peer)}

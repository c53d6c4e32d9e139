"""PCA basis functions, least-squares weights and the basis comparison of the Iwasaki journal paper.

Fit a basis of an object's surface intensity from point-light renders
(:func:`fit_pca_basis`, Iwasaki et al. 2007 Sec. 4.2) and solve the weights of
any intensity distribution with the precomputed ``A^{-1}`` (:class:`PCABasis`
``.weights`` / :func:`solve_weights`, Sec. 5.2).
"""

from ._basis import PCABasis, fit_pca_basis, pca_light_positions, point_light_intensity
from ._weights import WeightSolver, reconstruct, solve_weights

__all__ = [
    "PCABasis",
    "fit_pca_basis",
    "pca_light_positions",
    "point_light_intensity",
    "WeightSolver",
    "solve_weights",
    "reconstruct",
]

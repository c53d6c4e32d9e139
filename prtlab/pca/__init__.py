"""PCA basis functions, least-squares weights and the basis comparison of the Iwasaki journal paper.

Fit a basis of an object's surface intensity from point-light renders
(:func:`fit_pca_basis`, Iwasaki et al. 2007 Sec. 4.2) and solve the weights of
any intensity distribution with the precomputed ``A^{-1}`` (:class:`PCABasis`
``.weights`` / :func:`solve_weights`, Sec. 5.2). The journal paper's comparison
of SH, Haar, Fourier cosine and PCA bases over a (u, v) parameterisation
(:func:`surface_uv`, :func:`uv_basis`, :func:`compare_bases`) lives here too.
"""

from ._basis import (
    PCABasis,
    fit_pca_basis,
    pca_light_positions,
    point_light_intensity,
    principal_basis,
    untied_count,
)
from ._compare import (
    COMPARISON_BASES,
    BasisComparison,
    area_light_intensity,
    compare_bases,
    fourier_cosine_indices,
    uv_basis,
)
from ._param import SurfaceParam, surface_uv
from ._weights import WeightSolver, reconstruct, solve_weights

__all__ = [
    "PCABasis",
    "fit_pca_basis",
    "principal_basis",
    "untied_count",
    "pca_light_positions",
    "point_light_intensity",
    "WeightSolver",
    "solve_weights",
    "reconstruct",
    "SurfaceParam",
    "surface_uv",
    "COMPARISON_BASES",
    "BasisComparison",
    "uv_basis",
    "fourier_cosine_indices",
    "compare_bases",
    "area_light_intensity",
]

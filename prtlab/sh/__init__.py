"""Real spherical and zonal harmonics: evaluation, projection, rotation, products, exp/log.

Conventions, used throughout prtlab: real orthonormal basis, index
``i = l*l + l + m``, ``Y_1,-1 = c y, Y_1,0 = c z, Y_1,1 = c x``; "order n"
means bands ``l = 0..n-1`` (``n*n`` coefficients); colour is a trailing axis.
"""

from ._eval import basis, basis_reference, evaluate, index, n_coeffs
from ._explog import blocker_log_zh, blocker_zh, exp, log
from ._gaunt import GauntTensor, gaunt_tensor
from ._product import product, product_exact, product_matrix, triple_integral
from ._project import project, project_cubemap, project_equirect, project_function, quadrature
from ._rotate import rotate, rotation_matrices, rotation_matrix
from ._window import apply_window, is_nonnegative, min_value, nonnegative_window, window
from ._zh import clamped_cosine_zh, convolve, irradiance, zh_project, zh_rotate

__all__ = [
    # evaluation
    "basis",
    "basis_reference",
    "evaluate",
    "index",
    "n_coeffs",
    # projection
    "project",
    "project_cubemap",
    "project_equirect",
    "project_function",
    "quadrature",
    # rotation
    "rotate",
    "rotation_matrices",
    "rotation_matrix",
    # zonal harmonics
    "clamped_cosine_zh",
    "convolve",
    "irradiance",
    "zh_project",
    "zh_rotate",
    # products (Gaunt tensor)
    "GauntTensor",
    "gaunt_tensor",
    "product",
    "product_exact",
    "product_matrix",
    "triple_integral",
    # exponential and logarithm (Ren et al. 2006)
    "blocker_log_zh",
    "blocker_zh",
    "exp",
    "log",
    # windowing
    "apply_window",
    "is_nonnegative",
    "min_value",
    "nonnegative_window",
    "window",
]

"""Real spherical and zonal harmonics: evaluation, projection, rotation, products, exp/log.

Conventions (``../shared/DESIGN.md``): real orthonormal basis, index
``i = l*l + l + m``, ``Y_1,-1 = c y, Y_1,0 = c z, Y_1,1 = c x``; "order n"
means bands ``l = 0..n-1`` (``n*n`` coefficients); colour is a trailing axis.
"""

from ._eval import basis_reference

__all__ = [
    "basis_reference",
]

"""2D Haar wavelets on cubemaps: transforms, non-linear approximation, triple products,
pulse basis with 8-bit quantisation and sparse per-vertex transfer.

Conventions: cubemaps are ``(..., 6, r, r)`` (faces +X, -X, +Y, -Y, +Z, -Z,
OpenGL orientation, from :mod:`prtlab.geometry`), ``r`` a power of two. Haar
coefficients are those of the orthonormal non-standard transform of the
texel values (texel space: ``sum x y = sum haar2d(x) haar2d(y)``), in the
in-place quadtree layout of :func:`haar2d`. Integrals of products
(:func:`triple_product`) are over the faces' parameter squares ``[0, 1]^2``
(Ng et al. 2004) unless ``measure="solid_angle"``.
"""

from ._approx import energy_kept, keep_largest
from ._haar import coefficient_levels, haar2d, ihaar2d, solid_angle_weight, support_solid_angles
from ._quantize import Quantized8, SparseTransfer, dequantize8, encode_transfer, quantize8
from ._triple import product, triple_product, tripling_coefficient

__all__ = [
    # transforms
    "haar2d",
    "ihaar2d",
    "coefficient_levels",
    "solid_angle_weight",
    "support_solid_angles",
    # non-linear approximation (Ng et al. 2003)
    "keep_largest",
    "energy_kept",
    # triple products and products (Ng et al. 2004)
    "triple_product",
    "product",
    "tripling_coefficient",
    # pulse basis, 8-bit quantisation, sparse transfer (Yue et al. 2009)
    "Quantized8",
    "quantize8",
    "dequantize8",
    "SparseTransfer",
    "encode_transfer",
]

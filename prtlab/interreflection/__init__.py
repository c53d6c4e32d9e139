"""Iwasaki et al. 2007: precomputed radiance transfer for dynamic scenes with interreflections.

Basis radiance fields of every object on its sample spheres (Sec. 4.3), basis
irradiance per receiver vertex (Eq. 13), weights by the precomputed ``A^{-1}``
(Eq. 14), first and multiple bounces (Eq. 12, Sec. 5.3), on the shadow fields
of :mod:`prtlab.shadowfields` for visibility and direct light.
``prtlab.shade(scene, method="interreflection", bounces=1)`` runs it.
"""

from ._fields import (
    StoredBasisRadiance,
    basis_radiance_at,
    basis_radiance_field,
    self_basis_irradiance,
    store_basis_radiance,
)
from ._passes import basis_irradiance, fit_weights, outgoing_radiance, reflected_light
from ._haar_fields import HaarBasisRadianceField, haar_basis_radiance_cubemaps, haar_basis_radiance_field
from ._haar_passes import (
    haar_basis_irradiance,
    haar_irradiance_bound,
    haar_transfer,
    near_basis_irradiance,
    texel_basis_irradiance,
)
from ._pipeline import PAPER_OPTIONS, Interreflection, InterreflectionOptions, precompute, shade_scene

__all__ = [
    # precomputation (Sec. 4.3)
    "basis_radiance_at",
    "basis_radiance_field",
    "self_basis_irradiance",
    "StoredBasisRadiance",
    "store_basis_radiance",
    # per-frame passes (Sec. 5)
    "basis_irradiance",
    "reflected_light",
    "fit_weights",
    "outgoing_radiance",
    # all-frequency basis radiance and irradiance (Sec. 4.3, Eq. 13 with Haar cubemaps)
    "HaarBasisRadianceField",
    "haar_basis_radiance_cubemaps",
    "haar_basis_radiance_field",
    "haar_transfer",
    "haar_basis_irradiance",
    "texel_basis_irradiance",
    "near_basis_irradiance",
    "haar_irradiance_bound",
    # the pipeline
    "Interreflection",
    "InterreflectionOptions",
    "PAPER_OPTIONS",
    "precompute",
    "shade_scene",
]

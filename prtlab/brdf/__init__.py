"""BRDFs and their separable approximation: Lambert, normalised Phong, ``f ~ sum_k g_k(wi) h_k(wo)``.

Conventions: the models are those of :class:`prtlab.scene.Material`
(``f = kd/pi + ks (e+2)/(2 pi) max(0, r . wo)^e``), two-sided; the local
frame has z = normal and the tangents of :func:`prtlab.geometry.tangent_frame`;
colour is a trailing axis.
"""

from ._models import Lambert, Phong, from_material, lambert, local_frame, phong, to_local, to_world
from ._project import project_g_cos, project_h, transfer_error
from ._separable import ErrorTable, SeparableBRDF, relative_error_table, separable

__all__ = [
    # models
    "Lambert",
    "Phong",
    "lambert",
    "phong",
    "from_material",
    # local frame
    "local_frame",
    "to_local",
    "to_world",
    # separable approximation (Kautz and McCool 1999)
    "SeparableBRDF",
    "separable",
    "ErrorTable",
    "relative_error_table",
    # SH projections (Iwasaki et al. 2007, Eq. 11-13)
    "project_g_cos",
    "project_h",
    "transfer_error",
]

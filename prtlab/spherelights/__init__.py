"""Guerrero, Jeschke, Wimmer 2008: spherical lights (issue 6).

Sphere-set fitting (Sec. 4.1) and the direct soft shadows of Ren et al. 2006
that the method builds on (Sec. 5.1, Eqs. 3-8).
"""

from ._fit import SphereFit, fit_spheres, sphere_set_coverage, sphere_set_figure
from ._shadows import adjust_blockers, blocker_log_sum, direct_irradiance, environment_transfer

__all__ = [
    "SphereFit",
    "fit_spheres",
    "sphere_set_coverage",
    "sphere_set_figure",
    # direct soft shadows (Ren et al. 2006)
    "adjust_blockers",
    "blocker_log_sum",
    "direct_irradiance",
    "environment_transfer",
]

"""Zhou et al. 2005 shadow fields: object occlusion fields on concentric spheres, self-visibility,
run-time visibility products and direct illumination per vertex.

Used by :mod:`prtlab.interreflection` (Iwasaki et al. 2007) for visibility and
the sample-sphere grid of its basis radiance fields.
"""

from ._grid import SphereGrid, bounding_sphere, interpolate_field, sphere_grid
from ._occlusion import DEFAULT_DEGREE, OcclusionField, occlusion_field, project_visibility, self_visibility

__all__ = [
    # sample spheres
    "SphereGrid",
    "bounding_sphere",
    "interpolate_field",
    "sphere_grid",
    # occlusion fields
    "DEFAULT_DEGREE",
    "OcclusionField",
    "occlusion_field",
    "project_visibility",
    "self_visibility",
]

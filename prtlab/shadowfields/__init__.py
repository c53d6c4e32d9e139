"""Zhou et al. 2005 shadow fields: object occlusion fields on concentric spheres, self-visibility,
run-time visibility products and direct illumination per vertex.

Used by :mod:`prtlab.interreflection` (Iwasaki et al. 2007) for visibility and
the sample-sphere grid of its basis radiance fields.
"""

from ._grid import SphereGrid, bounding_sphere, interpolate_field, sphere_grid
from ._direct import direct_pass, occluder_order, visibility_pass
from ._occlusion import DEFAULT_DEGREE, OcclusionField, occlusion_field, project_visibility, self_visibility
from ._sources import area_light_sh
from ._scene import direct_environment, precompute_scene, scene_visibility, separable_brdfs

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
    # run-time passes
    "occluder_order",
    "visibility_pass",
    "direct_pass",
    # local lights
    "area_light_sh",
    # whole scenes
    "precompute_scene",
    "scene_visibility",
    "separable_brdfs",
    "direct_environment",
]

"""Zhou et al. 2005 shadow fields: object occlusion fields on concentric spheres, self-visibility,
run-time visibility products and direct illumination per vertex; in SH (low frequency) and as
sparse Haar cubemaps (all frequency: :func:`haar_direct`, with exact area-light pieces and point lights).

Used by :mod:`prtlab.interreflection` (Iwasaki et al. 2007) for visibility and
the sample-sphere grid of its basis radiance fields.
"""

from ._grid import SphereGrid, bounding_sphere, interpolate_field, sphere_grid
from ._direct import direct_pass, occluder_order, visibility_pass
from ._occlusion import (DEFAULT_DEGREE, LOG_FLOOR, OcclusionField, log_occlusion_field, occlusion_field,
                         project_visibility, self_visibility)
from ._sources import (
    SourceRadianceField,
    area_light_sh,
    point_light_direct,
    sh_visibility_toward,
    source_radiance_field,
)
from ._haar import (
    DEFAULT_HAAR_RESOLUTION,
    DEFAULT_KEEP,
    HaarOcclusionField,
    SparseCubemaps,
    cubemap_frames,
    encode_sparse,
    haar_occlusion_field,
    haar_self_visibility,
    rotation_texel_map,
    visibility_cubemaps,
)
from ._haar_direct import (
    edge_bound,
    environment_cubemap,
    haar_direct,
    haar_direct_pass,
    haar_visibility_pass,
    light_pieces,
    texel_moments,
)

__all__ = [
    # sample spheres
    "SphereGrid",
    "bounding_sphere",
    "interpolate_field",
    "sphere_grid",
    # occlusion fields
    "DEFAULT_DEGREE",
    "LOG_FLOOR",
    "OcclusionField",
    "log_occlusion_field",
    "occlusion_field",
    "project_visibility",
    "self_visibility",
    # run-time passes
    "occluder_order",
    "visibility_pass",
    "direct_pass",
    # local lights
    "area_light_sh",
    "SourceRadianceField",
    "source_radiance_field",
    "point_light_direct",
    "sh_visibility_toward",
    # all-frequency (Haar cubemap) shadow fields
    "DEFAULT_HAAR_RESOLUTION",
    "DEFAULT_KEEP",
    "SparseCubemaps",
    "HaarOcclusionField",
    "encode_sparse",
    "visibility_cubemaps",
    "haar_occlusion_field",
    "haar_self_visibility",
    "rotation_texel_map",
    "cubemap_frames",
    "light_pieces",
    "texel_moments",
    "environment_cubemap",
    "haar_visibility_pass",
    "haar_direct_pass",
    "haar_direct",
    "edge_bound",
]

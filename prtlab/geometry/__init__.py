"""Geometry: sphere-image maps, meshes, transforms, ray casting and sampling."""

from ._meshes import BUILTIN_MESHES, DATA_DIR, builtin_mesh, load_mesh, normalize_mesh, subdivide
from ._raycast import RAY_CHUNK, RAY_EPSILON_SCALE, RayCaster, RayHits, offset_origins
from ._spheremaps import (
    CUBE_FACES,
    cubemap_directions,
    cubemap_lookup,
    cubemap_solid_angles,
    direction_to_cubemap,
    direction_to_equirect,
    equirect_directions,
    equirect_lookup,
    equirect_solid_angles,
)

__all__ = [
    "RAY_CHUNK",
    "RAY_EPSILON_SCALE",
    "RayCaster",
    "RayHits",
    "offset_origins",
    "BUILTIN_MESHES",
    "DATA_DIR",
    "builtin_mesh",
    "load_mesh",
    "normalize_mesh",
    "subdivide",
    "CUBE_FACES",
    "cubemap_directions",
    "cubemap_lookup",
    "cubemap_solid_angles",
    "direction_to_cubemap",
    "direction_to_equirect",
    "equirect_directions",
    "equirect_lookup",
    "equirect_solid_angles",
]

"""Scenes: the YAML format, materials, lights, environment maps, and shading results."""

from ._animation import matrix_to_euler, quaternion_from_matrix, quaternion_to_matrix, slerp
from ._envmap import (
    SUN_ANGULAR_RADIUS_DEG,
    constant_envmap,
    cubemap_to_equirect,
    environment_sh,
    equirect_to_cubemap,
    preetham_sky,
    preetham_sky_radiance,
    preetham_sky_xyY,
    preetham_sun_radiance,
    preetham_zenith_xyY,
    read_envmap,
    read_exr,
    read_hdr,
    sun_direction,
    write_exr,
    write_hdr,
    xyY_to_linear_srgb,
)
from ._load import DEGENERATE_AREA_RTOL, DEGENERATE_FACE_FRACTION, load_scene, save_scene
from ._result import ShadeResult
from ._scene import (
    AreaLight,
    Camera,
    EnvironmentLight,
    Material,
    PointLight,
    Scene,
    SceneObject,
    Transform,
    euler_to_matrix,
)
from ._validate import SceneError

__all__ = [
    "AreaLight",
    "Camera",
    "EnvironmentLight",
    "Material",
    "PointLight",
    "Scene",
    "SceneObject",
    "ShadeResult",
    "Transform",
    "euler_to_matrix",
    # scene files
    "load_scene",
    "save_scene",
    "SceneError",
    "DEGENERATE_FACE_FRACTION",
    "DEGENERATE_AREA_RTOL",
    # environment maps
    "read_envmap",
    "read_exr",
    "write_exr",
    "read_hdr",
    "write_hdr",
    "constant_envmap",
    "preetham_sky",
    "preetham_sky_radiance",
    "preetham_sky_xyY",
    "preetham_sun_radiance",
    "preetham_zenith_xyY",
    "sun_direction",
    "SUN_ANGULAR_RADIUS_DEG",
    "xyY_to_linear_srgb",
    "equirect_to_cubemap",
    "cubemap_to_equirect",
    "environment_sh",
    # animation
    "slerp",
    "quaternion_from_matrix",
    "quaternion_to_matrix",
    "matrix_to_euler",
]

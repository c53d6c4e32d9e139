"""Scenes: the YAML format, materials, lights, environment maps, and shading results."""

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
]

"""The in-memory scene: what every method and the Mitsuba reference read alike.

A :class:`Scene` is built from the YAML format of ``docs/SCENE_FORMAT.md`` by
:func:`prtlab.load_scene` / :meth:`Scene.from_dict` (``_load.py``), which
validate everything before any work starts. The classes here hold already
validated, float64 data.

Conventions: right-handed world, +Y up; object transforms are
``M = T @ R @ S`` with ``R = Rz @ Ry @ Rx`` (``rotate_deg = [rx, ry, rz]``, in
degrees, about the world axes, x first); radiance in linear RGB.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "Transform",
    "Material",
    "SceneObject",
    "EnvironmentLight",
    "AreaLight",
    "PointLight",
    "Camera",
    "Scene",
    "euler_to_matrix",
]


def _values_equal(a, b) -> bool:
    """Exact structural equality that understands arrays, meshes, dataclasses and containers."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        if a is None or b is None:
            return False
        a, b = np.asarray(a), np.asarray(b)
        return a.shape == b.shape and bool(np.array_equal(a, b))
    if hasattr(a, "vertices") and hasattr(a, "faces"):  # meshes: geometry and connectivity
        return hasattr(b, "vertices") and _values_equal(np.asarray(a.vertices), np.asarray(b.vertices)) and (
            _values_equal(np.asarray(a.faces), np.asarray(b.faces))
        )
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_values_equal(x, y) for x, y in zip(a, b))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_values_equal(a[k], b[k]) for k in a)
    return bool(a == b)


def _float_lists(obj, *names: str) -> dict:
    """``{name: list of floats}`` of the vector fields ``names`` of ``obj`` (for ``to_dict``)."""
    return {name: [float(c) for c in getattr(obj, name)] for name in names}


def _dataclass_eq(self, other, skip: tuple[str, ...] = ()) -> bool:
    if type(self) is not type(other):
        return NotImplemented
    from dataclasses import fields

    return all(_values_equal(getattr(self, f.name), getattr(other, f.name)) for f in fields(self) if f.name not in skip)


def euler_to_matrix(rotate_deg) -> np.ndarray:
    """Rotation matrix ``Rz @ Ry @ Rx`` from ``[rx, ry, rz]`` in degrees."""
    rx, ry, rz = np.radians(np.asarray(rotate_deg, dtype=np.float64))
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    r_x = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    r_y = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    r_z = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return r_z @ r_y @ r_x


@dataclass
class Transform:
    """Rigid transform with uniform scale: ``x -> translate + R @ (scale * x)``."""

    translate: np.ndarray = field(default_factory=lambda: np.zeros(3))
    rotate_deg: np.ndarray = field(default_factory=lambda: np.zeros(3))
    scale: float = 1.0

    @property
    def rotation(self) -> np.ndarray:
        """(3, 3) rotation matrix."""
        return euler_to_matrix(self.rotate_deg)

    def matrix(self) -> np.ndarray:
        """(4, 4) homogeneous matrix ``T @ R @ S``."""
        m = np.eye(4)
        m[:3, :3] = self.rotation * self.scale
        m[:3, 3] = self.translate
        return m

    def apply_points(self, points) -> np.ndarray:
        """(..., 3) object-space points to world space."""
        p = np.asarray(points, dtype=np.float64)
        return p @ (self.rotation * self.scale).T + self.translate

    def apply_normals(self, normals) -> np.ndarray:
        """(..., 3) object-space unit normals to world space (uniform scale: just rotate)."""
        return np.asarray(normals, dtype=np.float64) @ self.rotation.T

    def to_dict(self) -> dict:
        return {
            "translate": [float(v) for v in self.translate],
            "rotate_deg": [float(v) for v in self.rotate_deg],
            "scale": float(self.scale),
        }

    def __eq__(self, other):
        return _dataclass_eq(self, other)


@dataclass
class Material:
    """Lambertian (``type='diffuse'``) or normalised Phong (``type='phong'``).

    Phong: ``f(wi, wo) = kd / pi + ks (e + 2) / (2 pi) max(0, r . wo)^e`` with
    ``r`` the mirror reflection of ``wi`` about the normal and ``e`` the exponent.
    Both reflect on both sides of the surface.
    """

    type: str = "diffuse"
    albedo: np.ndarray = field(default_factory=lambda: np.full(3, 0.7))  # diffuse
    kd: np.ndarray | None = None  # phong
    ks: np.ndarray | None = None  # phong
    exponent: float | None = None  # phong

    @property
    def diffuse_albedo(self) -> np.ndarray:
        """(3,) the Lambertian part: ``albedo`` or ``kd``."""
        return self.kd if self.type == "phong" else self.albedo

    def to_dict(self) -> dict:
        if self.type == "phong":
            return {
                "type": "phong",
                "kd": [float(v) for v in self.kd],
                "ks": [float(v) for v in self.ks],
                "exponent": float(self.exponent),
            }
        return {"type": "diffuse", "albedo": [float(v) for v in self.albedo]}

    def __eq__(self, other):
        return _dataclass_eq(self, other)


@dataclass
class SceneObject:
    """A mesh in object space, placed in the world by ``transform``.

    ``mesh_spec`` is what the scene file said (a path relative to the scene
    file, or ``{"builtin": ...}``) so that the scene round-trips.
    """

    name: str
    mesh: Any  # trimesh.Trimesh in object space
    transform: Transform = field(default_factory=Transform)
    material: Material = field(default_factory=Material)
    dynamic: bool = False
    portal: bool = False
    mesh_spec: Any = None

    @property
    def n_vertices(self) -> int:
        return len(self.mesh.vertices)

    def world_vertices(self, transform: Transform | None = None) -> np.ndarray:
        """(n_vertices, 3) vertex positions in world space, in input order."""
        return (transform or self.transform).apply_points(self.mesh.vertices)

    def world_normals(self, transform: Transform | None = None) -> np.ndarray:
        """(n_vertices, 3) unit vertex normals in world space."""
        return (transform or self.transform).apply_normals(self.mesh.vertex_normals)

    def world_shading_points(self, transform: Transform | None = None) -> np.ndarray:
        """(n_vertices, 3) where each vertex is shaded: its world position moved a hair
        into its own faces (:func:`prtlab.geometry.shading_points`; ``docs/DECISIONS.md``)."""
        from prtlab.geometry import shading_points

        # computed in object space and placed like the vertices: the construction commutes
        # with rotation, uniform scale and translation
        local = shading_points(self.mesh.vertices, np.asarray(self.mesh.faces), self.mesh.vertex_normals)
        return (transform or self.transform).apply_points(local)

    def __eq__(self, other):
        return _dataclass_eq(self, other)

    def to_dict(self) -> dict:
        """The object as in a scene file (needs ``mesh_spec``: a file path or ``{builtin: ...}``)."""
        if self.mesh_spec is None:
            raise ValueError(
                f"object {self.name!r} has no mesh_spec, so it cannot be written to a scene file; "
                "export its mesh (mesh.export('name.ply')) and set mesh_spec='name.ply'"
            )
        import copy

        return {
            "name": self.name,
            "mesh": copy.deepcopy(self.mesh_spec),
            "transform": self.transform.to_dict(),
            "material": self.material.to_dict(),
            "dynamic": bool(self.dynamic),
            "portal": bool(self.portal),
        }

@dataclass
class EnvironmentLight:
    """Distant light from every direction, as an equirectangular map.

    ``image`` is ``(H, W, 3)`` linear radiance in the equirect convention of
    :mod:`prtlab.geometry` (exactly Mitsuba's ``envmap``), already multiplied
    by ``scale``; ``constant`` is set instead for a constant environment.
    ``spec`` is what the scene file said (``file``, ``sky`` or ``constant``).
    """

    image: np.ndarray | None = None
    constant: np.ndarray | None = None
    scale: float = 1.0
    spec: dict = field(default_factory=dict)

    def radiance(self, dirs) -> np.ndarray:
        """(..., 3) radiance arriving *from* world directions ``dirs`` (..., 3)."""
        dirs = np.asarray(dirs, dtype=np.float64)
        if self.constant is not None:
            return np.broadcast_to(self.constant, dirs.shape[:-1] + (3,)).copy()
        from prtlab.geometry import equirect_lookup

        return equirect_lookup(self.image, dirs)

    def __eq__(self, other):
        return _dataclass_eq(self, other)

    def to_dict(self) -> dict:
        """``{type: environment, file | sky | constant: ..., scale}`` as the scene file said."""
        if not self.spec:
            raise ValueError(
                "this environment light has no spec (it was built from an array), so it cannot be written "
                "to a scene file; save the image with prtlab.scene.write_exr and use {file: ...}"
            )
        import copy

        return {"type": "environment", **copy.deepcopy(self.spec), "scale": float(self.scale)}


@dataclass
class AreaLight:
    """Parallelogram ``center + s u + t v``, s, t in [-1, 1], emitting ``radiance``
    on the side of ``normalize(cross(u, v))`` only. It reflects nothing."""

    center: np.ndarray
    u: np.ndarray
    v: np.ndarray
    radiance: np.ndarray

    @property
    def normal(self) -> np.ndarray:
        n = np.cross(self.u, self.v)
        return n / np.linalg.norm(n)

    @property
    def area(self) -> float:
        return float(4.0 * np.linalg.norm(np.cross(self.u, self.v)))

    def to_dict(self) -> dict:
        return {"type": "area", **_float_lists(self, "center", "u", "v", "radiance")}

    def __eq__(self, other):
        return _dataclass_eq(self, other)


@dataclass
class PointLight:
    """Isotropic point light: irradiance ``intensity * cos / r^2``."""

    position: np.ndarray
    intensity: np.ndarray

    def to_dict(self) -> dict:
        return {"type": "point", **_float_lists(self, "position", "intensity")}

    def __eq__(self, other):
        return _dataclass_eq(self, other)


@dataclass
class Camera:
    """Pinhole camera; ``fov_deg`` is the vertical field of view, ``resolution`` is (width, height)."""

    position: np.ndarray = field(default_factory=lambda: np.array([0.0, 2.0, 6.0]))
    look_at: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.5, 0.0]))
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))
    fov_deg: float = 40.0
    resolution: tuple[int, int] = (512, 512)

    def to_dict(self) -> dict:
        return {
            **_float_lists(self, "position", "look_at", "up"),
            "fov_deg": float(self.fov_deg),
            "resolution": [int(r) for r in self.resolution],
        }

    def __eq__(self, other):
        return _dataclass_eq(self, other)


@dataclass
class Scene:
    """Objects, lights, camera and optional animation of one scene."""

    objects: list[SceneObject] = field(default_factory=list)
    lights: list = field(default_factory=list)
    camera: Camera = field(default_factory=Camera)
    animation: dict | None = None
    base_dir: Path | None = None
    name: str = "scene"

    def object(self, name: str) -> SceneObject:
        for obj in self.objects:
            if obj.name == name:
                return obj
        raise KeyError(f"no object named {name!r}; the scene has {[o.name for o in self.objects]}")

    @property
    def environment(self) -> EnvironmentLight | None:
        envs = [light for light in self.lights if isinstance(light, EnvironmentLight)]
        return envs[0] if envs else None

    @property
    def area_lights(self) -> list[AreaLight]:
        return [light for light in self.lights if isinstance(light, AreaLight)]

    @property
    def point_lights(self) -> list[PointLight]:
        return [light for light in self.lights if isinstance(light, PointLight)]

    def __eq__(self, other):
        """Equal content (objects, meshes, lights, camera, animation, name); ``base_dir`` is not compared."""
        return _dataclass_eq(self, other, skip=("base_dir",))

    # ---- the scene format (``_load.py``)

    @classmethod
    def from_dict(cls, d: dict, base_dir=None, source: str | None = None) -> "Scene":
        """Validate a scene dict (the YAML format) and build the scene; see :func:`prtlab.load_scene`."""
        from ._load import scene_from_dict

        return scene_from_dict(d, base_dir=base_dir, source=source)

    @classmethod
    def load(cls, path) -> "Scene":
        """Load and validate a YAML scene file (same as :func:`prtlab.load_scene`)."""
        from ._load import load_scene

        return load_scene(path)

    def to_dict(self) -> dict:
        """The scene as a YAML-ready dict; ``Scene.from_dict(s.to_dict(), s.base_dir) == s``."""
        from ._load import scene_to_dict

        return scene_to_dict(self)

    def save(self, path):
        """Write the scene as a YAML file."""
        from ._load import save_scene

        return save_scene(self, path)

    # ---- animation (``_animation.py``)

    @property
    def duration(self) -> float:
        """Length of the animation in seconds (0 without one)."""
        return 0.0 if not self.animation else float(self.animation["duration"])

    def at_time(self, t: float) -> "Scene":
        """The scene at time ``t`` of its animation: a new Scene sharing the meshes."""
        from ._animation import scene_at_time

        return scene_at_time(self, t)

    def at_frame(self, i: int, n_frames: int) -> "Scene":
        """Frame ``i`` of ``n_frames`` spread evenly over ``[0, duration]`` (both ends included)."""
        from ._animation import scene_at_frame

        return scene_at_frame(self, i, n_frames)

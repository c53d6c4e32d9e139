"""Direction and surface sampling: deterministic point sets and random samplers with pdfs.

Deterministic sets (no ``rng``): :func:`fibonacci_sphere`,
:func:`geodesic_sphere`, :func:`geodesic_directions`.
Random samplers take a ``numpy.random.Generator`` ``rng`` and return their
samples together with the pdf of each sample, with respect to solid angle
(directions) or area (surface points), so that ``mean(f(x) / pdf(x))`` is an
unbiased estimate of the integral of ``f``.

Conventions: the polar axis of a sampler without ``normal`` is ``+z``
(as the SH basis); a hemisphere sampler with ``normal`` of shape ``(..., 3)``
returns ``(..., n, 3)`` directions around each normal, built in the tangent
frame of :func:`tangent_frame`.
"""

from __future__ import annotations

from functools import lru_cache
from typing import NamedTuple

import numpy as np

from prtlab._validate import check_int

__all__ = [
    "fibonacci_sphere",
    "geodesic_sphere",
    "geodesic_directions",
    "uniform_sphere",
    "uniform_hemisphere",
    "stratified_sphere",
    "stratified_hemisphere",
    "cosine_hemisphere",
    "cosine_hemisphere_pdf",
    "tangent_frame",
    "sample_mesh_area",
    "sample_parallelogram",
    "MeshSamples",
]

_GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))


def _check_rng(rng) -> np.random.Generator:
    if not isinstance(rng, np.random.Generator):
        raise TypeError(
            f"rng must be a numpy.random.Generator (e.g. numpy.random.default_rng(seed)), got {type(rng).__name__}"
        )
    return rng


def _check_normal(normal) -> np.ndarray | None:
    if normal is None:
        return None
    normal = np.asarray(normal, dtype=np.float64)
    if normal.ndim == 0 or normal.shape[-1] != 3:
        raise ValueError(f"normal must be a (..., 3) array of unit vectors, got shape {normal.shape}")
    if not np.all(np.isfinite(normal)):
        raise ValueError("normal contains NaN or inf; pass finite unit normals")
    length = np.linalg.norm(normal, axis=-1, keepdims=True)
    if np.any(length == 0):
        raise ValueError("normal contains zero vectors; pass unit normals")
    return normal / length


def tangent_frame(normals) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal tangents ``(t, b)`` with ``(t, b, n)`` right-handed.

    Branch-free in the sign of ``n_z``; the frame jumps where ``n_z`` changes sign.

    Parameters
    ----------
    normals : (..., 3) float
        Unit normals, used as given (not renormalised).

    Returns
    -------
    t, b : (..., 3) float64
        Unit tangent and bitangent, ``b = n x t``.

    References
    ----------
    Duff et al., "Building an Orthonormal Basis, Revisited", JCGT 6(1), 2017, Listing 3.
    """
    n = np.asarray(normals, dtype=np.float64)
    x, y, z = n[..., 0], n[..., 1], n[..., 2]
    sign = np.where(z >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + z)
    b = x * y * a
    t = np.stack([1.0 + sign * x * x * a, sign * b, -sign * x], axis=-1)
    bb = np.stack([b, sign + y * y * a, -y], axis=-1)
    return t, bb


def _to_frame(local: np.ndarray, normal: np.ndarray | None) -> np.ndarray:
    """(n, 3) local directions (z = normal) -> world: (n, 3) or (..., n, 3)."""
    if normal is None:
        return local
    t, b = tangent_frame(normal)
    return (
        local[..., 0:1] * t[..., None, :] + local[..., 1:2] * b[..., None, :] + local[..., 2:3] * normal[..., None, :]
    )


def _sphere_from_unit_square(u1, u2) -> np.ndarray:
    z = 1.0 - 2.0 * u1
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = 2.0 * np.pi * u2
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)


def _cosine_from_unit_square(u1, u2) -> np.ndarray:
    r = np.sqrt(u1)
    phi = 2.0 * np.pi * u2
    z = np.sqrt(np.maximum(0.0, 1.0 - u1))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)


# ------------------------------------------------------------- deterministic sets


def fibonacci_sphere(n: int) -> np.ndarray:
    """Spherical Fibonacci point set: ``n`` nearly uniform directions.

    Returns
    -------
    dirs : (n, 3) float64

    Notes
    -----
    ``z_i = 1 - (2 i + 1) / n``, ``phi_i = i * pi (3 - sqrt 5)`` (the golden
    angle), so every point owns an equal-area band ``4 pi / n``.

    References
    ----------
    Keinert et al., "Spherical Fibonacci Mapping", ACM TOG 34(6), 2015, Eq. 2.
    """
    n = check_int(n, "n", 0, meaning="sample count")
    i = np.arange(n, dtype=np.float64)
    z = 1.0 - (2.0 * i + 1.0) / max(n, 1)
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = i * _GOLDEN_ANGLE
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)


def _icosahedron() -> tuple[np.ndarray, np.ndarray]:
    g = (1.0 + np.sqrt(5.0)) / 2.0
    v = np.array(
        [[-1, g, 0], [1, g, 0], [-1, -g, 0], [1, -g, 0], [0, -1, g], [0, 1, g],
         [0, -1, -g], [0, 1, -g], [g, 0, -1], [g, 0, 1], [-g, 0, -1], [-g, 0, 1]],
        dtype=np.float64,
    )
    f = np.array(
        [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
         [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
         [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]],
        dtype=np.int64,
    )
    return v / np.linalg.norm(v, axis=1, keepdims=True), f


def geodesic_sphere(frequency: int) -> tuple[np.ndarray, np.ndarray]:
    """Class-I geodesic sphere: every icosahedron face cut into ``frequency**2`` triangles.

    Parameters
    ----------
    frequency : int >= 1
        Number of segments per icosahedron edge.

    Returns
    -------
    vertices : (10 * frequency**2 + 2, 3) float64
        Unit vectors: the points ``(i a + j b + k c) / frequency`` (``i + j + k
        = frequency``) of each flat face, projected to the sphere.
    faces : (20 * frequency**2, 3) int64
        Outward (counter-clockwise) triangles.

    Notes
    -----
    ``frequency = 1`` is the icosahedron (12 vertices), 2 gives 42, 3 gives
    92: the 12 icosahedron vertices, two points on each of its 30 edges and
    the centre of each of its 20 faces. Frequency ``2**s`` has the vertex
    count of ``s`` four-way subdivisions (trimesh's ``icosphere(s)``), but the
    points differ for ``s >= 2`` (here the flat face is cut once, then projected).
    """
    vertices, faces = _geodesic_sphere(check_int(frequency, "frequency", 1))
    return vertices.copy(), faces.copy()


@lru_cache(maxsize=16)
def _geodesic_sphere(f: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`geodesic_sphere`, kept per frequency (the spherical lights ask for their directions every frame)."""
    ico_v, ico_f = _icosahedron()
    points, tris = list(ico_v), []  # icosahedron vertices first, in their order
    offset = len(points)
    for a, b, c in ico_v[ico_f]:
        index = {}
        local = []
        for i in range(f + 1):
            for j in range(f + 1 - i):
                k = f - i - j
                index[(i, j)] = offset + len(local)
                local.append((k * a + i * b + j * c) / f)
        for i in range(f):
            for j in range(f - i):
                tris.append((index[(i, j)], index[(i + 1, j)], index[(i, j + 1)]))
                if i + j < f - 1:
                    tris.append((index[(i + 1, j)], index[(i + 1, j + 1)], index[(i, j + 1)]))
        points.extend(local)
        offset += len(local)
    points = np.asarray(points)
    points /= np.linalg.norm(points, axis=1, keepdims=True)
    key = np.round(points * 1e9).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)  # first-seen order: the 12 icosahedron vertices lead
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    vertices = points[first[order]]
    faces = rank[inverse.reshape(-1)][np.asarray(tris)]
    vertices.setflags(write=False)
    faces.setflags(write=False)
    return vertices, faces


def geodesic_directions(n: int) -> np.ndarray:
    """The ``n`` vertices of the geodesic sphere that has exactly ``n`` of them.

    Parameters
    ----------
    n : int
        ``10 * f**2 + 2`` for a frequency ``f >= 1``: 12, 42, 92, 162, 252, 362, ...

    Returns
    -------
    dirs : (n, 3) float64

    Notes
    -----
    ``geodesic_directions(92)`` is the frequency-3 geodesic sphere, the
    92-direction set of Guerrero et al. (a geodesic sphere with 92 vertices,
    the smallest class-I geodesic with that count; it equals the 12
    icosahedron vertices plus the 80 face centres of the once-subdivided
    icosahedron only in count, not in position).
    """
    n = check_int(n, "n", 0, meaning="sample count")
    f = int(round(np.sqrt(max(n - 2, 0) / 10.0)))
    if f < 1 or 10 * f * f + 2 != n:
        raise ValueError(
            f"a geodesic sphere has 10*f**2 + 2 vertices (12, 42, 92, 162, 252, ...), got n={n}; "
            "use fibonacci_sphere(n) for arbitrary counts"
        )
    return _geodesic_sphere(f)[0].copy()


# ----------------------------------------------------------------- random samplers


def uniform_sphere(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Uniform directions on the unit sphere.

    Returns
    -------
    dirs : (n, 3) float64
    pdf : (n,) float64
        ``1 / (4 pi)`` per steradian.
    """
    n = check_int(n, "n", 0, meaning="sample count")
    u = _check_rng(rng).random((n, 2))
    return _sphere_from_unit_square(u[:, 0], u[:, 1]), np.full(n, 1.0 / (4.0 * np.pi))


def uniform_hemisphere(n: int, rng: np.random.Generator, normal=None) -> tuple[np.ndarray, np.ndarray]:
    """Uniform directions on the hemisphere around ``normal`` (default ``+z``).

    Returns
    -------
    dirs : (n, 3) or (..., n, 3) float64
    pdf : (n,) or (..., n) float64
        ``1 / (2 pi)``.
    """
    n = check_int(n, "n", 0, meaning="sample count")
    normal = _check_normal(normal)
    batch = () if normal is None else normal.shape[:-1]
    u = _check_rng(rng).random(batch + (n, 2))
    local = _sphere_from_unit_square(0.5 * u[..., 0], u[..., 1])
    return _to_frame(local, normal), np.full(batch + (n,), 1.0 / (2.0 * np.pi))


def cosine_hemisphere(n: int, rng: np.random.Generator, normal=None) -> tuple[np.ndarray, np.ndarray]:
    """Cosine-weighted directions on the hemisphere around ``normal`` (default ``+z``).

    Parameters
    ----------
    n : int
    rng : numpy.random.Generator
    normal : (..., 3) float, optional

    Returns
    -------
    dirs : (n, 3) or (..., n, 3) float64
    pdf : (n,) or (..., n) float64
        ``cos(theta) / pi`` per steradian.

    Notes
    -----
    Malley's method: a uniform point on the unit disc lifted to the hemisphere.
    """
    n = check_int(n, "n", 0, meaning="sample count")
    normal = _check_normal(normal)
    batch = () if normal is None else normal.shape[:-1]
    u = _check_rng(rng).random(batch + (n, 2))
    local = _cosine_from_unit_square(u[..., 0], u[..., 1])
    return _to_frame(local, normal), local[..., 2] / np.pi


def cosine_hemisphere_pdf(dirs, normal=None) -> np.ndarray:
    """``max(0, n . w) / pi``: the density of :func:`cosine_hemisphere`.

    Parameters
    ----------
    dirs : (..., 3) float
        Unit directions.
    normal : (..., 3) float, optional
        Broadcasts against ``dirs``; default ``+z``.

    Returns
    -------
    pdf : (...) float64
    """
    dirs = np.asarray(dirs, dtype=np.float64)
    if dirs.ndim == 0 or dirs.shape[-1] != 3:
        raise ValueError(f"dirs must be a (..., 3) array of directions, got shape {dirs.shape}")
    normal = np.array([0.0, 0.0, 1.0]) if normal is None else _check_normal(normal)
    return np.maximum(0.0, np.sum(dirs * normal, axis=-1)) / np.pi


def _grid_shape(n: int) -> tuple[int, int]:
    """Rows x columns = n with columns ~ 2 rows (the divisor of n nearest sqrt(n / 2))."""
    target = np.sqrt(n / 2.0)
    rows = min((d for d in range(1, n + 1) if n % d == 0), key=lambda d: (abs(d - target), d))
    return rows, n // rows


def _stratified_unit_square(n: int, rng, batch=()) -> np.ndarray:
    rows, cols = _grid_shape(n)
    jitter = rng.random(batch + (n, 2))
    cell = np.arange(n)
    u1 = (cell // cols + jitter[..., 0]) / rows
    u2 = (cell % cols + jitter[..., 1]) / cols
    return np.stack([u1, u2], axis=-1)


def stratified_sphere(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Jittered stratified directions: one uniform sample in each of ``n`` equal-area cells.

    Returns
    -------
    dirs : (n, 3) float64
    pdf : (n,) float64
        ``1 / (4 pi)``: each sample's marginal density is uniform.

    Notes
    -----
    Cells are a ``rows x cols = n`` grid in ``(z, phi)`` (equal area because
    ``dz dphi = d omega``), with ``rows`` the divisor of ``n`` nearest
    ``sqrt(n / 2)``; a prime ``n`` gives ``n`` bands in ``z``. The sample
    variance of stratified samples overestimates the estimator's variance, so
    error bars from it are conservative.
    """
    n = check_int(n, "n", 0, meaning="sample count")
    if n == 0:
        return np.zeros((0, 3)), np.zeros(0)
    u = _stratified_unit_square(n, _check_rng(rng))
    return _sphere_from_unit_square(u[:, 0], u[:, 1]), np.full(n, 1.0 / (4.0 * np.pi))


def stratified_hemisphere(
    n: int, rng: np.random.Generator, normal=None, cosine: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Jittered stratified directions on the hemisphere around ``normal`` (default ``+z``).

    Parameters
    ----------
    n : int
    rng : numpy.random.Generator
    normal : (..., 3) float, optional
    cosine : bool
        Stratify the cosine-weighted map (pdf ``cos / pi``) instead of the
        uniform one (pdf ``1 / (2 pi)``).

    Returns
    -------
    dirs : (n, 3) or (..., n, 3) float64
    pdf : (n,) or (..., n) float64
    """
    n = check_int(n, "n", 0, meaning="sample count")
    normal = _check_normal(normal)
    rng = _check_rng(rng)
    batch = () if normal is None else normal.shape[:-1]
    if n == 0:
        return np.zeros(batch + (0, 3)), np.zeros(batch + (0,))
    u = _stratified_unit_square(n, rng, batch)
    if cosine:
        local = _cosine_from_unit_square(u[..., 0], u[..., 1])
        pdf = local[..., 2] / np.pi
    else:
        local = _sphere_from_unit_square(0.5 * u[..., 0], u[..., 1])
        pdf = np.full(batch + (n,), 1.0 / (2.0 * np.pi))
    return _to_frame(local, normal), pdf


class MeshSamples(NamedTuple):
    """Uniform samples on a mesh surface (see :func:`sample_mesh_area`)."""

    points: np.ndarray  # (n, 3)
    face_ids: np.ndarray  # (n,) int64
    barycentrics: np.ndarray  # (n, 2): (u, v), point = (1-u-v) a + u b + v c
    normals: np.ndarray  # (n, 3) unit face normals (winding)
    pdf: np.ndarray  # (n,) 1 / total area


def sample_mesh_area(mesh, n: int, rng: np.random.Generator) -> MeshSamples:
    """Points uniformly distributed over the area of a triangle mesh.

    Parameters
    ----------
    mesh : trimesh.Trimesh or (vertices (V, 3), faces (F, 3))
    n : int
    rng : numpy.random.Generator

    Returns
    -------
    MeshSamples
        ``points (n, 3)``, ``face_ids (n,)``, ``barycentrics (n, 2)`` as Embree's
        ``(u, v)``, unit face ``normals (n, 3)`` and ``pdf (n,) = 1 / A``.

    Notes
    -----
    A face is drawn with probability ``A_f / A``, then ``(u, v) = (sqrt(r1) (1 - r2),
    sqrt(r1) r2)``, uniform on the triangle.

    References
    ----------
    Pharr, Jakob, Humphreys, *Physically Based Rendering*, 3rd ed., Sec. 13.6.5.
    """
    n = check_int(n, "n", 0, meaning="sample count")
    rng = _check_rng(rng)
    if hasattr(mesh, "vertices") and hasattr(mesh, "faces"):
        vertices, faces = mesh.vertices, mesh.faces
    elif isinstance(mesh, (tuple, list)) and len(mesh) == 2:
        vertices, faces = mesh
    else:
        raise TypeError(f"mesh must be a trimesh.Trimesh or a (vertices, faces) pair, got {type(mesh).__name__}")
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(
            f"mesh needs (V, 3) vertices and (F, 3) faces, got {vertices.shape} and {faces.shape}"
        )
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    cross = np.cross(b - a, c - a)
    double_area = np.linalg.norm(cross, axis=1)
    total = 0.5 * double_area.sum()
    if not total > 0:
        raise ValueError("mesh has no area to sample (no faces, or only degenerate ones)")
    cdf = np.cumsum(double_area)
    cdf /= cdf[-1]
    face = np.minimum(np.searchsorted(cdf, rng.random(n), side="right"), len(faces) - 1)
    r = rng.random((n, 2))
    s = np.sqrt(r[:, 0])
    uv = np.stack([s * (1.0 - r[:, 1]), s * r[:, 1]], axis=-1)
    points = (1.0 - uv[:, :1] - uv[:, 1:]) * a[face] + uv[:, :1] * b[face] + uv[:, 1:] * c[face]
    normals = cross[face] / double_area[face][:, None]
    return MeshSamples(points, face, uv, normals, np.full(n, 1.0 / total))


def sample_parallelogram(center, u, v, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Uniform points on the parallelogram ``center + s u + t v``, ``s, t`` in [-1, 1].

    Parameters
    ----------
    center, u, v : (3,) float
        Centre and half edges (an :class:`prtlab.scene.AreaLight`'s fields).
    n : int
    rng : numpy.random.Generator

    Returns
    -------
    points : (n, 3) float64
    pdf : (n,) float64
        ``1 / A`` with ``A = 4 |u x v|``.
    """
    n = check_int(n, "n", 0, meaning="sample count")
    rng = _check_rng(rng)
    arrays = []
    for name, x in (("center", center), ("u", u), ("v", v)):
        x = np.asarray(x, dtype=np.float64)
        if x.shape != (3,) or not np.all(np.isfinite(x)):
            raise ValueError(f"{name} must be a finite (3,) vector, got {x!r}")
        arrays.append(x)
    center, u, v = arrays
    area = 4.0 * np.linalg.norm(np.cross(u, v))
    if not area > 0:
        raise ValueError("u and v span no area (parallel or zero half edges)")
    st = 2.0 * rng.random((n, 2)) - 1.0
    return center + st[:, :1] * u + st[:, 1:] * v, np.full(n, 1.0 / area)

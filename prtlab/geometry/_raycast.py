"""Ray casting through Embree for scenes of many rigid objects.

A :class:`RayCaster` holds one Embree triangle geometry per object, in world
space, and one acceleration structure (BVH) per *pose* of the scene. It is
rebuilt only when :meth:`RayCaster.update_transforms` changes a transform.
Queries are batched: any number of rays with leading batch axes.

Engines (``method=``)
    ``"embree"`` (default) calls Embree 4's ``rtcIntersect1`` / ``rtcOccluded1``
    from a numba ``prange`` kernel (:mod:`prtlab.geometry._embree`), so rays are
    traced on every numba thread without the GIL, each thread taking the next
    block of 256 rays as it finishes one; results do not depend on the thread
    count. ``"embreex"`` traces the same float32 rays through ``embreex``'s
    ``EmbreeScene.run``, which holds the GIL (one core), in chunks of
    :data:`RAY_CHUNK` rays; its scene is built on first use per pose. Both give
    the same hits ray by ray (same library, robust flag and float32 rays).
    ``"numpy"`` is the float64 brute-force specification. If the Embree 4
    library cannot be loaded from beside ``embreex``, the caster warns and
    ``"embree"`` runs the ``embreex`` path.

Self-intersection offset
    Rays that start on a surface are moved off it before they are cast:

    .. math::

        o' = p + \\epsilon \\, \\operatorname{sign}(n \\cdot d) \\, n,
        \\qquad \\epsilon = \\texttt{RAY_EPSILON_SCALE} \\cdot \\lVert b_{max} - b_{min} \\rVert

    with ``p`` the surface point, ``n`` its normal, ``d`` the ray direction and
    ``b`` the world bounding box of the current pose (``RayCaster.epsilon``).
    The offset goes along the normal *on the side of the outgoing ray*, so a
    ray leaving either side of a two-sided sheet starts on that side. Pass
    ``normals=`` to :meth:`RayCaster.closest_hit` / :meth:`RayCaster.occluded`
    to apply it; without ``normals`` origins are used as given. A shadow ray
    toward a light point ``y`` should start at ``o'`` (:func:`offset_origins`),
    be aimed at ``y`` from there and use ``tmax = |y - o'| - epsilon``, so that
    geometry lying exactly at the light (a ceiling light on the ceiling) does
    not shadow it even at grazing angles.
    (``embreex``'s ``run`` fixes Embree's ``tnear`` to 0 and takes only a
    per-ray ``tfar``, so the offset moves the origin instead of raising ``tnear``;
    the ``"embree"`` engine casts the same rays.)

Ray start (``tnear``)
    Rays start at their (offset) origin: ``RAY_TNEAR_SCALE = 0``, and
    ``RayCaster.tnear = RAY_TNEAR_SCALE * diagonal`` is kept as the one place to
    change that. A positive start skips every surface closer than it, and a path
    vertex near an edge (a ray from a wall point a few float32 ulps below the
    ceiling) then leaks light through room corners. The price of 0 is that an
    origin lying *exactly* on another surface is blocked by it (Embree reports
    ``t = 0`` hits for such origins, in every direction); the vertices where
    that happens by construction (a floor vertex at a room corner lies in the
    wall's plane) are shaded at :func:`prtlab.geometry.shading_points`, a hair
    inside their own faces, so it never happens there.

Precision (float32)
    Embree stores vertices, origins, directions and distances in float32. The
    world vertices are computed in float64 and rounded once; distances carry a
    relative error of about ``2**-24`` of the scene's coordinate magnitude, so
    hit points are accurate to roughly ``1e-7 * (|o| + t)``. ``RAY_EPSILON_SCALE
    = 1e-4`` leaves three orders of magnitude of margin above that for scenes
    centred near the origin; a scene placed far from the origin (coordinates
    ``>> 1e3`` times its size) needs a larger epsilon (``epsilon=`` argument).
    Hit *points* and *normals* returned here are recomputed in float64 from the
    triangle id and barycentrics, so they lie on the float64 triangle.
    Scenes are built in Embree's robust mode (``RTC_SCENE_FLAG_ROBUST``: no
    optimisations that reduce arithmetic accuracy, as Embree recommends for
    rays that must not slip through shared edges of watertight meshes).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import NamedTuple, Sequence

import numba
import numpy as np

from .._validate import check_choice
from . import _embree

__all__ = ["RayCaster", "RayHits", "RAY_EPSILON_SCALE", "RAY_TNEAR_SCALE", "RAY_CHUNK", "offset_origins"]

#: Self-intersection offset, as a fraction of the world bounding-box diagonal.
RAY_EPSILON_SCALE = 1e-4

#: Start of every ray (an emulated Embree ``tnear``), as a fraction of the bounding-box diagonal;
#: 0, so that no surface next to an origin is skipped (see the module docstring).
RAY_TNEAR_SCALE = 0.0

#: Whether the ``"embree"`` engine traces 16 consecutive rays at a time (``rtcIntersect16`` /
#: ``rtcOccluded16``): faster when neighbouring rays share an origin or a direction, as the callers'
#: rays do (a point's rays in order); the hits are those of the one-ray calls (tests).
PACKETS = True

#: Rays per call into ``embreex`` (``method="embreex"``; bounds its output buffers).
RAY_CHUNK = 1 << 19


@dataclass
class RayHits:
    """Closest hits of a batch of rays; every field has the rays' batch shape ``(...)``.

    Attributes
    ----------
    hit : (...) bool
    object : (...) int64
        Index of the object hit (``-1`` on a miss).
    triangle : (...) int64
        Face index within that object's mesh (``-1`` on a miss).
    barycentric : (..., 2) float64
        Embree's ``(u, v)``: the hit point is ``(1-u-v) a + u b + v c`` for the
        face's vertices ``(a, b, c)`` (zeros on a miss).
    distance : (...) float64
        Distance along the unit direction from the (offset) origin; ``inf`` on a miss.
    normal : (..., 3) float64
        Unit geometric normal of the face, oriented by its winding
        ``normalize(cross(b - a, c - a))`` (not toward the ray); zeros on a miss.
    point : (..., 3) float64
        Hit point from the barycentrics on the float64 triangle; NaN on a miss.
    """

    hit: np.ndarray
    object: np.ndarray
    triangle: np.ndarray
    barycentric: np.ndarray
    distance: np.ndarray
    normal: np.ndarray
    point: np.ndarray


def _as_rays(origins, dirs, normals=None):
    """Validate and broadcast rays; returns flat float64 views and the batch shape."""
    origins = np.asarray(origins, dtype=np.float64)
    dirs = np.asarray(dirs, dtype=np.float64)
    for name, arr in (("origins", origins), ("dirs", dirs)):
        if arr.ndim == 0 or arr.shape[-1] != 3:
            raise ValueError(f"{name} must be a (..., 3) array, got shape {arr.shape}")
    try:
        shape = np.broadcast_shapes(origins.shape, dirs.shape)
    except ValueError:
        raise ValueError(
            f"origins {origins.shape} and dirs {dirs.shape} do not broadcast; give both as (..., 3)"
        ) from None
    batch = shape[:-1]

    def flat(a):  # writeable C-contiguous float64 (one numba signature for every call), copied only if need be
        return _writeable((a if a.shape == shape else np.broadcast_to(a, shape)).reshape(-1, 3))
    if normals is not None:
        normals = np.asarray(normals, dtype=np.float64)
        if normals.ndim == 0 or normals.shape[-1] != 3:
            raise ValueError(f"normals must be a (..., 3) array, got shape {normals.shape}")
        try:
            normals = np.broadcast_to(normals, shape)
        except ValueError:
            raise ValueError(f"normals {normals.shape} do not broadcast to the rays' shape {shape}") from None
        normals = flat(normals)
    return flat(origins), flat(dirs), normals, batch


@numba.njit(cache=True, inline="always")
def barycentric_normal(vertex_normals, i0, i1, i2, b0, b1, b2):
    """``b0 n[i0] + b1 n[i1] + b2 n[i2]`` of ``vertex_normals (V, 3)`` as three floats (not normalised)."""
    nx = b0 * vertex_normals[i0, 0] + b1 * vertex_normals[i1, 0] + b2 * vertex_normals[i2, 0]
    ny = b0 * vertex_normals[i0, 1] + b1 * vertex_normals[i1, 1] + b2 * vertex_normals[i2, 1]
    nz = b0 * vertex_normals[i0, 2] + b1 * vertex_normals[i1, 2] + b2 * vertex_normals[i2, 2]
    return nx, ny, nz


def _writeable(a: np.ndarray) -> np.ndarray:
    """``a`` if it is a writeable C-contiguous float64 array, else such a copy."""
    if a.dtype == np.float64 and a.flags.c_contiguous and a.flags.writeable:
        return a
    return np.array(a, dtype=np.float64, order="C")


@numba.njit(cache=True, inline="always")
def may_hit_ray(ox, oy, oz, cx, cy, cz, dist2, r2, dx, dy, dz, lo, hi):
    """Whether the ray from ``o`` along ``d`` meets the sphere of squared radius ``r2`` whose centre lies at
    ``c = centre - o`` (``dist2 = |c|^2``) and the box ``[lo, hi]`` (``may_hit``'s test of one ray)."""
    along = cx * dx + cy * dy + cz * dz
    ok = dist2 <= r2 or (along > 0.0 and dist2 - along * along <= r2)
    if ok:  # slab test: the ray's parameter interval inside the box is not empty
        enter, leave = 0.0, np.inf
        for axis in range(3):
            start = (ox, oy, oz)[axis]
            step = (dx, dy, dz)[axis]
            if step == 0.0:
                if start < lo[axis] or start > hi[axis]:
                    ok = False
            else:
                t1 = (lo[axis] - start) / step
                t2 = (hi[axis] - start) / step
                enter = max(enter, min(t1, t2))
                leave = min(leave, max(t1, t2))
        ok = ok and enter <= leave
    return ok


@numba.njit(cache=True, parallel=True)
def _may_hit_kernel(origins, dirs, centre, radius, lo, hi, out):
    """``out[p, d]``: the ray meets the sphere ``(centre, radius)`` and the box ``[lo, hi]`` (see ``may_hit``)."""
    r2 = radius * radius
    for p in numba.prange(origins.shape[0]):
        ox, oy, oz = origins[p, 0], origins[p, 1], origins[p, 2]
        cx, cy, cz = centre[0] - ox, centre[1] - oy, centre[2] - oz
        dist2 = cx * cx + cy * cy + cz * cz
        for j in range(dirs.shape[0]):
            out[p, j] = may_hit_ray(ox, oy, oz, cx, cy, cz, dist2, r2, dirs[j, 0], dirs[j, 1], dirs[j, 2], lo, hi)


#: The query engines, fastest first (module docstring).
METHODS = ("embree", "embreex", "numpy")

_FLOAT32_MAX = float(np.finfo(np.float32).max)

#: Per-ray status of staging: cast, not cast (empty segment), or one of three input errors.
CAST, NOT_CAST, NONFINITE_RAY, ZERO_DIRECTION, NONFINITE_NORMAL = 0, 1, 2, 3, 4


class _Rays(NamedTuple):
    """Rays as numba kernels take them (float64, C-contiguous, writeable)."""

    origins: np.ndarray  # (n, 3)
    dirs: np.ndarray  # (n, 3), any nonzero length
    normals: np.ndarray  # (n, 3), or (0, 3): no origin offset
    tmax: np.ndarray  # (n,), or (1,): one for every ray
    epsilon: float
    tnear: float


class _Mesh(NamedTuple):
    """Every object's triangles in one float64 world-space mesh; object ``g``'s faces start at ``face_offset[g]``."""

    face_offset: np.ndarray  # (n_objects + 1,) int64
    faces: np.ndarray  # (n_faces, 3) int64
    vertices: np.ndarray  # (n_vertices, 3) float64
    face_normals: np.ndarray  # (n_faces, 3) float64


class _Hits(NamedTuple):
    """Flat outputs of a closest-hit query (see :class:`RayHits`)."""

    hit: np.ndarray
    geom: np.ndarray
    prim: np.ndarray
    uv: np.ndarray
    dist: np.ndarray
    point: np.ndarray
    normal: np.ndarray

    @classmethod
    def empty(cls, n: int, any_hit: bool = False) -> "_Hits":
        """Outputs for ``n`` rays (``any_hit``: only ``hit``; the other fields hold no rays)."""
        m = 0 if any_hit else n
        i64 = np.int64
        return cls(np.empty(n, bool), np.empty(m, i64), np.empty(m, i64), np.empty((m, 2)), np.empty(m),
                   np.empty((m, 3)), np.empty((m, 3)))


class _Tracer(NamedTuple):
    """An Embree query for a kernel: C function and scene addresses, one ray slot per block of rays and
    the numba thread count (``numba.get_num_threads()`` inside a kernel would keep it from being cached)."""

    function: int
    scene: int
    slot_f32: np.ndarray
    slot_u32: np.ndarray
    threads: int
    any_hit: bool
    packet: bool
    valid: np.ndarray


@numba.njit(cache=True, inline="always")
def _stage_ray(rays, i):
    """Ray ``i``: unit direction, origin offset off its surface (``normals``) and moved ``tnear`` along the
    ray, and ``tmax - tnear`` (inf past float32's range). Returns ``(status, ox, oy, oz, dx, dy, dz, tfar)``."""
    dx, dy, dz = rays.dirs[i, 0], rays.dirs[i, 1], rays.dirs[i, 2]
    ox, oy, oz = rays.origins[i, 0], rays.origins[i, 1], rays.origins[i, 2]
    length = np.sqrt(dx * dx + dy * dy + dz * dz)
    tfar = rays.tmax[np.int64(i) if rays.tmax.shape[0] > 1 else np.int64(0)] - rays.tnear
    if not (np.isfinite(length) and np.isfinite(ox) and np.isfinite(oy) and np.isfinite(oz)):
        return NONFINITE_RAY, ox, oy, oz, dx, dy, dz, tfar
    if length == 0.0:
        return ZERO_DIRECTION, ox, oy, oz, dx, dy, dz, tfar
    dx /= length
    dy /= length
    dz /= length
    if rays.normals.shape[0] > 0:
        nx, ny, nz = rays.normals[i, 0], rays.normals[i, 1], rays.normals[i, 2]
        if not (np.isfinite(nx) and np.isfinite(ny) and np.isfinite(nz)):
            return NONFINITE_NORMAL, ox, oy, oz, dx, dy, dz, tfar
        side = rays.epsilon if nx * dx + ny * dy + nz * dz >= 0.0 else -rays.epsilon
        ox += side * nx
        oy += side * ny
        oz += side * nz
    tnear = rays.tnear
    if tfar > _FLOAT32_MAX:
        tfar = np.inf
    status = CAST if np.float32(tfar) > 0.0 else NOT_CAST
    return status, ox + tnear * dx, oy + tnear * dy, oz + tnear * dz, dx, dy, dz, tfar


@numba.njit(cache=True, inline="always")
def _store_hit(hit, geom, prim, uv, dist, i, g, face, u, v, t):
    """Ray ``i`` hit face ``face`` of object ``g`` at distance ``t`` (``g < 0``: a miss).

    The kernels pass ``_Hits`` fields as local arrays: numba 0.68 drops writes made inside a ``prange``
    loop through a named tuple's fields (``out.geom[i] = g``)."""
    hit[i] = g >= 0
    geom[i] = g if g >= 0 else -1
    prim[i] = face if g >= 0 else -1
    uv[i, 0] = u if g >= 0 else 0.0
    uv[i, 1] = v if g >= 0 else 0.0
    dist[i] = t if g >= 0 else np.inf


@numba.njit(cache=True, parallel=True, nogil=True)
def _trace_kernel(tracer, rays, mesh, out, status):
    """Closest hits through ``rtcIntersect1`` into ``out``, or with ``tracer.any_hit`` occlusion through
    ``rtcOccluded1`` (which sets ``tfar`` to ``-inf`` on a hit) into ``out.hit`` only; with
    ``tracer.packet``, 16 consecutive rays at a time through ``rtcIntersect16`` / ``rtcOccluded16``. Each
    thread takes the next block ``b`` of ``RAYS_PER_TASK`` rays from a shared counter, traces it through
    slot ``b``, then resolves the block's hit points (``_resolve_point``; a loop of its own: done ray by ray
    between the traces, the mesh's reads and the BVH's evict each other from the caches)."""
    n = rays.origins.shape[0]
    n_blocks = tracer.slot_f32.shape[0]
    step = _embree.RAYS_PER_TASK
    w = _embree.PACKET
    hit, geom, prim, uv, dist, point, normal = out.hit, out.geom, out.prim, out.uv, out.dist, out.point, out.normal
    counter = np.zeros(1, dtype=np.int64)
    for _ in numba.prange(tracer.threads):
        while True:
            block = _embree.fetch_add(counter, 1)
            if block >= n_blocks:
                break
            f32, u32 = tracer.slot_f32[block], tracer.slot_u32[block]
            address = f32.ctypes.data
            end = min(n, (block + 1) * step)
            if tracer.packet:
                valid = tracer.valid[block]
                for start in range(block * step, end, w):
                    stop = min(end, start + w)
                    cast = False
                    for k in range(w):
                        valid[k] = 0
                    for i in range(start, stop):
                        state, ox, oy, oz, dx, dy, dz, tfar = _stage_ray(rays, i)
                        status[i] = state
                        if state == CAST:
                            _embree.set_packet_ray(f32, u32, i - start, ox, oy, oz, dx, dy, dz, tfar)
                            valid[i - start] = -1
                            cast = True
                    if cast:
                        _embree.rtc_call_packet(tracer.function, valid.ctypes.data, tracer.scene, address)
                    for i in range(start, stop):
                        k = i - start
                        g = np.int64(-1)
                        if valid[k] != 0:
                            if tracer.any_hit:
                                g = np.int64(0) if f32[_embree.TFAR * w + k] < 0.0 else np.int64(-1)
                            elif u32[_embree.HIT_GEOM * w + k] != _embree.INVALID_ID:
                                g = np.int64(u32[_embree.HIT_GEOM * w + k])
                        if tracer.any_hit:
                            hit[i] = g >= 0
                        else:
                            _store_hit(hit, geom, prim, uv, dist, i, g, np.int64(u32[_embree.HIT_PRIM * w + k]),
                                       np.float64(f32[_embree.HIT_U * w + k]), np.float64(f32[_embree.HIT_V * w + k]),
                                       np.float64(f32[_embree.TFAR * w + k]) + rays.tnear)
            else:
                for i in range(block * step, end):
                    state, ox, oy, oz, dx, dy, dz, tfar = _stage_ray(rays, i)
                    status[i] = state
                    g = np.int64(-1)
                    if state == CAST:
                        _embree.set_ray(f32, u32, ox, oy, oz, dx, dy, dz, tfar)
                        _embree.rtc_call(tracer.function, tracer.scene, address)
                        if tracer.any_hit:
                            g = np.int64(0) if f32[_embree.TFAR] < 0.0 else np.int64(-1)
                        elif u32[_embree.HIT_GEOM] != _embree.INVALID_ID:
                            g = np.int64(u32[_embree.HIT_GEOM])
                    if tracer.any_hit:
                        hit[i] = g >= 0
                    else:
                        _store_hit(hit, geom, prim, uv, dist, i, g, np.int64(u32[_embree.HIT_PRIM]),
                                   np.float64(f32[_embree.HIT_U]), np.float64(f32[_embree.HIT_V]),
                                   np.float64(f32[_embree.TFAR]) + rays.tnear)
            if not tracer.any_hit:
                for i in range(block * step, end):
                    _resolve_point(mesh, geom, prim, uv, point, normal, i)


@numba.njit(cache=True, parallel=True)
def _stage_rays(rays, o32, d32, t32, status):
    """The float32 rays of ``_stage_ray`` in arrays (``method="embreex"``); ``t32 = 0`` for a ray not cast."""
    for i in numba.prange(rays.origins.shape[0]):
        state, ox, oy, oz, dx, dy, dz, tfar = _stage_ray(rays, i)
        status[i] = state
        o32[i, 0], o32[i, 1], o32[i, 2] = ox, oy, oz
        d32[i, 0], d32[i, 1], d32[i, 2] = dx, dy, dz
        t32[i] = tfar if state == CAST else 0.0


@numba.njit(cache=True, parallel=True)
def _collect_hits(start, g32, p32, u32, v32, t32, cast, tnear, out):
    """``embreex``'s float32 / int32 output for rays ``start + j`` into ``out`` (rays not cast: misses)."""
    hit, geom, prim, uv, dist = out.hit, out.geom, out.prim, out.uv, out.dist
    for j in numba.prange(g32.shape[0]):
        g = np.int64(g32[j]) if cast[j] > 0.0 else np.int64(-1)
        _store_hit(hit, geom, prim, uv, dist, start + j, g, np.int64(p32[j]), np.float64(u32[j]), np.float64(v32[j]),
                   np.float64(t32[j]) + tnear)


@numba.njit(cache=True, inline="always")
def _resolve_point(mesh, geom, prim, uv, point, normal, i):
    """Ray ``i``'s hit point from its barycentrics on the float64 triangle, and the unit face normal
    (NaN and 0 on a miss)."""
    g = geom[i]
    if g < 0:
        for k in range(3):
            point[i, k] = np.nan
            normal[i, k] = 0.0
        return
    f = mesh.face_offset[g] + prim[i]
    a, b, c = mesh.faces[f, 0], mesh.faces[f, 1], mesh.faces[f, 2]
    u, v = uv[i, 0], uv[i, 1]
    w = 1.0 - u - v
    for k in range(3):
        point[i, k] = w * mesh.vertices[a, k] + u * mesh.vertices[b, k] + v * mesh.vertices[c, k]
        normal[i, k] = mesh.face_normals[f, k]


@numba.njit(cache=True, parallel=True)
def _resolve_points(mesh, geom, prim, uv, point, normal):
    """``_resolve_point`` for every ray (the ``embreex`` and ``numpy`` engines)."""
    for i in numba.prange(geom.shape[0]):
        _resolve_point(mesh, geom, prim, uv, point, normal, i)


def offset_origins(points, normals, dirs, epsilon: float) -> np.ndarray:
    """Move ray origins off their surface: ``p + epsilon * sign(n . d) * n``.

    Parameters
    ----------
    points, normals, dirs : (..., 3) float
        Surface points, their unit normals (either orientation) and the
        outgoing ray directions; broadcast together.
    epsilon : float
        Offset distance, usually :attr:`RayCaster.epsilon`.

    Returns
    -------
    origins : (..., 3) float64

    Notes
    -----
    A direction exactly in the tangent plane (``n . d = 0``) is offset along
    ``+n``.
    """
    points = np.asarray(points, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    dirs = np.asarray(dirs, dtype=np.float64)
    side = np.where(np.sum(normals * dirs, axis=-1) < 0.0, -1.0, 1.0)
    return points + (float(epsilon) * side)[..., None] * normals


def _transform_matrix(transform) -> np.ndarray:
    if transform is None:
        return np.eye(4)
    if hasattr(transform, "matrix"):
        return np.asarray(transform.matrix(), dtype=np.float64)
    m = np.asarray(transform, dtype=np.float64)
    if m.shape != (4, 4):
        raise ValueError(
            f"a transform must be a prtlab Transform or a (4, 4) matrix, got shape {m.shape}"
        )
    if not np.all(np.isfinite(m)):
        raise ValueError("a transform contains NaN or inf; pass finite transforms")
    return m


def _used_vertices(faces, n_vertices: int) -> np.ndarray:
    """The vertices ``faces (F, 3)`` use, ascending: ``np.unique(faces)`` by a mask over the ``n_vertices`` (no
    sort)."""
    used = np.zeros(n_vertices, dtype=bool)
    used[faces.ravel()] = True
    return np.flatnonzero(used)


def _mesh_arrays(mesh, index: int):
    if hasattr(mesh, "vertices") and hasattr(mesh, "faces"):
        vertices, faces = mesh.vertices, mesh.faces
    elif isinstance(mesh, (tuple, list)) and len(mesh) == 2:
        vertices, faces = mesh
    else:
        raise TypeError(
            f"meshes[{index}] must be a trimesh.Trimesh or a (vertices, faces) pair, got {type(mesh).__name__}"
        )
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"meshes[{index}] vertices must be (n_vertices, 3), got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
        raise ValueError(f"meshes[{index}] faces must be an integer (n_faces, 3) array, got {faces.shape}")
    if not np.all(np.isfinite(vertices)):
        raise ValueError(f"meshes[{index}] vertices contain NaN or inf")
    if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise ValueError(f"meshes[{index}] faces index vertices outside [0, {len(vertices)})")
    return vertices, faces.astype(np.int64)


class RayCaster:
    """Closest-hit and any-hit queries against a scene of rigid objects.

    Parameters
    ----------
    meshes : Scene, trimesh.Trimesh, or sequence of trimesh.Trimesh / (vertices, faces)
        The objects in object space. A :class:`prtlab.scene.Scene` contributes
        every object except portals (a portal is an opening, not a surface),
        each with its own transform; ``object_index`` maps the caster's
        object index back to ``scene.objects``.
    transforms : sequence of (Transform or (4, 4) array or None), optional
        One per mesh; ``None`` is the identity. Ignored for a Scene (its
        objects carry their transforms); use :meth:`update_transforms` to move them.
    epsilon : float, optional
        Fixed self-intersection offset; default ``RAY_EPSILON_SCALE`` times the
        world bounding-box diagonal of the current pose.

    Notes
    -----
    One Embree geometry per object, so hits report the object index, the
    face index within that object's mesh, Embree's barycentrics and the
    distance. Embree computes in float32; see the module docstring for the
    precision this gives and for the offset convention.

    Examples
    --------
    >>> import trimesh
    >>> caster = RayCaster([trimesh.creation.box()])
    >>> hits = caster.closest_hit([[0.0, 0.0, 5.0]], [[0.0, 0.0, -1.0]])
    >>> float(hits.distance[0])
    4.5
    """

    def __init__(self, meshes, transforms: Sequence | None = None, *, epsilon: float | None = None):
        self.object_index: list[int] = []
        if hasattr(meshes, "objects") and hasattr(meshes, "lights"):  # a Scene
            objs = [(i, o) for i, o in enumerate(meshes.objects) if not getattr(o, "portal", False)]
            self.object_index = [i for i, _ in objs]
            mesh_list = [o.mesh for _, o in objs]
            transforms = [o.transform for _, o in objs]
        else:
            mesh_list = [meshes] if hasattr(meshes, "faces") else list(meshes)
            self.object_index = list(range(len(mesh_list)))
        if transforms is None:
            transforms = [None] * len(mesh_list)
        transforms = list(transforms)
        if len(transforms) != len(mesh_list):
            raise ValueError(
                f"transforms has {len(transforms)} entries for {len(mesh_list)} meshes; give one per mesh"
            )
        if epsilon is not None and not (np.isfinite(epsilon) and epsilon >= 0):
            raise ValueError(f"epsilon must be a finite number >= 0, got {epsilon}")
        self._fixed_epsilon = None if epsilon is None else float(epsilon)
        self._object_vertices = []
        self._faces = []
        for i, mesh in enumerate(mesh_list):
            v, f = _mesh_arrays(mesh, i)
            self._object_vertices.append(v)
            self._faces.append(f)
        self._matrices = [_transform_matrix(t) for t in transforms]
        self.n_builds = 0
        self._scene = self._embreex_scene = None
        self._build()

    # ------------------------------------------------------------------ pickling

    def __getstate__(self) -> dict:
        """Everything but the Embree scene (a C object): a caster sent to another
        process (a Dask worker) rebuilds its acceleration structure there."""
        state = self.__dict__.copy()
        state["_scene"] = state["_embreex_scene"] = None
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        n_builds = self.n_builds
        self._build()
        self.n_builds = n_builds

    # ------------------------------------------------------------------ pose

    @property
    def n_objects(self) -> int:
        return len(self._faces)

    def _build(self) -> None:
        # an object whose matrix is the previous build's keeps its world vertices, face normals and box (the same
        # arithmetic on the same arrays): a move of one object recomputes that object's arrays alone
        previous = self.__dict__.get("_posed") or []
        if len(self.__dict__.get("_used") or []) != len(self._faces):
            self._used = [_used_vertices(f, len(v)) for v, f in zip(self._object_vertices, self._faces)]
        self._world_vertices, self._face_normals, self._posed = [], [], []
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for i, (v, f, m) in enumerate(zip(self._object_vertices, self._faces, self._matrices)):
            if i < len(previous) and np.array_equal(previous[i][0], m):
                posed = previous[i]
            else:
                w = v @ m[:3, :3].T + m[:3, 3]
                if len(f):
                    a, b, c = w[f[:, 0]], w[f[:, 1]], w[f[:, 2]]
                    n = np.cross(b - a, c - a)
                    length = np.linalg.norm(n, axis=1, keepdims=True)
                    used = w[self._used[i]]
                    posed = (m, w, np.divide(n, length, out=np.zeros_like(n), where=length > 0), used,
                             used.min(axis=0), used.max(axis=0))
                else:
                    posed = (m, w, np.zeros((0, 3)), None, None, None)
            self._posed.append(posed)
            self._world_vertices.append(posed[1])
            self._face_normals.append(posed[2])
            if len(f):
                lo, hi = np.minimum(lo, posed[4]), np.maximum(hi, posed[5])
        self._bounds = np.stack([lo, hi]) if np.all(np.isfinite(lo)) else np.zeros((2, 3))
        if np.all(np.isfinite(lo)):  # the sphere about the box centre through the farthest used vertex
            centre = 0.5 * (lo + hi)
            used = np.concatenate([p[3] for p, f in zip(self._posed, self._faces) if len(f)])
            self._sphere = (centre, float(np.max(np.linalg.norm(used - centre, axis=1))))
        else:
            self._sphere = (np.zeros(3), 0.0)
        diag = float(np.linalg.norm(self._bounds[1] - self._bounds[0]))
        self._diagonal = diag if diag > 0 else 1.0
        vert_offset = np.cumsum([0] + [len(w) for w in self._world_vertices])
        self._face_offset = np.cumsum([0] + [len(f) for f in self._faces]).astype(np.int64)
        self._all_vertices = np.concatenate(self._world_vertices + [np.zeros((0, 3))])
        self._all_faces = np.concatenate(
            [f + off for f, off in zip(self._faces, vert_offset[:-1])] + [np.zeros((0, 3), dtype=np.int64)]
        )
        self._all_face_normals = np.concatenate(self._face_normals + [np.zeros((0, 3))])
        self._mesh = _Mesh(self._face_offset, self._all_faces, self._all_vertices, self._all_face_normals)
        self._scene = self._embreex_scene = None  # the previous pose's scenes are released here
        try:
            self._scene = _embree.EmbreeScene(list(zip(self._world_vertices, self._faces)))
        except _embree.EmbreeUnavailable as err:
            warnings.warn(f"{err}; RayCaster traces through embreex on one thread", RuntimeWarning, stacklevel=3)
        self.n_builds += 1

    def _embreex(self):
        """The ``embreex`` scene of the current pose, built on first use (``method="embreex"``)."""
        if self._embreex_scene is None:
            from embreex import mesh_construction, rtcore_scene

            scene = rtcore_scene.EmbreeScene(robust=True)
            for w, f in zip(self._world_vertices, self._faces):
                # one geometry per object, so that Embree's geometry id is the object index;
                # an empty mesh gets one zero-area triangle no ray hits
                if len(f):
                    mesh_construction.TriangleMesh(scene, w.astype(np.float32), f.astype(np.int32))
                else:
                    mesh_construction.TriangleMesh(scene, np.zeros((1, 3, 3), dtype=np.float32))
            self._embreex_scene = scene
        return self._embreex_scene

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) world bounding box (min, max) of the current pose."""
        return self._bounds.copy()

    def may_hit(self, origins, dirs) -> np.ndarray:
        """(P, D) bool: whether the ray from each of ``origins`` (P, 3) along each unit direction of ``dirs``
        (D, 3) meets both the geometry's bounding sphere and its bounding box (an origin inside one: every
        ray passes that test). A ray for which it is False hits nothing, so casting it can be skipped. Both
        are widened by :attr:`epsilon` (the origin offset of ``normals=``) and a relative ``1e-6``
        (Embree's float32 arithmetic); a flat object's box is then a thin slab that rays leaving its side
        miss."""
        o = np.ascontiguousarray(np.asarray(origins, dtype=np.float64).reshape(-1, 3))
        d = np.ascontiguousarray(np.asarray(dirs, dtype=np.float64).reshape(-1, 3))
        out = np.empty((len(o), len(d)), dtype=np.bool_)
        _may_hit_kernel(o, d, *self.may_hit_bounds(), out)
        return out

    def may_hit_bounds(self) -> tuple:
        """``(centre, radius, lo, hi)``: the widened sphere and box of :meth:`may_hit`."""
        centre, radius = self._sphere
        margin = 1e-6 * radius + self.epsilon + 1e-12
        return centre, radius + margin, self._bounds[0] - margin, self._bounds[1] + margin

    @property
    def epsilon(self) -> float:
        """Self-intersection offset: ``RAY_EPSILON_SCALE * |bounds[1] - bounds[0]|`` (or the fixed value)."""
        if self._fixed_epsilon is not None:
            return self._fixed_epsilon
        return RAY_EPSILON_SCALE * self._diagonal

    @property
    def tnear(self) -> float:
        """Start of every ray along its direction: ``RAY_TNEAR_SCALE * |bounds[1] - bounds[0]|``."""
        return RAY_TNEAR_SCALE * self._diagonal

    def world_vertices(self, index: int) -> np.ndarray:
        """(n_vertices, 3) float64 world vertices of object ``index`` in the current pose."""
        return self._world_vertices[index]

    def faces(self, index: int) -> np.ndarray:
        """(n_faces, 3) int64 faces of object ``index``."""
        return self._faces[index]

    def face_normals(self, index: int) -> np.ndarray:
        """(n_faces, 3) float64 unit world face normals (by winding) of object ``index``."""
        return self._face_normals[index]

    def update_transforms(self, transforms) -> bool:
        """Move objects; rebuild the acceleration structure only if a transform changed.

        Parameters
        ----------
        transforms : sequence or dict
            A sequence with one entry per object (``Transform``, ``(4, 4)`` array,
            or ``None`` to keep that object's pose), or a dict
            ``{object index: transform}``.

        Returns
        -------
        rebuilt : bool
        """
        if isinstance(transforms, dict):
            items = list(transforms.items())
        else:
            transforms = list(transforms)
            if len(transforms) != self.n_objects:
                raise ValueError(
                    f"transforms has {len(transforms)} entries for {self.n_objects} objects; give one per "
                    "object (None keeps a pose) or a dict {index: transform}"
                )
            items = [(i, t) for i, t in enumerate(transforms) if t is not None]
        new = list(self._matrices)
        for i, t in items:
            if not (0 <= int(i) < self.n_objects):
                raise ValueError(f"object index {i} is out of range [0, {self.n_objects})")
            new[int(i)] = _transform_matrix(t)
        if all(np.array_equal(a, b) for a, b in zip(new, self._matrices)):
            return False
        self._matrices = new
        self._build()
        return True

    def moved(self, transforms) -> "RayCaster":
        """A new caster at ``transforms`` (as :meth:`update_transforms`), this one unchanged: the objects that did
        not move keep their posed arrays (shared, not copied), so a move costs the moved objects' arrays and one
        acceleration-structure build; with no transform changed it shares this caster's scene."""
        out = object.__new__(type(self))
        out.__dict__.update(self.__dict__)
        out.update_transforms(transforms)
        return out

    # --------------------------------------------------------------- queries

    def _rays(self, origins, dirs, tmax, normals):
        """Validated rays for the kernels, and their batch shape."""
        o, d, n, batch = _as_rays(origins, dirs, normals)
        t = self._tmax(tmax, batch, len(o))
        t = np.array([t[0]]) if len(t) and t.strides[0] == 0 else _writeable(t)  # one tmax for all: (1,)
        return _Rays(o, d, np.zeros((0, 3)) if n is None else n, t, self.epsilon, self.tnear), batch

    @staticmethod
    def _check_status(status) -> None:
        if not len(status) or status.max() <= NOT_CAST:
            return
        counts = np.bincount(status, minlength=5)
        if counts[NONFINITE_RAY]:
            raise ValueError("origins or dirs contain NaN or inf; pass finite rays")
        if counts[ZERO_DIRECTION]:
            raise ValueError("dirs contains zero vectors; every ray needs a nonzero direction")
        if counts[NONFINITE_NORMAL]:
            raise ValueError("normals contain NaN or inf; pass finite normals")

    @staticmethod
    def _tmax(tmax, batch, n):
        t = np.asarray(tmax, dtype=np.float64)
        if np.any(np.isnan(t)):
            raise ValueError("tmax contains NaN; pass distances > 0 or inf")
        try:
            t = np.broadcast_to(t, batch).reshape(-1)
        except ValueError:
            raise ValueError(f"tmax of shape {t.shape} does not broadcast to the rays' shape {batch}") from None
        return np.broadcast_to(t, (n,)) if t.size != n else t

    def _tracer(self, n: int, any_hit: bool) -> _Tracer:
        scene = self._scene
        if PACKETS:
            slot_f32, slot_u32, valid = _embree.packet_slots(-(-n // _embree.RAYS_PER_TASK))
            function = scene.occluded16_fn if any_hit else scene.intersect16_fn
        else:
            slot_f32, slot_u32 = _embree.ray_slots(n)
            valid = np.zeros((0, _embree.PACKET), np.int32)
            function = scene.occluded_fn if any_hit else scene.intersect_fn
        return _Tracer(function, scene.handle, slot_f32, slot_u32, numba.get_num_threads(), any_hit, PACKETS, valid)

    @staticmethod
    def _check_method(method):
        check_choice(method, "method", METHODS)

    def _prepare64(self, origins, dirs, normals):
        o, d, n, batch = _as_rays(origins, dirs, normals)
        if not (np.all(np.isfinite(o)) and np.all(np.isfinite(d))):
            raise ValueError("origins or dirs contain NaN or inf; pass finite rays")
        length = np.linalg.norm(d, axis=1)
        if np.any(length == 0):
            raise ValueError("dirs contains zero vectors; every ray needs a nonzero direction")
        d = d / length[:, None]
        if n is not None:
            if not np.all(np.isfinite(n)):
                raise ValueError("normals contain NaN or inf; pass finite normals")
            side = np.where(np.sum(n * d, axis=1) >= 0.0, 1.0, -1.0)
            o = o + (self.epsilon * side)[:, None] * n
        return o, d, batch

    def _brute_force(self, o, d, t):
        """Float64 Moller-Trumbore against every triangle: the specification of the Embree tier."""
        n = len(o)
        geom = np.full(n, -1, dtype=np.int64)
        prim = np.full(n, -1, dtype=np.int64)
        uv = np.zeros((n, 2))
        dist = np.full(n, np.inf)
        faces = self._all_faces
        if not len(faces):
            return geom, prim, uv, dist
        a = self._all_vertices[faces[:, 0]]
        e1 = self._all_vertices[faces[:, 1]] - a
        e2 = self._all_vertices[faces[:, 2]] - a
        owner = np.searchsorted(self._face_offset, np.arange(len(faces)), side="right") - 1
        tnear = self.tnear
        step = max(1, (1 << 22) // len(faces))
        for s in range(0, n, step):
            oo, dd = o[s : s + step, None, :], d[s : s + step, None, :]
            p = np.cross(dd, e2)
            det = np.sum(e1 * p, axis=-1)
            ok = det != 0.0
            inv = 1.0 / np.where(ok, det, 1.0)
            sv = oo - a
            u = np.sum(sv * p, axis=-1) * inv
            q = np.cross(sv, e1)
            v = np.sum(dd * q, axis=-1) * inv
            tt = np.sum(e2 * q, axis=-1) * inv
            hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (tt > tnear) & (tt <= t[s : s + step, None])
            tt = np.where(hit, tt, np.inf)
            k = np.argmin(tt, axis=1)
            rows = np.arange(len(k))
            found = np.isfinite(tt[rows, k])
            idx = np.flatnonzero(found) + s
            kk = k[found]
            geom[idx] = owner[kk]
            prim[idx] = kk - self._face_offset[owner[kk]]
            uv[idx, 0], uv[idx, 1] = u[found, kk], v[found, kk]
            dist[idx] = tt[found, kk]
        return geom, prim, uv, dist

    def closest_hit(self, origins, dirs, tmax=np.inf, *, normals=None, method: str = "embree") -> RayHits:
        """First surface hit along each ray within ``(tnear, tmax]``.

        Parameters
        ----------
        origins, dirs : (..., 3) float
            Ray origins and directions (normalised here; broadcast together).
        tmax : float or (...) float
            Largest distance searched, along the unit direction.
        normals : (..., 3) float, optional
            Surface normals at the origins: if given, each origin is offset by
            ``epsilon`` along ``±normal`` on the side of its ray (module docstring).
        method : {"embree", "embreex", "numpy"}
            Embree in float32 on every numba thread (fast); the same through
            ``embreex`` on one thread; or a float64 brute-force test of every
            triangle (the slow specification, for tests and small scenes).

        Returns
        -------
        RayHits
            Fields with the rays' batch shape ``(...)``.
        """
        self._check_method(method)
        if method == "numpy":
            o, d, batch = self._prepare64(origins, dirs, normals)
            geom, prim, uv, dist = self._brute_force(o, d, self._tmax(tmax, batch, len(o)))
            return self._ray_hits(_Hits(geom >= 0, geom, prim, uv, dist, np.empty((len(o), 3)),
                                        np.empty((len(o), 3))), batch)
        rays, batch = self._rays(origins, dirs, tmax, normals)
        n = len(rays.origins)
        out = _Hits.empty(n)
        status = np.empty(n, dtype=np.int8)
        if method == "embree" and self._scene is not None:
            _trace_kernel(self._tracer(n, False), rays, self._mesh, out, status)
            self._check_status(status)
            return self._ray_hits(out, batch, resolved=True)
        o32, d32, t32 = self._stage32(rays, status)
        scene = self._embreex()
        for s in range(0, n, RAY_CHUNK):
            e = min(n, s + RAY_CHUNK)
            hits = scene.run(o32[s:e], d32[s:e], dists=t32[s:e], output=1)
            _collect_hits(s, hits["geomID"], hits["primID"], hits["u"], hits["v"], hits["tfar"], t32[s:e],
                          rays.tnear, out)
        return self._ray_hits(out, batch)

    def _stage32(self, rays, status):
        """float32 origins, directions and ``tfar`` (0: not cast) for ``embreex``; input errors raised."""
        n = len(rays.origins)
        o32, d32, t32 = np.empty((n, 3), np.float32), np.empty((n, 3), np.float32), np.empty(n, np.float32)
        _stage_rays(rays, o32, d32, t32, status)
        self._check_status(status)
        return o32, d32, t32

    def _ray_hits(self, out: _Hits, batch, resolved: bool = False) -> RayHits:
        """``out`` with its hit points and normals resolved (unless they are), shaped as the rays."""
        if not resolved:
            _resolve_points(self._mesh, out.geom, out.prim, out.uv, out.point, out.normal)
        return RayHits(
            hit=out.hit.reshape(batch),
            object=out.geom.reshape(batch),
            triangle=out.prim.reshape(batch),
            barycentric=out.uv.reshape(batch + (2,)),
            distance=out.dist.reshape(batch),
            normal=out.normal.reshape(batch + (3,)),
            point=out.point.reshape(batch + (3,)),
        )

    def occluded(self, origins, dirs, tmax=np.inf, *, normals=None, method: str = "embree") -> np.ndarray:
        """Whether any surface lies along each ray within ``(tnear, tmax)`` (any-hit query).

        Parameters
        ----------
        origins, dirs : (..., 3) float
            Ray origins and directions (normalised here; broadcast together).
        tmax : float or (...) float
            Length of the segment tested, along the unit direction; for a
            shadow ray toward a light at distance ``r`` use ``r - epsilon``.
        normals : (..., 3) float, optional
            As in :meth:`closest_hit`: offset origins by ``epsilon`` off their surface.
        method : {"embree", "embreex", "numpy"}
            As in :meth:`closest_hit`.

        Returns
        -------
        occluded : (...) bool
        """
        self._check_method(method)
        if method == "numpy":
            o, d, batch = self._prepare64(origins, dirs, normals)
            t = np.asarray(self._tmax(tmax, batch, len(o)), dtype=np.float64)
            dist = self._brute_force(o, d, t)[3]
            return ((dist < t) & (t > 0)).reshape(batch)
        rays, batch = self._rays(origins, dirs, tmax, normals)
        n = len(rays.origins)
        status = np.empty(n, dtype=np.int8)
        if method == "embree" and self._scene is not None:
            out = _Hits.empty(n, any_hit=True)
            _trace_kernel(self._tracer(n, True), rays, self._mesh, out, status)
            self._check_status(status)
            return out.hit.reshape(batch)
        o32, d32, t32 = self._stage32(rays, status)
        result = np.zeros(n, dtype=bool)
        for s in range(0, n, RAY_CHUNK):
            e = min(n, s + RAY_CHUNK)
            live = t32[s:e] > 0
            if np.any(live):
                ids = self._embreex().run(o32[s:e], d32[s:e], dists=t32[s:e], query="OCCLUDED")
                result[s:e] = (ids != -1) & live
        return result.reshape(batch)

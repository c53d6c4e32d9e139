"""Basis radiance fields ``S_(k,i)`` of a source object on its sample spheres (Iwasaki et al. 2007, Sec. 4.3).

A source object whose outgoing radiance is written with its PCA basis
functions ``Psi_i`` and the view factors ``h_k`` of its separable BRDF
(Eq. 9)::

    B(x, w_o) = sum_k sum_i w_(k,i) h_k(w_o) Psi_i(x)

sends toward a point ``p`` in direction ``-w_in`` the radiance
``sum_(k,i) w_(k,i) S_(k,i)(p, w_in)`` with the *basis radiance*

    S_(k,i)(p, w_in) = h_k(-w_in) Psi_i(x~(p, w_in))

where ``x~`` is the first hit of the ray ``p + t w_in`` on the source (0 if
the ray misses it). ``Psi_i`` at the hit is the barycentric interpolation of
its vertex values; ``h_k`` is evaluated in the local frame of the
interpolated shading normal (:func:`prtlab.brdf.local_frame`). A hit on the
back of the surface (``n . w_in > 0``: the ray meets the side the vertex
normals do not point to) carries 0, following the vertex shading side of
``docs/DECISIONS.md``. ``S_(k,i)(p, .)`` is projected to SH by the product
quadrature of :func:`prtlab.sh.quadrature` at every point of the sample
spheres (:func:`prtlab.shadowfields.sphere_grid`), in object space.

References
----------
K. Iwasaki, Y. Dobashi, F. Yoshimoto, T. Nishita, "Precomputed radiance transfer
for dynamic scenes taking into account light interreflection", EGSR 2007,
Sec. 3.1 (Eq. 2), Sec. 4.3.

Self-interreflection (an extension)
    The paper lets an object receive basis irradiance from the *other*
    objects only (Sec. 3.2: ``N_obj - 1`` sources per receiver), so light
    bounced between parts of one object (a bunny's ears onto its back) is
    missing; the path-traced references include it (Fig. 9 scene: 14 % of the
    bunny's green and 35 % of its red one-bounce light). For a rigid object the
    basis irradiance a vertex receives from its own surface does not change
    with the pose, so it is precomputed once, exactly (ray-cast quadrature, no
    SH): :func:`self_basis_irradiance`. Occlusion of an object's light on itself by
    *other* objects is neglected (another object would have to sit between two
    parts of it).
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from prtlab import brdf, sh
from prtlab._validate import as_points
from prtlab.geometry import RayCaster
from prtlab.shadowfields import DEFAULT_DEGREE, SphereGrid

from ._kernels import (flat_source_hits_kernel, hit_basis_kernel, project_hits_kernel, project_source_hits_kernel,
                       source_hit_tasks, source_hits_kernel)

__all__ = ["basis_radiance_field", "basis_radiance_at", "self_basis_irradiance", "StoredBasisRadiance",
           "store_basis_radiance", "STORAGES"]

#: Formats of a stored basis radiance field (:func:`store_basis_radiance`)
STORAGES = ("float64", "float32", "int16")
_INT16_STEPS = 32767

_RAYS_PER_BATCH = 1 << 19


def hit_basis_radiance(hits, sel, w_in, faces, vertex_normals, basis, sep, method: str = "numba") -> np.ndarray:
    """``S_(k,i) = h_k(-w_in) Psi_i`` (H, K, N) leaving the source toward the rays that hit it.

    ``hits`` are a :class:`prtlab.geometry.RayHits` whose entries ``sel`` (a tuple of index arrays, as
    ``np.nonzero``) are rays of directions ``w_in`` (H, 3) that hit; ``Psi`` is interpolated barycentrically
    from the vertices (``basis`` (N, n_vertices)) and is 0 where a ray meets the back of the surface (the
    shading normal, interpolated from ``vertex_normals``, facing away from the ray's origin). ``method``:
    the parallel kernel (``"numba"``) or the numpy specification (``"reference"``); a Lambertian source's
    constant ``h`` is not evaluated per hit.
    """
    tri = np.ascontiguousarray(faces[hits.triangle[sel]], dtype=np.int64)  # (H, 3)
    uv = np.ascontiguousarray(hits.barycentric[sel], dtype=np.float64)
    w_in = np.ascontiguousarray(w_in, dtype=np.float64)
    if method == "reference":
        bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)  # (H, 3)
        shading_n = np.einsum("hc,hcx->hx", bary, vertex_normals[tri])
        shading_n /= np.maximum(np.linalg.norm(shading_n, axis=1, keepdims=True), 1e-300)
        front = np.sum(shading_n * w_in, axis=1) < 0.0
        psi = np.einsum("hc,nhc->hn", bary, basis[:, tri]) * front[:, None]  # (H, N)
    else:
        psi, shading_n = np.empty((len(tri), basis.shape[0])), np.empty((len(tri), 3))
        hit_basis_kernel(tri, uv, np.ascontiguousarray(vertex_normals, dtype=np.float64),
                         np.ascontiguousarray(basis, dtype=np.float64), w_in, psi, shading_n)
    if method != "reference" and _constant_h(sep):
        h = np.broadcast_to(sep.h(np.array([0.0, 0.0, 1.0])), (len(tri), sep.K))
    else:
        h = brdf.project_h(sep, -w_in, shading_n)  # (H, K)
    return h[:, :, None] * psi[:, None, :]


def _constant_h(sep) -> bool:
    """Whether ``h`` (one term, no azimuthal dependence, a constant radial table) is the same everywhere."""
    h_radial = np.asarray(sep.h_radial)
    flat = np.ptp(h_radial) <= 1e-12 * max(np.abs(h_radial).max(), 1e-300)
    return sep.K == 1 and int(sep.freq[0]) == 0 and bool(flat)


class _SourceHits(NamedTuple):
    """The hits of :func:`source_hits`'s fused path: face (int64) and barycentrics (float64) of each hit ray."""

    triangle: np.ndarray
    barycentric: np.ndarray


def source_hits(caster, points, dirs, step, method: str = "numba"):
    """The rays from every point along every direction that hit the source, in batches of ``step`` points:
    yields ``(a, b, point, direction, hits, at)``: points ``a:b``, the candidate rays (``point`` relative to
    ``a``, ``direction``), their hits (``.triangle``, ``.barycentric``) and the indices ``at`` of the hits; batches
    with no hit are skipped. ``method="numba"`` (a one-object caster with Embree) tests and traces the rays in one
    kernel (:func:`source_hits_kernel`: the candidates are the hits); ``"reference"``: :meth:`RayCaster.may_hit`
    then :meth:`RayCaster.closest_hit` of the rays it keeps. The same hits, bit for bit."""
    fused = method == "numba" and _fusable(caster)
    if fused:
        from ._residual import _tracer

        centre, radius, lo, hi = caster.may_hit_bounds()
        dirs64 = np.ascontiguousarray(dirs, dtype=np.float64)
    for a in range(0, len(points), step):
        b = min(len(points), a + step)
        if fused:
            origins = np.ascontiguousarray(points[a:b], dtype=np.float64)
            triangle = np.empty((b - a, len(dirs64)), np.int32)
            uv = np.empty((b - a, len(dirs64), 2), np.float32)
            source_hits_kernel(_tracer(caster, source_hit_tasks(b - a)), origins, dirs64,
                               np.asarray(centre, np.float64), float(radius) ** 2, lo, hi, float(caster.tnear),
                               triangle, uv)
            point, direction = np.nonzero(triangle >= 0)
            if len(point):
                hits = _SourceHits(triangle[point, direction].astype(np.int64),
                                   uv[point, direction].astype(np.float64))
                yield a, b, point, direction, hits, np.arange(len(point))
            continue
        point, direction = np.nonzero(caster.may_hit(points[a:b], dirs))  # the other rays miss the source
        hits = caster.closest_hit(points[a:b][point], dirs[direction])
        at = np.flatnonzero(hits.hit)
        if len(at):
            yield a, b, point, direction, hits, at


def _fusable(caster) -> bool:
    """Whether :func:`source_hits_kernel` can trace for ``caster`` (one object, Embree)."""
    return getattr(caster, "_scene", None) is not None and caster.n_objects == 1


def _projected_hits(caster, flat, dirs, wy, faces, normals, basis, sep, step, method, out):
    """``out`` (P, K N, n2) += the SH projection (quadrature weights and ``Y`` in ``wy``) of the basis radiance
    at the hits of the rays from ``flat`` along ``dirs``: :func:`source_hits`, :func:`hit_basis_radiance`, then
    the dense product (``"reference"``) or :func:`project_hits_kernel` over the hits (``"numba"``)."""
    n_kb = sep.K * basis.shape[0]
    for a, b, point, direction, hits, at in source_hits(caster, flat, dirs, step, method):
        sel = (point[at], direction[at])  # sorted by point (row-major nonzero)
        value = hit_basis_radiance(hits, (at,), dirs[sel[1]], faces, normals, basis, sep,
                                   method).reshape(-1, n_kb)
        if method == "reference":
            dense = np.zeros((b - a, len(dirs), n_kb))
            dense[sel] = value
            out[a:b] = np.matmul(dense.transpose(0, 2, 1), wy)
        else:
            starts = np.searchsorted(sel[0], np.arange(b - a + 1))
            project_hits_kernel(starts, np.ascontiguousarray(sel[1]), np.ascontiguousarray(value), wy, out[a:b])


class FlatSource(NamedTuple):
    """A flat source's plane and a grid of its faces, for :func:`flat_source_hits_kernel` (:func:`flat_source`).

    ``normal`` (3,) unit normal of the plane through ``origin`` (3,); ``axes`` (2, 3) orthonormal in-plane axes;
    ``shading`` (3,) the mean vertex normal and ``spread`` the largest distance of a vertex normal from it;
    ``low``, ``high`` (2,) the faces' bounds in plane coordinates, split in ``cells`` x ``cells`` cells of
    ``1 / inv_cell`` (2,); the faces whose bounds meet cell ``c`` are ``cell_faces[c]`` (slots, int32, -2 past
    them) and ``cell_affine[c, :, m]`` maps plane coordinates ``(s, r)`` to the barycentrics of slot ``m``'s face
    (of its vertices 1 and 2), ``(a0 s + a1 r + a2, a3 s + a4 r + a5)`` (``(-1, -1)`` in an empty slot);
    ``inv_height`` one over the least face height; ``extent`` the largest vertex coordinate (absolute)."""

    normal: np.ndarray
    origin: np.ndarray
    axes: np.ndarray
    shading: np.ndarray
    spread: float
    low: np.ndarray
    high: np.ndarray
    inv_cell: np.ndarray
    cells: int
    cell_faces: np.ndarray
    cell_affine: np.ndarray
    inv_height: float
    extent: float


#: Largest spread of a flat source's vertex normals, and most faces in a cell (:class:`FlatSource`), for which
#: its hits are located.
_FLAT_SPREAD = 0.5
_FLAT_SLOTS = 64
_FLAT_SOURCES: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def flat_source(vertices, faces, vertex_normals) -> FlatSource | None:
    """The :class:`FlatSource` of a mesh whose vertices lie on one plane (within ``1e-9`` of its diagonal), or
    None (not flat, a face of zero area, no face, vertex normals spread over more than ``_FLAT_SPREAD``, more
    than ``_FLAT_SLOTS`` faces in a cell)."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if len(faces) == 0:
        return None
    used = np.unique(faces)
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    cross = np.cross(b - a, c - a)
    area2 = np.linalg.norm(cross, axis=1)
    if not np.all(area2 > 0.0):
        return None
    k = int(np.argmax(area2))
    normal, origin = cross[k] / area2[k], a[k]
    diagonal = float(np.linalg.norm(np.ptp(vertices[used], axis=0)))
    if np.max(np.abs((vertices[used] - origin) @ normal)) > 1e-9 * diagonal:
        return None
    shading = np.asarray(vertex_normals, dtype=np.float64)[used].mean(axis=0)
    spread = float(np.max(np.linalg.norm(np.asarray(vertex_normals, dtype=np.float64)[used] - shading, axis=1)))
    if not spread <= _FLAT_SPREAD:
        return None
    e1 = (b[k] - a[k]) / np.linalg.norm(b[k] - a[k])
    axes = np.stack([e1, np.cross(normal, e1)])
    q = (vertices - origin) @ axes.T  # (V, 2) plane coordinates
    qa, qb, qc = q[faces[:, 0]], q[faces[:, 1]], q[faces[:, 2]]
    bx, by, cx, cy = qb[:, 0] - qa[:, 0], qb[:, 1] - qa[:, 1], qc[:, 0] - qa[:, 0], qc[:, 1] - qa[:, 1]
    det = bx * cy - by * cx
    if not np.all(det != 0.0):
        return None
    affine = np.stack([cy / det, -cx / det, (qa[:, 1] * cx - qa[:, 0] * cy) / det,
                       -by / det, bx / det, (qa[:, 0] * by - qa[:, 1] * bx) / det], axis=1)
    longest = np.max(np.stack([np.linalg.norm(b - a, axis=1), np.linalg.norm(c - b, axis=1),
                               np.linalg.norm(a - c, axis=1)]), axis=0)
    corners = q[faces]  # (F, 3, 2)
    low, high = corners.min(axis=(0, 1)), corners.max(axis=(0, 1))
    cells = int(min(1024, max(1, math.isqrt(len(faces)))))
    inv_cell = cells / np.maximum(high - low, 1e-300)
    c_lo = np.clip(np.floor((corners.min(axis=1) - low) * inv_cell), 0, cells - 1).astype(np.int64)
    c_hi = np.clip(np.floor((corners.max(axis=1) - low) * inv_cell), 0, cells - 1).astype(np.int64)
    n_s, n_r = c_hi[:, 0] - c_lo[:, 0] + 1, c_hi[:, 1] - c_lo[:, 1] + 1
    count = n_s * n_r
    face = np.repeat(np.arange(len(faces)), count)
    step = np.arange(len(face)) - np.repeat(np.cumsum(count) - count, count)
    cell = (c_lo[face, 0] + step // n_r[face]) * cells + c_lo[face, 1] + step % n_r[face]
    order = np.argsort(cell, kind="stable")
    cell, face = cell[order], face[order]
    per_cell = np.bincount(cell, minlength=cells * cells)
    slots = int(per_cell.max())
    if slots > _FLAT_SLOTS:
        return None
    slot = np.arange(len(cell)) - np.repeat(np.cumsum(per_cell) - per_cell, per_cell)
    cell_faces = np.full((cells * cells, slots), -2, np.int32)
    cell_faces[cell, slot] = face
    cell_affine = np.zeros((cells * cells, 6, slots))
    cell_affine[:, 2, :] = cell_affine[:, 5, :] = -1.0  # an empty slot: barycentrics (-1, -1), never inside
    cell_affine[cell, :, slot] = affine[face]
    return FlatSource(normal, origin, axes, shading, spread, low, high, inv_cell, cells, cell_faces, cell_affine,
                      float(1.0 / np.min(area2 / longest)), float(np.max(np.abs(vertices[used]))))


def _flat_source_of(caster, vertex_normals) -> FlatSource | None:
    """:func:`flat_source` of a one-object caster's mesh, kept while the caster lives (for the same normals)."""
    kept = _FLAT_SOURCES.get(caster)
    if kept is not None and np.array_equal(kept[0], vertex_normals):
        return kept[1]
    plane = flat_source(caster.world_vertices(0), caster.faces(0), vertex_normals)
    _FLAT_SOURCES[caster] = (np.array(vertex_normals, dtype=np.float64), plane)
    return plane


def _ray_tracer(caster, n_tasks: int):
    """A one-ray-at-a-time closest-hit query of a one-object caster's Embree scene (``_raycast._Tracer``), one slot
    per task: what :func:`flat_source_hits_kernel` traces its undecided rays with."""
    import numba

    from prtlab.geometry import _embree, _raycast

    slot_f32, slot_u32 = _embree.ray_slots(max(1, int(n_tasks)) * _embree.RAYS_PER_TASK)
    return _raycast._Tracer(caster._scene.intersect_fn, caster._scene.handle, slot_f32, slot_u32,
                            numba.get_num_threads(), False, False, _embree.packet_slots(1)[2])


def _projected_hits_fused(caster, flat, dirs, wy, faces, normals, basis, h, out, plane: FlatSource | None = None):
    """:func:`_projected_hits` (``"numba"``) for a source of constant ``h`` (K,) and a one-object Embree caster:
    per batch :func:`source_hits_kernel` then :func:`project_source_hits_kernel` (the hit radiance and its
    projection in one pass, no per-hit arrays); the same sums, term for term. With ``plane`` (a flat source's
    :class:`FlatSource`) the hits are located on it (:func:`flat_source_hits_kernel`, the undecided rays traced):
    the same faces, barycentrics within float32 rounding of Embree's."""
    from ._residual import _tracer

    centre, radius, lo, hi = caster.may_hit_bounds()
    dirs = np.ascontiguousarray(dirs, dtype=np.float64)
    centre, h = np.asarray(centre, np.float64), np.ascontiguousarray(h, dtype=np.float64)
    step = max(1, _RAYS_PER_BATCH // max(1, len(dirs)))
    basis_t = np.ascontiguousarray(np.asarray(basis, np.float64).T)  # a vertex's Psi_i in one cache line or two
    triangle = np.empty((min(step, len(flat)), len(dirs)), np.int32)
    uv = np.empty((min(step, len(flat)), len(dirs), 2), np.float32)
    for a in range(0, len(flat), step):
        b = min(len(flat), a + step)
        origins = np.ascontiguousarray(flat[a:b], dtype=np.float64)
        if plane is None:
            source_hits_kernel(_tracer(caster, source_hit_tasks(b - a)), origins, dirs, centre, float(radius) ** 2,
                               lo, hi, float(caster.tnear), triangle[:b - a], uv[:b - a])
        else:
            flat_source_hits_kernel(plane, _ray_tracer(caster, source_hit_tasks(b - a)), origins, dirs, centre,
                                    float(radius) ** 2, lo, hi, float(caster.tnear), triangle[:b - a], uv[:b - a])
        project_source_hits_kernel(triangle[:b - a], uv[:b - a], faces, normals, basis_t, h, dirs, wy, out[a:b])


def basis_radiance_at(mesh, basis, sep, points, order: int, degree: int | None = None,
                      caster: RayCaster | None = None, method: str = "numba") -> np.ndarray:
    """SH of the basis radiance ``S_(k,i)(p, .)`` of a source object at points (object space).

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The source object in object space (its ``vertex_normals`` give the shading side).
    basis : (N, n_vertices) float
        Basis functions ``Psi_i`` at the vertices (e.g. ``PCABasis.basis``).
    sep : prtlab.brdf.SeparableBRDF
        The source's separable BRDF (K terms, ``"plain"``).
    points : (..., 3) float
    order : int
    degree : int, optional
        Quadrature degree (default :data:`prtlab.shadowfields.DEFAULT_DEGREE`).
    caster : prtlab.geometry.RayCaster, optional
        A caster of ``mesh`` alone, kept by callers that cast often (building one takes milliseconds).
    method : {"numba", "reference"}
        Rays traced and projected by kernels (:func:`source_hits`'s fused trace, then a parallel sum over the
        hits only), or the float64 specification (``RayCaster.may_hit`` and ``closest_hit``, then a dense
        ``(points, K N, directions) x (directions, n*n)`` product); the same hits, except that the numba tier
        locates a flat source's hits on its plane (:func:`flat_source_hits_kernel`): the same faces, their
        barycentrics within float32 rounding of Embree's.

    Returns
    -------
    S : (..., K, N, n*n) float64
    """
    basis = np.asarray(basis, dtype=np.float64)
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if basis.ndim != 2 or basis.shape[1] != len(vertices):
        raise ValueError(f"basis must be (N, n_vertices) = (N, {len(vertices)}), got shape {basis.shape}")
    if isinstance(order, bool) or not isinstance(order, (int, np.integer)) or order < 1:
        raise ValueError(f"order must be an int >= 1, got {order!r}")
    if method not in ("numba", "reference"):
        raise ValueError(f"method must be 'numba' or 'reference', got {method!r}")
    degree = max(DEFAULT_DEGREE, 2 * order - 2) if degree is None else int(degree)
    points = as_points(points)
    batch = points.shape[:-1]
    flat = points.reshape(-1, 3)
    normals = np.asarray(mesh.vertex_normals, dtype=np.float64)
    caster = RayCaster([(vertices, faces)]) if caster is None else caster
    dirs, weights = sh.quadrature(order, degree)
    y = sh.basis(dirs, order)  # (D, n2)
    n_b, n_k, n2 = basis.shape[0], sep.K, order * order
    wy = weights[:, None] * y  # (D, n2)
    out = np.zeros((len(flat), n_k * n_b, n2))
    if method == "numba" and _constant_h(sep) and _fusable(caster) and len(flat):
        _projected_hits_fused(caster, flat, dirs, wy, faces, np.ascontiguousarray(normals),
                              np.ascontiguousarray(basis),
                              np.broadcast_to(sep.h(np.array([0.0, 0.0, 1.0])), (n_k,)), out,
                              _flat_source_of(caster, normals))
    else:
        step = max(1, _RAYS_PER_BATCH // (len(dirs) * max(1, n_k * n_b // 4)))
        _projected_hits(caster, flat, dirs, wy, faces, normals, basis, sep, step, method, out)
    return out.reshape(batch + (n_k, n_b, n2))


def basis_radiance_field(mesh, basis, sep, grid: SphereGrid, order: int, degree: int | None = None) -> np.ndarray:
    """The basis radiance field of a source object on its sample spheres (Sec. 4.3).

    Returns
    -------
    S : (n_r, 6, res, res, K, N, n*n) float64
        :func:`basis_radiance_at` at ``grid.points()``.
    """
    return basis_radiance_at(mesh, basis, sep, grid.points(), order, degree)


def self_basis_irradiance(mesh, basis, sep, points, normals, receiver_sep=None, degree: int | None = None,
                          ) -> np.ndarray:
    """Basis irradiance of an object on its own vertices (Eq. 13 with source = receiver), object space.

    ``Phi_(k',k,i)(x_j) = int S_(k,i)(x_j, w) g_k'(w) max(0, n_j . w) dw`` with ``S`` of
    :func:`basis_radiance_at` cast from the shading point itself (the ray leaves from the
    surface offset on its side, :class:`prtlab.geometry.RayCaster`), by the product
    quadrature of :func:`prtlab.sh.quadrature` of ``degree`` directly, without SH.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The object in object space.
    basis : (N, n_vertices) float
    sep : prtlab.brdf.SeparableBRDF
        The object's separable BRDF as a source (``h_k``).
    points, normals : (V, 3) float
        Receiver shading points and unit normals on the object (object space).
    receiver_sep : prtlab.brdf.SeparableBRDF, optional
        As a receiver (``g_k'``); default ``sep``.
    degree : int, optional
        Quadrature degree (default :data:`prtlab.shadowfields.DEFAULT_DEGREE`).

    Returns
    -------
    phi : (V, K', K, N) float64
    """
    receiver_sep = sep if receiver_sep is None else receiver_sep
    basis = np.asarray(basis, dtype=np.float64)
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if basis.ndim != 2 or basis.shape[1] != len(vertices):
        raise ValueError(f"basis must be (N, n_vertices) = (N, {len(vertices)}), got shape {basis.shape}")
    points = np.asarray(points, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or normals.shape != points.shape:
        raise ValueError(f"points and normals must both be (V, 3), got {points.shape} and {normals.shape}")
    degree = DEFAULT_DEGREE if degree is None else int(degree)
    n_b, n_k, n_kp = basis.shape[0], sep.K, receiver_sep.K
    out = np.zeros((len(points), n_kp, n_k, n_b))
    if len(points) == 0 or len(faces) == 0:
        return out
    vertex_normals = np.asarray(mesh.vertex_normals, dtype=np.float64)
    caster = RayCaster([(vertices, faces)])
    dirs, weights = sh.quadrature(1, degree)
    step = max(1, _RAYS_PER_BATCH // (len(dirs) * max(1, n_b // 4)))
    for a in range(0, len(points), step):
        b = min(len(points), a + step)
        nrm = normals[a:b]
        cos = nrm @ dirs.T  # (B, D)
        shape = (b - a, len(dirs), 3)
        hits = caster.closest_hit(np.broadcast_to(points[a:b, None, :], shape), np.broadcast_to(dirs, shape),
                                  normals=np.broadcast_to(nrm[:, None, :], shape))
        sel = np.nonzero(hits.hit & (cos > 0.0))
        if not len(sel[0]):
            continue
        w_in = dirs[sel[1]]
        s_hit = hit_basis_radiance(hits, sel, w_in, faces, vertex_normals, basis, sep)  # (H, K, N) of the source
        g = receiver_sep.g(brdf.to_local(w_in, nrm[sel[0]]))  # (H, K')
        g = g * (cos[sel] * weights[sel[1]])[:, None]
        contrib = np.einsum("hq,hkn->hqkn", g, s_hit).reshape(len(sel[0]), -1)
        rows, starts = np.unique(sel[0], return_index=True)  # sel[0] is sorted (row-major nonzero)
        out[a + rows] = np.add.reduceat(contrib, starts, axis=0).reshape(len(rows), n_kp, n_k, n_b)
    return out


@dataclass(frozen=True)
class StoredBasisRadiance:
    """A basis radiance field as the pipeline stores it: only its non-zero sample points, in one format.

    Attributes
    ----------
    shape : tuple of int
        The dense field's shape ``(n_r, 6, res, res, K, N, n*n)``.
    rows : (n_r, 6, res, res) int32
        Row of each sample point in ``values``; -1 where ``S_(k,i) = 0`` for every ``(k, i)`` (behind a flat
        source, inside a closed one), a point that is not stored.
    values : (n_rows, K N, n*n) float64, float32 or int16
        ``S`` at the stored points (``storage`` "float64", "float32"), or its quantised form (``"int16"``).
    scale : (n_rows, K N) float32
        ``"int16"``: ``S = scale * values`` per ``(point, k, i)``, ``scale`` the block's largest ``|S|`` over
        32767 rounded up to float32, so ``|S - scale * values| <= scale / 2``; else empty, (0, K N).
    """

    shape: tuple
    rows: np.ndarray
    values: np.ndarray
    scale: np.ndarray

    @property
    def storage(self) -> str:
        return {"f8": "float64", "f4": "float32", "i2": "int16"}[self.values.dtype.str[1:]]

    @property
    def nbytes(self) -> int:
        return int(self.rows.nbytes + self.values.nbytes + self.scale.nbytes)

    def dense(self) -> np.ndarray:
        """The field ``(n_r, 6, res, res, K, N, n*n)`` float64 as stored (0 at the points not stored)."""
        flat = np.zeros((int(np.prod(self.shape[:4])),) + self.values.shape[1:])
        at = self.rows.ravel()
        kept = at >= 0
        values = self.values.astype(np.float64)
        if self.storage == "int16":
            values *= self.scale[..., None]
        flat[kept] = values[at[kept]]
        return flat.reshape(self.shape)

    def truncated(self, n_basis: int, order: int) -> "StoredBasisRadiance":
        """The first ``n_basis`` basis functions and ``order**2`` SH coefficients (no requantisation)."""
        n_r, f, r1, r2, n_k, n_b, _ = self.shape
        n_basis, n2 = min(int(n_basis), n_b), order * order
        values = self.values.reshape(len(self.values), n_k, n_b, -1)[:, :, :n_basis, :n2]
        scale = self.scale.reshape(len(self.scale), n_k, n_b)[:, :, :n_basis]
        return StoredBasisRadiance((n_r, f, r1, r2, n_k, n_basis, n2), self.rows,
                                   np.ascontiguousarray(values.reshape(len(values), n_k * n_basis, n2)),
                                   np.ascontiguousarray(scale.reshape(len(scale), n_k * n_basis)))

    def to_arrays(self) -> dict:
        return {"shape": np.asarray(self.shape, np.int64), "rows": self.rows, "values": self.values,
                "scale": self.scale}

    @classmethod
    def from_arrays(cls, d) -> "StoredBasisRadiance":
        shape = tuple(int(x) for x in np.asarray(d["shape"]))
        values = np.ascontiguousarray(d["values"])
        if values.dtype.str[1:] not in ("f8", "f4", "i2") or len(shape) != 7:
            raise ValueError(f"not a stored basis radiance field: shape {shape}, values of dtype {values.dtype}")
        return cls(shape, np.ascontiguousarray(d["rows"], dtype=np.int32), values,
                   np.ascontiguousarray(d["scale"], dtype=np.float32))


def store_basis_radiance(field, storage: str = "int16") -> StoredBasisRadiance:
    """A dense basis radiance field (:func:`basis_radiance_field`) in a :class:`StoredBasisRadiance` format.

    ``"float64"`` keeps every value (the reference); ``"float32"`` rounds each to float32 (relative error at
    most ``2^-24``); ``"int16"`` quantises each ``(point, k, i)`` block of ``n*n`` coefficients to integers
    times a float32 scale, an absolute error at most half the block's step, ``max |S| / 65534`` (rounded up).
    Sample points where every ``S_(k,i)`` is 0 are dropped in every format (without loss).
    """
    if storage not in STORAGES:
        raise ValueError(f"storage must be one of {', '.join(map(repr, STORAGES))}, got {storage!r}")
    field = np.asarray(field, dtype=np.float64)
    if field.ndim != 7:
        raise ValueError(f"field must be (n_r, 6, res, res, K, N, n*n), got shape {field.shape}")
    m, n2 = field.shape[4] * field.shape[5], field.shape[6]
    flat = field.reshape(-1, m, n2)
    kept = np.flatnonzero(np.any(flat != 0.0, axis=(1, 2)))
    rows = np.full(len(flat), -1, np.int32)
    rows[kept] = np.arange(len(kept), dtype=np.int32)
    block = flat[kept]
    scale = np.zeros((0, m), np.float32)
    if storage == "int16":
        step = np.max(np.abs(block), axis=2) / _INT16_STEPS  # (rows, M)
        scale = step.astype(np.float32)
        low = scale < step  # rounded down: one float32 ulp up, so |S| / scale <= 32767
        scale[low] = np.nextafter(scale[low], np.float32(np.inf))
        safe = np.where(scale > 0, scale, 1.0).astype(np.float64)
        values = np.rint(block / safe[..., None]).astype(np.int16)
    else:
        values = block.astype(storage)
    return StoredBasisRadiance(field.shape, rows.reshape(field.shape[:4]), np.ascontiguousarray(values), scale)

"""The ground shaded against the objects' meshes by ray casting (an extension of Guerrero et al. 2008; option
``ground_shading="rays"``).

A ground (horizontal, normal ``+Y``, see ``_ground``) is a receiver the paper shades like any other: its direct
light through the exponentiated SH visibility of the objects' bounding spheres, its indirect light from their
emission. Both carry the sphere proxy's error where it matters most for a ground: under and beside the objects,
whose spheres' outside volume shadows and emits where the object is not, and whose spheres hold the ground under
an object's base (culled there, so that ground is lit). Here, over a fixed product rule of the upper hemisphere
(Gauss-Legendre in ``cos theta`` times uniform azimuths, ``w_j`` folding in the cosine),

.. math:: E^{dir}(p) = \\int L(\\omega) \\cos\\theta\\, d\\omega
          - \\sum_j w_j\\, L(\\omega_j)\\, B_p(\\omega_j), \\qquad
          E^{ind}(p) = \\sum_j w_j\\, L_o\\big(x_p(\\omega_j)\\big),

the first integral in closed form from the environment's SH (exact for the band-limited environment), ``B_p``
the rays blocked by a mesh (or a local light's sphere), ``x_p(w)`` the first mesh hit and ``L_o`` the objects'
shaded exit radiance there (the pipeline's own per-vertex result, interpolated over the hit face; a back face
hit, from a point inside a closed object, gives 0). Only rays that meet a bounding sphere of the objects (or a
local light) are cast: the spheres bound the meshes (``_fit``), so the others hit nothing. With ``spacing > 0``
the rays are cast only at the points near the spheres and at the nodes of coarser grids farther out, the light
between interpolated bilinearly (:func:`ground_ray_nodes`; the ground's light is smooth away from the contacts).
The points are cast in chunks of :data:`_CHUNK`, the chunks as tasks on numba's threads (:mod:`prtlab._tasks`;
each chunk writes its own rows, so the results are the same bit for bit).

The geometry (which ray meets which face where, which rays are blocked: :class:`GroundHits`, from
:func:`ground_light_hits` and :func:`ground_direct_hits`) does not depend on the lighting; :func:`ground_light_sums`
and :func:`ground_direct_sums` evaluate it for an environment and the objects' radiance, so a caller may keep it
while the blockers and points stay the same (``SphereLights``' :class:`~prtlab.spherelights._reuse.FrameReuse`).

Measured figures: ``docs/notes/spherelights.md``.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numba
import numpy as np

from prtlab import sh
from prtlab._tasks import run_tasks
from ._meshdirect import _cones

__all__ = ["GroundRayRule", "ground_ray_rule", "MeshBlockers", "mesh_blockers", "ground_direct_rays",
           "ground_gather_rays", "ground_light_rays", "GroundHits", "ground_direct_hits", "ground_direct_sums",
           "ground_light_hits", "ground_light_sums", "ground_hits_update", "contact_radiance",
           "candidate_rays", "sphere_hits", "ground_ray_nodes", "MAX_SPACING"]

_UP = np.array([0.0, 1.0, 0.0])
_CHUNK = 256  # receivers per batch of rays (bounds the (P, K) arrays)
#: The largest ``spacing`` of :func:`ground_ray_nodes`: a cell's nodes then stay outside the spheres
#: (``gap - sqrt(2) h > 0`` for ``h <= spacing * gap``).
MAX_SPACING = 0.7
_FINEST = 2.0  # the finest grid's side over the points' mean spacing


class GroundRayRule(NamedTuple):
    """Directions ``(K, 3)`` over the upper hemisphere (``+Y``) and weights ``(K,)``: solid angle times
    ``cos theta``, summing to ``pi``."""

    dirs: np.ndarray
    weights: np.ndarray


@functools.lru_cache(maxsize=None)
def ground_ray_rule(n_azimuth: int = 64, n_elevation: int = 16) -> GroundRayRule:
    """:class:`GroundRayRule` of ``n_elevation`` Gauss-Legendre nodes in ``cos theta`` times ``n_azimuth``
    uniform azimuths (``K = n_azimuth * n_elevation`` rays)."""
    from prtlab._validate import check_int

    check_int(n_azimuth, "n_azimuth", 1)
    check_int(n_elevation, "n_elevation", 1)
    x, w = np.polynomial.legendre.leggauss(n_elevation)
    mu, w_mu = 0.5 * (x + 1.0), 0.5 * w
    phi = (np.arange(n_azimuth) + 0.5) * (2.0 * np.pi / n_azimuth)
    mm, pp = np.meshgrid(mu, phi, indexing="ij")
    s = np.sqrt(1.0 - mm * mm)
    dirs = np.stack([s * np.cos(pp), mm, s * np.sin(pp)], -1).reshape(-1, 3)
    weights = (w_mu[:, None] * mm * (2.0 * np.pi / n_azimuth)).reshape(-1)
    dirs.setflags(write=False)
    weights.setflags(write=False)
    return GroundRayRule(dirs, weights)


class MeshBlockers(NamedTuple):
    """What the rays of a frame meet, in the rays' frame (see :func:`mesh_blockers`): the objects' meshes (a
    :class:`prtlab.geometry.RayCaster`, object ``g``'s faces ``faces[g]``), their bounding spheres (``bounds``:
    ``(S, 4)`` centre and radius; a ray missing them all misses the meshes), opaque spheres (``spheres``: ``(L,
    4)``, the local lights) and the frame (``origin (3,)``, ``turn``: the world directions of its axes as columns,
    a turn about ``+Y``; ``scale``); ``mesh_balls (G, 4)``: per mesh a ball around its vertices in the rays' frame
    (what :func:`ground_hits_update` recasts near)."""

    caster: object
    faces: tuple
    bounds: np.ndarray
    spheres: np.ndarray
    origin: np.ndarray
    turn: np.ndarray
    scale: float
    mesh_balls: np.ndarray | None = None


def object_size(local_vertices, scale: float = 1.0) -> float:
    """The diagonal of the bounding box of an object's vertices in its own frame, times its scale: the length
    :func:`mesh_blockers` scales its rays' offset by (the largest over the objects), the same at every rigid pose."""
    v = np.asarray(local_vertices, dtype=np.float64).reshape(-1, 3)
    return float(np.linalg.norm(v.max(axis=0) - v.min(axis=0))) * float(scale) if len(v) else 0.0


def mesh_blockers(meshes, bounds, spheres=(), origin=(0.0, 0.0, 0.0), azimuth: float = 0.0,
                  scale: float = 1.0, size: float | None = None) -> MeshBlockers:
    """:class:`MeshBlockers` from world meshes ``[(vertices (V, 3), faces (F, 3))]``, bounding spheres ``(S, 4)``
    (rows ``[x, y, z, r]``; every mesh must lie inside their union) and opaque spheres ``(L, 4)``.

    The rays are cast in the frame at ``origin`` turned by ``azimuth`` about ``+Y`` (its ``x`` axis the world's
    ``(cos a, 0, sin a)``) and shrunk by ``scale``: given a ground's own frame, a similarity of the whole scene
    casts the same rays (the caster computes in float32), and the rule's azimuths turn with the ground.
    ``size`` (world units): the length the rays' offset off the ground is ``RAY_EPSILON_SCALE`` of
    (:func:`object_size`: it does not change when an object moves or turns, so a move keeps the other rays'
    origins and :func:`ground_hits_update` can keep their hits); None: the meshes' bounding-box diagonal at this
    pose, the caster's own offset."""
    from prtlab.geometry import RayCaster
    from prtlab.geometry._raycast import RAY_EPSILON_SCALE

    o = np.asarray(origin, dtype=np.float64).reshape(3)
    c, s = math.cos(azimuth), math.sin(azimuth)
    turn = np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])
    scale = float(scale)

    def local(x):
        return (np.asarray(x, dtype=np.float64).reshape(-1, 3) - o) @ turn / scale

    def balls(b):
        b = np.asarray(b, dtype=np.float64).reshape(-1, 4)
        return np.concatenate([local(b[:, :3]), b[:, 3:] / scale], axis=1)

    meshes = [(local(v), np.asarray(f, dtype=np.int64)) for v, f in meshes]
    epsilon = None if size is None else RAY_EPSILON_SCALE * float(size) / scale
    caster = RayCaster(meshes, epsilon=epsilon) if meshes else None
    mesh_balls = np.zeros((len(meshes), 4))
    for g, (v, _) in enumerate(meshes):
        if len(v):
            mesh_balls[g, :3] = 0.5 * (v.min(axis=0) + v.max(axis=0))
            mesh_balls[g, 3] = np.linalg.norm(v - mesh_balls[g, :3], axis=1).max()
    return MeshBlockers(caster, tuple(f for _, f in meshes), balls(bounds), balls(spheres), o, turn, scale,
                        mesh_balls)


def _local_points(points, blockers: MeshBlockers) -> np.ndarray:
    return np.ascontiguousarray((np.asarray(points, dtype=np.float64).reshape(-1, 3) - blockers.origin)
                                @ blockers.turn / blockers.scale)


def ground_ray_nodes(points, spheres, spacing: float):
    """Where the rays of ground points are cast when the light between them is interpolated: the points near the
    spheres themselves, the others from the corners of a square cell of a grid in the ground plane.

    A point at distance ``gap`` from the nearest sphere's surface takes the bilinear interpolation over the cell of
    the coarsest grid of side ``h_l = h_0 2^l <= spacing * gap`` that contains it (every grid aligned with the
    points' bounding box, its lower corner a node, ``h_0 = 2 sqrt(area / P)``: a quarter of the points' density,
    ``h_l`` at most the box's longer side); a point with ``spacing * gap < h_0`` (or inside a sphere) is cast at
    itself. If that would cast at as many places as there are points, every point is cast at itself. The result
    is continuous within a grid's cells, not where neighbouring points take grids of different sides.

    Parameters
    ----------
    points : (P, 3) float
        Points of one ground (``x, z`` in its plane, one ``y``; e.g. in :class:`MeshBlockers`' frame). Points of
        several heights are all cast at themselves.
    spheres : (S, 4) float
        ``[x, y, z, r]``: what the rays meet (the meshes' bounding spheres and the opaque ones).
    spacing : float
        In ``[0, MAX_SPACING]``; 0 casts at every point.

    Returns
    -------
    cast : (C, 3) float
        Where to cast: the points cast at themselves (in their order), then the grid nodes (``y`` the points').
    rows : (P, 4) int
        Rows of ``cast`` whose values a point takes, with ``weights (P, 4)`` (summing to 1; a point cast at itself:
        its own row with weights ``1, 0, 0, 0``): ``value[p] = sum_c weights[p, c] value[rows[p, c]]``.
    """
    from prtlab._validate import check_float

    spacing = check_float(spacing, "spacing", 0.0, MAX_SPACING, meaning="0: every point cast")
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    sph = np.asarray(spheres, dtype=np.float64).reshape(-1, 4)
    n = len(p)
    rows = np.repeat(np.arange(n, dtype=np.int64)[:, None], 4, axis=1)
    weights = np.zeros((n, 4))
    weights[:, 0] = 1.0
    lo, hi = p.min(axis=0, initial=np.inf), p.max(axis=0, initial=-np.inf)
    extent = max(hi[0] - lo[0], hi[2] - lo[2]) if n else 0.0
    if not spacing or n < 8 or not len(sph) or extent <= 0.0 or hi[1] - lo[1] > 1e-12 * extent:
        return p, rows, weights
    h0 = _FINEST * math.sqrt(max(hi[0] - lo[0], 1e-3 * extent) * max(hi[2] - lo[2], 1e-3 * extent) / n)
    gap = np.empty(n)
    _gaps(p, sph, gap)
    top = int(math.floor(math.log2(extent / h0))) if extent >= h0 else -1
    with np.errstate(divide="ignore", invalid="ignore"):
        level = np.floor(np.log2(spacing * gap / h0))
    level = np.where(gap > 0.0, np.minimum(level, top), -1.0).astype(np.int64)
    near = level < 0
    far = np.nonzero(~near)[0]
    if not len(far):
        return p, rows, weights
    step = np.left_shift(1, level[far])  # the cell's side in units of h0
    h = h0 * step
    fx, fz = (p[far, 0] - lo[0]) / h, (p[far, 2] - lo[2]) / h
    ix, iz = np.floor(fx), np.floor(fz)
    u, v = fx - ix, fz - iz
    ix, iz = ix.astype(np.int64) * step, iz.astype(np.int64) * step  # the cell's lower corner, units of h0
    width = int(math.ceil(extent / h0)) + 2 * (1 << max(top, 0)) + 2
    keys = np.stack([ix * width + iz, (ix + step) * width + iz, ix * width + iz + step,
                     (ix + step) * width + iz + step], axis=1)  # the corners in the order of the weights below
    nodes, inverse = _unique_keys(keys)
    exact = np.nonzero(near)[0]
    if len(exact) + len(nodes) >= n:
        return p, rows, weights
    cast = np.empty((len(exact) + len(nodes), 3))
    cast[: len(exact)] = p[exact]
    cast[len(exact):, 0] = lo[0] + (nodes // width) * h0
    cast[len(exact):, 1] = p[0, 1]
    cast[len(exact):, 2] = lo[2] + (nodes % width) * h0
    rows[exact] = np.arange(len(exact))[:, None]
    rows[far] = len(exact) + inverse.reshape(-1, 4)
    weights[far] = np.stack([(1 - u) * (1 - v), u * (1 - v), (1 - u) * v, u * v], axis=1)
    return cast, rows, weights


def _unique_keys(keys):
    """``np.unique(keys, return_inverse=True)`` of non-negative int64 ``keys``: by marking a dense table when the
    largest key is at most 16 times their number (no sort), else by ``np.unique``."""
    top = int(keys.max(initial=-1)) + 1
    if keys.size == 0 or keys.min() < 0 or top > 16 * keys.size:
        return np.unique(keys, return_inverse=True)
    seen = np.zeros(top, dtype=bool)
    seen[keys.ravel()] = True
    nodes = np.flatnonzero(seen)
    rank = np.cumsum(seen) - 1
    return nodes, rank[keys]


@numba.njit(cache=True)
def _gaps(points, spheres, out):
    """``out[p]``: the least ``|p - c| - r`` over the spheres, as numpy's ``min(sqrt(sum((p - c)^2)) - r)``."""
    for q in range(points.shape[0]):
        gap = np.inf
        for j in range(spheres.shape[0]):
            dx, dy, dz = points[q, 0] - spheres[j, 0], points[q, 1] - spheres[j, 1], points[q, 2] - spheres[j, 2]
            gap = min(gap, math.sqrt(dx * dx + dy * dy + dz * dz) - spheres[j, 3])
        out[q] = gap


def _interpolated(values, rows, weights) -> np.ndarray:
    """``(P, 3)``: ``sum_c weights[:, c] values[rows[:, c]]`` (see :func:`ground_ray_nodes`), summed over ``c`` in
    order as :func:`_interpolated_reference` sums them (the same bits)."""
    out = np.empty((rows.shape[0], values.shape[1]))
    _interpolated_kernel(np.ascontiguousarray(values, dtype=np.float64), np.ascontiguousarray(rows, dtype=np.int64),
                         np.ascontiguousarray(weights, dtype=np.float64), out)
    return out


@numba.njit(cache=True, parallel=True, nogil=True)
def _interpolated_kernel(values, rows, weights, out):
    for p in numba.prange(rows.shape[0]):
        for j in range(values.shape[1]):
            acc = values[rows[p, 0], j] * weights[p, 0]
            for c in range(1, rows.shape[1]):
                acc += values[rows[p, c], j] * weights[p, c]
            out[p, j] = acc


def _interpolated_reference(values, rows, weights) -> np.ndarray:
    """numpy specification of :func:`_interpolated` (about 1 ms for the benchmark's 16,800 ground points)."""
    out = values[rows[:, 0]] * weights[:, :1]
    for c in range(1, rows.shape[1]):
        out += values[rows[:, c]] * weights[:, c:c + 1]
    return out


def sphere_hits(points, dirs, spheres, *, method: str = "numba") -> np.ndarray:
    """``(P, K)`` distance to the first of ``spheres (L, 4)`` (rows ``[x, y, z, r]``) along each ray ``p + t d``
    from ``points (P, 3)`` along unit ``dirs (K, 3)``: ``t > 0``, inf where none is met, 0 from inside one.
    ``method``: ``"numba"`` (the kernel) or ``"reference"`` (the float64 numpy specification)."""
    from prtlab._validate import check_choice

    check_choice(method, "method", ("numba", "reference"))
    p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    d = np.ascontiguousarray(dirs, dtype=np.float64).reshape(-1, 3)
    sph = np.ascontiguousarray(spheres, dtype=np.float64).reshape(-1, 4)
    if method == "reference":
        return _sphere_hits_reference(p, d, sph)
    out = np.empty((len(p), len(d)))
    _sphere_hits_kernel(p, d, sph, out)
    return out


def _sphere_hits_reference(points, dirs, spheres) -> np.ndarray:
    out = np.full((len(points), len(dirs)), np.inf)
    for c in spheres:
        o = c[:3] - points  # (P, 3)
        b = o @ dirs.T  # (P, K)
        c2 = np.einsum("pi,pi->p", o, o)[:, None] - c[3] * c[3]
        disc = b * b - c2
        t = np.where(disc > 0.0, b - np.sqrt(np.maximum(disc, 0.0)), np.inf)
        t = np.where(c2 <= 0.0, 0.0, np.where(t > 0.0, t, np.inf))
        np.minimum(out, t, out=out)
    return out


@numba.njit(cache=True, parallel=True, nogil=True)
def _sphere_hits_kernel(points, dirs, spheres, out):
    """``sphere_hits``: per point, the spheres it does not lie in are tested along every ray."""
    for q in numba.prange(points.shape[0]):
        for k in range(dirs.shape[0]):
            out[q, k] = np.inf
        for j in range(spheres.shape[0]):
            ox, oy, oz = spheres[j, 0] - points[q, 0], spheres[j, 1] - points[q, 1], spheres[j, 2] - points[q, 2]
            c2 = ox * ox + oy * oy + oz * oz - spheres[j, 3] * spheres[j, 3]
            if c2 <= 0.0:
                for k in range(dirs.shape[0]):
                    out[q, k] = 0.0
                continue
            for k in range(dirs.shape[0]):
                b = ox * dirs[k, 0] + oy * dirs[k, 1] + oz * dirs[k, 2]
                disc = b * b - c2
                if b > 0.0 and disc > 0.0:
                    t = b - math.sqrt(disc)
                    if t < out[q, k]:
                        out[q, k] = t


def candidate_rays(points, dirs, bounds, *, method: str = "numba") -> np.ndarray:
    """``(P, K)`` bool: the rays from ``points (P, 3)`` along unit ``dirs (K, 3)`` that meet one of ``bounds (S,
    4)`` (``isfinite`` of :func:`sphere_hits`; the kernel tests the ray's angle to each sphere's cone and stops at
    the first). ``method``: ``"numba"`` or ``"reference"``."""
    from prtlab._validate import check_choice

    check_choice(method, "method", ("numba", "reference"))
    p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    d = np.ascontiguousarray(dirs, dtype=np.float64).reshape(-1, 3)
    b = np.ascontiguousarray(bounds, dtype=np.float64).reshape(-1, 4)
    if method == "reference":
        return np.isfinite(_sphere_hits_reference(p, d, b))
    return _candidates(p, d, b, _rings(d))


def _candidates(points, dirs, bounds, n_azimuth: int, counts=None) -> np.ndarray:
    """``candidate_rays``' kernels on checked arrays; ``n_azimuth``: ``_rings(dirs)``; ``counts (P,)``, if given,
    receives each point's number of candidates."""
    out = np.empty((len(points), len(dirs)), dtype=np.bool_)
    counts = np.empty(0, dtype=np.int64) if counts is None else counts
    if n_azimuth:
        _candidates_rings_kernel(points, dirs, n_azimuth, bounds, out, counts)
    else:
        _candidates_kernel(points, dirs, bounds, out, counts)
    return out


def _rings(dirs) -> int:
    """The azimuths per ring if ``dirs`` are a product rule as :func:`ground_ray_rule` makes (rings of one ``y``,
    each ``A`` azimuths ``(j + 1/2) 2 pi / A`` in order), else 0."""
    k = len(dirs)
    if k == 0:
        return 0
    a = int(np.argmax(dirs[:, 1] != dirs[0, 1])) or k
    if k % a or not np.all(dirs[:, 1].reshape(-1, a) == dirs[::a, 1:2]):
        return 0
    phi = np.arctan2(dirs[:, 2], dirs[:, 0]) % (2.0 * np.pi)
    expect = np.tile((np.arange(a) + 0.5) * (2.0 * np.pi / a), k // a)
    return a if np.allclose(phi, expect, rtol=0.0, atol=1e-9) else 0


@numba.njit(cache=True, inline="always")
def _count_row(out, q, counts):
    """``counts[q]``: the candidates of row ``q`` (skipped if ``counts`` is empty)."""
    if counts.shape[0]:
        c = 0
        for k in range(out.shape[1]):
            c += out[q, k]
        counts[q] = c


@numba.njit(cache=True, parallel=True, nogil=True)
def _candidates_kernel(points, dirs, spheres, out, counts):
    """``candidate_rays``: per point, each sphere's cone (unit axis, cosine of its half angle); a ray meets the
    sphere when its cosine to the axis exceeds that (a point inside a sphere: every ray)."""
    n_s = spheres.shape[0]
    for q in numba.prange(points.shape[0]):
        axis = np.empty((n_s, 3))
        cos_half = np.empty(n_s)
        inside = _cones(points[q], spheres, axis, cos_half)
        for k in range(dirs.shape[0]):
            out[q, k] = inside or _in_a_cone(dirs, k, axis, cos_half)
        _count_row(out, q, counts)


@numba.njit(cache=True, inline="always")
def _in_a_cone(dirs, k, axis, cos_half) -> bool:
    """Whether direction ``k`` lies in one of the cones of ``_meshdirect._cones`` (tested in order, first found)."""
    for j in range(axis.shape[0]):
        if axis[j, 0] * dirs[k, 0] + axis[j, 1] * dirs[k, 1] + axis[j, 2] * dirs[k, 2] > cos_half[j]:
            return True
    return False


@numba.njit(cache=True, parallel=True, nogil=True)
def _candidates_rings_kernel(points, dirs, n_azimuth, spheres, out, counts):
    """``_candidates_kernel`` for a product rule (``_rings``): per ring, a sphere whose cone no direction of the
    ring can enter (the largest cosine over the ring's azimuths below its half angle's, with a margin) is skipped,
    and the others are tested only at the azimuths of their window (widened by one azimuth each side); the test of
    a direction against a sphere is ``_candidates_kernel``'s, so the result is the same."""
    n_ring = dirs.shape[0] // n_azimuth
    ring_sin = np.empty(n_ring)
    for e in range(n_ring):
        ring_sin[e] = math.sqrt(max(0.0, 1.0 - dirs[e * n_azimuth, 1] ** 2))
    no_cones, no_cos, no_cand = np.empty((0, 3)), np.empty(0), np.empty((0, 0), dtype=np.bool_)
    for q in numba.prange(points.shape[0]):
        c, _ = _ring_row(points, q, dirs, n_azimuth, ring_sin, spheres, out, False, no_cones, no_cos, False,
                         no_cand)
        if counts.shape[0]:
            counts[q] = c


@numba.njit(cache=True, parallel=True, nogil=True)
def _zone_candidates_kernel(points, dirs, n_azimuth, spheres, bounds, zone, cand, zone_counts, cand_counts):
    """``_candidates_rings_kernel``'s rays in the cones of ``spheres`` (``zone``, ``zone_counts``) and, of those,
    the candidates against ``bounds`` (``cand``, ``cand_counts``: ``_candidates_within``'s test), in one pass."""
    n_ring = dirs.shape[0] // n_azimuth
    ring_sin = np.empty(n_ring)
    for e in range(n_ring):
        ring_sin[e] = math.sqrt(max(0.0, 1.0 - dirs[e * n_azimuth, 1] ** 2))
    for q in numba.prange(points.shape[0]):
        b_axis = np.empty((bounds.shape[0], 3))
        b_cos = np.empty(bounds.shape[0])
        b_in = _cones(points[q], bounds, b_axis, b_cos)
        zone_counts[q], cand_counts[q] = _ring_row(points, q, dirs, n_azimuth, ring_sin, spheres, zone, True, b_axis,
                                                   b_cos, b_in, cand)


@numba.njit(cache=True, inline="always")
def _ring_row(points, q, dirs, n_azimuth, ring_sin, spheres, out, with_cand, b_axis, b_cos, b_in, cand):
    """Row ``q`` of ``_candidates_rings_kernel`` into ``out``; with ``with_cand`` also ``cand[q, k]`` for its rays:
    the ray in a cone ``(b_axis, b_cos)`` (``b_in``: every ray), ``cand`` False elsewhere. Returns the counts of
    both."""
    n_s = spheres.shape[0]
    step = 2.0 * math.pi / n_azimuth
    n_ring = dirs.shape[0] // n_azimuth
    axis = np.empty((n_s, 3))
    cos_half = np.empty(n_s)
    rho = np.empty(n_s)  # |axis| in the horizontal plane
    centre = np.empty(n_s)  # the axis's azimuth in units of the azimuth step, less 1/2
    inside = False
    for j in range(n_s):
        ox, oy, oz = spheres[j, 0] - points[q, 0], spheres[j, 1] - points[q, 1], spheres[j, 2] - points[q, 2]
        d2 = ox * ox + oy * oy + oz * oz
        r2 = spheres[j, 3] * spheres[j, 3]
        if d2 <= r2:
            inside = True
            break
        inv = 1.0 / math.sqrt(d2)
        axis[j, 0], axis[j, 1], axis[j, 2] = ox * inv, oy * inv, oz * inv
        cos_half[j] = math.sqrt(1.0 - r2 / d2)
        rho[j] = math.sqrt(axis[j, 0] ** 2 + axis[j, 2] ** 2)
        centre[j] = math.atan2(axis[j, 2], axis[j, 0]) / step - 0.5
    count, n_cand = 0, 0
    out[q, :] = inside
    if with_cand:
        cand[q, :] = False
    if inside:
        if with_cand:
            for k in range(dirs.shape[0]):
                cand[q, k] = b_in or _in_a_cone(dirs, k, b_axis, b_cos)
                n_cand += cand[q, k]
        return dirs.shape[0], n_cand
    for e in range(n_ring):
        base = e * n_azimuth
        mu = dirs[base, 1]
        for j in range(n_s):
            ax, ay, az = axis[j, 0], axis[j, 1], axis[j, 2]
            rho_s = rho[j] * ring_sin[e]
            if ay * mu + rho_s < cos_half[j] - 1e-9:
                continue  # no direction of the ring enters the cone
            lo, hi = 0, n_azimuth - 1
            if rho_s > 1e-9:
                x = (cos_half[j] - ay * mu) / rho_s  # cos(phi - phi_axis) > x inside the cone
                if x > -1.0:
                    half = math.acos(min(x, 1.0)) / step
                    lo = int(math.floor(centre[j] - half)) - 1
                    hi = int(math.ceil(centre[j] + half)) + 1
                    if hi - lo + 1 >= n_azimuth:
                        lo, hi = 0, n_azimuth - 1
            t = lo % n_azimuth  # the azimuths lo..hi, wrapped (one division per window, not per ray)
            for _ in range(hi - lo + 1):
                k = base + t
                if not out[q, k] and ax * dirs[k, 0] + ay * dirs[k, 1] + az * dirs[k, 2] > cos_half[j]:
                    out[q, k] = True
                    count += 1
                    if with_cand and (b_in or _in_a_cone(dirs, k, b_axis, b_cos)):
                        cand[q, k] = True
                        n_cand += 1
                t = t + 1 if t + 1 < n_azimuth else 0
    return count, n_cand


def _chunk_sizes(cast, blockers: MeshBlockers, n_rays: int) -> list:
    """Per chunk of :data:`_CHUNK` points of ``cast`` (local) an estimate of its rays, for :func:`run_tasks`'
    ``sizes`` (a chunk holding more than its share of the work runs first, on every thread): per point, ``n_rays``
    times the fraction of the sphere of directions in the cones of the bounding and opaque spheres (capped at the
    hemisphere, every ray inside a sphere), plus one ray. Scheduling only: the chunks' rays are the same."""
    spheres = np.concatenate([blockers.bounds.reshape(-1, 4), blockers.spheres.reshape(-1, 4)])
    if not len(cast) or not len(spheres):
        return [1.0] * len(range(0, len(cast), _CHUNK))
    d2 = np.sum((spheres[None, :, :3] - cast[:, None]) ** 2, axis=2)
    r2 = spheres[None, :, 3] ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        cone = np.where(d2 > r2, 0.5 * (1.0 - np.sqrt(np.maximum(0.0, 1.0 - r2 / d2))), 1.0)
    rays = 1.0 + n_rays * np.minimum(2.0 * cone.sum(axis=1), 1.0)
    return [float(rays[s:s + _CHUNK].sum()) for s in range(0, len(cast), _CHUNK)]


def _chunk_rays(rule, blockers):
    """``chunk(points, s)``, for the chunk of ``points`` from ``s`` (:data:`_CHUNK` points): its slice, the
    candidate rays ``(P, K)``, their point and rule direction indices (flat, as ``np.nonzero``), the distance to
    the first opaque sphere ``(P, K)`` (None: none), their origins (offset off the ground as the caster offsets
    them along a normal ``+Y``: cast them without normals) and directions (flat) and each point's first ray
    (``(P + 1,)``)."""
    dirs = np.ascontiguousarray(rule.dirs, dtype=np.float64)
    n_azimuth = _rings(dirs) if blockers.caster is not None else 0
    bounds = np.ascontiguousarray(blockers.bounds, dtype=np.float64)
    lift = blockers.caster.epsilon if blockers.caster is not None else 0.0

    def chunk(points, s):
        p = points[s:s + _CHUNK]
        counts = np.zeros(len(p), dtype=np.int64)
        cand = _candidates(p, dirs, bounds, n_azimuth, counts) if blockers.caster is not None else np.zeros(
            (len(p), len(rule.dirs)), dtype=bool)
        t_sphere = sphere_hits(p, rule.dirs, blockers.spheres) if len(blockers.spheres) else None
        ptr = np.zeros(len(p) + 1, dtype=np.int64)
        np.cumsum(counts, out=ptr[1:])
        ip, ik = np.empty(ptr[-1], dtype=np.int64), np.empty(ptr[-1], dtype=np.int64)
        origins, ray_dirs = np.empty((ptr[-1], 3)), np.empty((ptr[-1], 3))
        _list_rays(p, cand, dirs, ptr, lift, ip, ik, origins, ray_dirs)
        return slice(s, s + len(p)), cand, ip, ik, t_sphere, origins, ray_dirs, ptr

    return chunk


@numba.njit(cache=True, parallel=True, nogil=True)
def _list_rays(points, cand, dirs, ptr, epsilon, ip, ik, origins, ray_dirs):
    """The candidate rays as lists, point by point (``ptr[q]:ptr[q + 1]``) in the order of ``np.nonzero(cand)``:
    their point ``ip`` and direction ``ik``, origin ``points[ip]`` offset by ``epsilon`` along the normal ``+Y``
    on the side of the ray (the arithmetic of ``RayCaster``'s ``normals``) and direction ``dirs[ik]``."""
    for q in numba.prange(points.shape[0]):
        i = ptr[q]
        for k in range(cand.shape[1]):
            if cand[q, k]:
                ip[i], ik[i] = q, k
                side = epsilon if dirs[k, 1] >= 0.0 else -epsilon
                origins[i, 0] = points[q, 0] + side * 0.0
                origins[i, 1] = points[q, 1] + side * 1.0
                origins[i, 2] = points[q, 2] + side * 0.0
                ray_dirs[i, 0], ray_dirs[i, 1], ray_dirs[i, 2] = dirs[k, 0], dirs[k, 1], dirs[k, 2]
                i += 1


def ground_direct_rays(points, env_sh, blockers: MeshBlockers, rule: GroundRayRule | None = None, *,
                       method: str = "embree", spacing: float = 0.0) -> np.ndarray:
    """Direct irradiance ``(P, 3)`` from the environment at ground points (normal ``+Y``), the objects' meshes
    and the opaque spheres blocking (see the module docstring): :func:`ground_direct_sums` of
    :func:`ground_direct_hits`.

    Parameters
    ----------
    points : (P, 3) float
        Points on a ground (world space; rays leave them along ``+Y``'s hemisphere, offset by the caster's
        epsilon along ``+Y``).
    env_sh : (N*N, 3) float
        Environment radiance.
    blockers : MeshBlockers
    rule : GroundRayRule, optional
        Default :func:`ground_ray_rule` ``(64, 16)``.
    method : {"embree", "numpy"}
        The ray caster's engine (``"numpy"``: its float64 brute-force specification).
    spacing : float
        0 (default): cast at every point; else cast only where :func:`ground_ray_nodes` says and interpolate
        (``points`` of one ground).
    """
    return ground_direct_sums(ground_direct_hits(points, blockers, rule, method=method, spacing=spacing), env_sh,
                              blockers)


class GroundHits(NamedTuple):
    """What the rays of ground points met, the geometry only (:func:`ground_direct_hits`,
    :func:`ground_light_hits`): valid for the blockers and points it was cast with, whatever the lighting.

    ``rule``: the rays' :class:`GroundRayRule`; ``n_points``: the points; ``rows, weights``: the interpolation of
    :func:`ground_ray_nodes` (None: every point cast); ``chunks``: per chunk of :data:`_CHUNK` cast points a
    :class:`_ChunkHits`; ``cast``: what :func:`ground_hits_update` needs to keep some of them (:class:`_CastFrame`).
    """

    rule: GroundRayRule
    n_points: int
    rows: np.ndarray | None
    weights: np.ndarray | None
    chunks: tuple
    cast: "_CastFrame | None" = None


class _CastFrame(NamedTuple):
    """Where the rays of a :class:`GroundHits` were cast from (``points (C, 3)``, the rays' frame) and what they
    were cast against: the bounding spheres ``bounds``, the opaque ``spheres``, each mesh's ``mesh_balls`` and its
    number of faces ``n_faces`` (:class:`MeshBlockers`), the origins' offset ``epsilon``; ``closest``: closest hits
    (:func:`ground_light_hits`) or blocked rays (:func:`ground_direct_hits`); ``flat``: None, or the chunks' hit
    lists as one (``ptr (C + 1,)``, ``ray_k``, ``face``, ``u``, ``v``; the chunks are views of them)."""

    points: np.ndarray
    bounds: np.ndarray
    spheres: np.ndarray
    mesh_balls: np.ndarray
    n_faces: np.ndarray
    epsilon: float
    closest: bool
    flat: tuple | None = None


def _cast_frame(cast, blockers: MeshBlockers, closest: bool) -> _CastFrame | None:
    """The :class:`_CastFrame` of a cast (None: blockers without ``mesh_balls``, not made by :func:`mesh_blockers`;
    then nothing can be kept)."""
    if blockers.mesh_balls is None:
        return None
    return _CastFrame(np.ascontiguousarray(cast, dtype=np.float64), blockers.bounds.copy(), blockers.spheres.copy(),
                      np.asarray(blockers.mesh_balls, dtype=np.float64).copy(),
                      np.array([len(f) for f in blockers.faces], dtype=np.int64), _epsilon(blockers), closest)


def _epsilon(blockers: MeshBlockers) -> float:
    return float(blockers.caster.epsilon) if blockers.caster is not None else 0.0


class _ChunkHits(NamedTuple):
    """The hit rays of the cast points ``start:stop``: ``ptr (P + 1,)``, point ``q``'s hit rays ``ptr[q]:ptr[q +
    1]`` in ray order; their rule directions ``ray_k``; with closest hits (:func:`ground_light_hits`) the stacked
    face (``MeshBlockers.faces`` in order) of a front-face hit nearer than the opaque spheres, else -1, and its
    barycentrics ``u, v`` (None: blocked rays only); ``sphere_blocked (P, K)`` bool, the rays meeting an opaque
    sphere (None: no opaque sphere)."""

    start: int
    stop: int
    ptr: np.ndarray
    ray_k: np.ndarray
    face: np.ndarray | None
    u: np.ndarray | None
    v: np.ndarray | None
    sphere_blocked: np.ndarray | None


def ground_direct_hits(points, blockers: MeshBlockers, rule: GroundRayRule | None = None, *,
                       method: str = "embree", spacing: float = 0.0) -> GroundHits:
    """The rays of :func:`ground_direct_rays` that a mesh or an opaque sphere blocks (:class:`GroundHits`, any-hit
    casts; arguments as there): the geometry, evaluated for a lighting by :func:`ground_direct_sums`."""
    rule = rule or ground_ray_rule()
    p = _local_points(points, blockers)
    cast, rows, weights = _cast_points(p, blockers, spacing)
    rays = _chunk_rays(rule, blockers)
    starts = range(0, len(cast), _CHUNK)
    chunks = [None] * len(starts)

    def chunk(i, s):  # a task of run_tasks: the rays of one chunk
        sl, cand, ip, ik, t_sphere, origins, ray_dirs, _ = rays(cast, s)
        hit = np.zeros(len(ip), dtype=bool)
        if len(ip):
            hit = blockers.caster.occluded(origins, ray_dirs, method=method)  # origins offset by _chunk_rays
        ptr = np.zeros(len(cand) + 1, dtype=np.int64)
        np.cumsum(np.bincount(ip[hit], minlength=len(cand)), out=ptr[1:])
        chunks[i] = _ChunkHits(s, s + len(cand), ptr, ik[hit], None, None, None,
                               None if t_sphere is None else np.isfinite(t_sphere))

    run_tasks([functools.partial(chunk, i, s) for i, s in enumerate(starts)],
              sizes=_chunk_sizes(cast, blockers, len(rule.dirs)))
    interpolate = len(cast) < len(p)
    return GroundHits(rule, len(p), rows if interpolate else None, weights if interpolate else None, tuple(chunks),
                      _cast_frame(cast, blockers, False))


def ground_direct_sums(hits: GroundHits, env_sh, blockers: MeshBlockers) -> np.ndarray:
    """:func:`ground_direct_rays` from its geometry ``hits`` (:func:`ground_direct_hits` with these ``blockers``)
    under the environment ``env_sh (N*N, 3)``: the closed-form open sky less the blocked rays' radiance."""
    env = np.asarray(env_sh, dtype=np.float64)
    rule = hits.rule
    order = math.isqrt(env.shape[0])
    e_open = sh.basis(_UP[None], order) @ sh.irradiance(env)  # (1, 3): nothing blocked
    radiance = (sh.basis(rule.dirs @ blockers.turn.T, order) @ env) * rule.weights[:, None]  # (K, 3), world
    n_cast = hits.chunks[-1].stop if hits.chunks else 0
    out = np.empty((n_cast, 3))
    for c in hits.chunks:
        ip = np.repeat(np.arange(c.stop - c.start), np.diff(c.ptr))
        out[c.start:c.stop] = e_open - _blocked_sum(c.stop - c.start, ip, c.ray_k, c.sphere_blocked, radiance)
    return _interpolated(out, hits.rows, hits.weights) if hits.rows is not None else out


def _blocked_sum(n_points, ip, ik, sphere_blocked, radiance) -> np.ndarray:
    """``(P, 3)`` sum of ``radiance[k]`` over the blocked rays: ``(ip, ik)`` (by a mesh) and those meeting an opaque
    sphere (``sphere_blocked (P, K)`` bool, None: none)."""
    if sphere_blocked is not None:
        blocked = sphere_blocked.copy()
        blocked[ip, ik] = True
        return blocked.astype(np.float64) @ radiance
    return np.stack([np.bincount(ip, weights=radiance[ik, c], minlength=n_points) for c in range(3)], axis=1)


def ground_gather_rays(points, blockers: MeshBlockers, radiance, rule: GroundRayRule | None = None, *,
                       method: str = "embree", tier: str = "numba") -> np.ndarray:
    """Irradiance ``(P, 3)`` at ground points (normal ``+Y``) from the objects' surfaces: over the rays, the exit
    radiance at the first mesh hit (interpolated from ``radiance[g] (V_g, 3)``, the vertices of object ``g``; a
    back face gives 0), a hit beyond an opaque sphere giving nothing (see the module docstring).

    Parameters
    ----------
    points : (P, 3) float
        Points on a ground (world space).
    blockers : MeshBlockers
    radiance : sequence of (V_g, 3) float
        Exit radiance at each object's vertices, in the caster's object order.
    rule : GroundRayRule, optional
        Default :func:`ground_ray_rule` ``(64, 16)``.
    method : {"embree", "numpy"}
        As in :func:`ground_direct_rays`.
    tier : {"numba", "reference"}
        The sums over the hits: a numba kernel, or numpy (the specification; the same sums in the same order).
    """
    from prtlab._validate import check_choice

    check_choice(tier, "tier", ("numba", "reference"))
    rule = rule or ground_ray_rule()
    p = _local_points(points, blockers)
    if len(radiance) != len(blockers.faces):
        raise ValueError(f"radiance must give one (V, 3) array per mesh ({len(blockers.faces)}), got {len(radiance)}")
    if tier == "numba":
        return ground_light_sums(ground_light_hits(points, blockers, rule, method=method), None, blockers,
                                 radiance)[1]
    return _gather_reference(p, blockers, radiance, rule, method, None)[1]


def ground_light_rays(points, env_sh, blockers: MeshBlockers, radiance, rule: GroundRayRule | None = None, *,
                      method: str = "embree", tier: str = "numba",
                      spacing: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """``(direct, gathered)``, each ``(P, 3)``: :func:`ground_direct_rays` and :func:`ground_gather_rays` at the
    same points from one closest-hit cast per ray (the same values as the two apart). ``tier``: the sums over the
    hits in a numba kernel (``"numba"``: :func:`ground_light_sums` of :func:`ground_light_hits`) or numpy
    (``"reference"``, the specification; the same sums in the same order). ``spacing``: 0 (default) casts at every
    point; else only where :func:`ground_ray_nodes` says, the rest interpolated (``points`` of one ground)."""
    from prtlab._validate import check_choice

    check_choice(tier, "tier", ("numba", "reference"))
    rule = rule or ground_ray_rule()
    if len(radiance) != len(blockers.faces):
        raise ValueError(f"radiance must give one (V, 3) array per mesh ({len(blockers.faces)}), got {len(radiance)}")
    if tier == "numba":
        return ground_light_sums(ground_light_hits(points, blockers, rule, method=method, spacing=spacing), env_sh,
                                 blockers, radiance)
    p = _local_points(points, blockers)
    cast, rows, weights = _cast_points(p, blockers, spacing)
    direct, gathered = _gather_reference(cast, blockers, radiance, rule, method, np.asarray(env_sh, dtype=np.float64))
    if len(cast) < len(p):
        return _interpolated_reference(direct, rows, weights), _interpolated_reference(gathered, rows, weights)
    return direct, gathered


def ground_light_hits(points, blockers: MeshBlockers, rule: GroundRayRule | None = None, *, method: str = "embree",
                      spacing: float = 0.0) -> GroundHits:
    """The closest hits of the rays of :func:`ground_light_rays` (:class:`GroundHits`; arguments as there): the
    geometry, evaluated for a lighting by :func:`ground_light_sums`."""
    rule = rule or ground_ray_rule()
    p = _local_points(points, blockers)
    cast, rows, weights = _cast_points(p, blockers, spacing)
    dirs = np.ascontiguousarray(rule.dirs, dtype=np.float64)
    face_start = np.zeros(len(blockers.faces) + 1, dtype=np.int64)
    face_start[1:] = np.cumsum([len(f) for f in blockers.faces])
    k_type = np.int16 if len(dirs) <= np.iinfo(np.int16).max else np.int64
    f_type = np.int32 if face_start[-1] <= np.iinfo(np.int32).max else np.int64
    rays = _chunk_rays(rule, blockers)
    starts = range(0, len(cast), _CHUNK)
    chunks = [None] * len(starts)

    def chunk(i, s):  # a task of run_tasks: the rays of one chunk
        sl, cand, ip, ik, t_sphere, origins, ray_dirs, ptr = rays(cast, s)
        hit = np.zeros(len(ip), dtype=bool)
        if len(ip):
            hits = blockers.caster.closest_hit(origins, ray_dirs, method=method)  # origins offset by _chunk_rays
            hit = hits.hit
        hit_ptr = np.zeros(len(cand) + 1, dtype=np.int64)
        np.cumsum(np.bincount(ip[hit], minlength=len(cand)), out=hit_ptr[1:])
        n = int(hit_ptr[-1])
        ray_k, face = np.empty(n, dtype=k_type), np.empty(n, dtype=f_type)
        u, v = np.empty(n), np.empty(n)
        if n:
            _compact_hits(ptr, ik, hit, hits.object, hits.triangle, hits.barycentric, hits.normal, hits.distance,
                          dirs, t_sphere if t_sphere is not None else np.zeros((0, 0)), face_start, hit_ptr, ray_k,
                          face, u, v)
        chunks[i] = _ChunkHits(s, s + len(cand), hit_ptr, ray_k, face, u, v,
                               None if t_sphere is None else np.isfinite(t_sphere))

    run_tasks([functools.partial(chunk, i, s) for i, s in enumerate(starts)],
              sizes=_chunk_sizes(cast, blockers, len(rule.dirs)))
    interpolate = len(cast) < len(p)
    return GroundHits(rule, len(p), rows if interpolate else None, weights if interpolate else None, tuple(chunks),
                      _cast_frame(cast, blockers, True))


def ground_light_sums(hits: GroundHits, env_sh, blockers: MeshBlockers, radiance):
    """:func:`ground_light_rays` from its geometry ``hits`` (:func:`ground_light_hits` with these ``blockers``):
    ``(direct, gathered)``, each ``(P, 3)``, under the environment ``env_sh (N*N, 3)`` (None: ``direct`` is None)
    and the objects' exit radiance ``radiance`` (one ``(V_g, 3)`` per mesh). Per point the sums run over its hit
    rays in ray order (the numba kernel; the reference tier of :func:`ground_light_rays` is its specification)."""
    rule = hits.rule
    rad = [np.asarray(r, dtype=np.float64).reshape(-1, 3) for r in radiance]
    if len(rad) != len(blockers.faces):
        raise ValueError(f"radiance must give one (V, 3) array per mesh ({len(blockers.faces)}), got {len(rad)}")
    n_cast = hits.chunks[-1].stop if hits.chunks else 0
    gathered = np.zeros((n_cast, 3))
    direct = None
    no_env = np.zeros((0, 3))
    if env_sh is not None:
        env = np.asarray(env_sh, dtype=np.float64)
        order = math.isqrt(env.shape[0])
        e_open = sh.basis(_UP[None], order) @ sh.irradiance(env)
        blocked_radiance = (sh.basis(rule.dirs @ blockers.turn.T, order) @ env) * rule.weights[:, None]
        direct = np.empty((n_cast, 3))
    faces, _, _ = _stacked_faces(blockers.faces, [len(r) for r in rad])
    rad_all = np.ascontiguousarray(np.concatenate(rad)) if rad else np.zeros((0, 3))
    weights = np.ascontiguousarray(rule.weights, dtype=np.float64)

    def chunk(c):  # a task of run_tasks: the rows of one chunk
        blocked = np.zeros((c.stop - c.start, 3))
        with_env = env_sh is not None and c.sphere_blocked is None
        _hit_list_sums(c.ptr, c.ray_k, c.face, c.u, c.v, weights, blocked_radiance if with_env else no_env, faces,
                       rad_all, blocked, gathered[c.start:c.stop])
        if env_sh is not None:
            if with_env:
                direct[c.start:c.stop] = e_open - blocked
            else:
                ip = np.repeat(np.arange(c.stop - c.start), np.diff(c.ptr))
                direct[c.start:c.stop] = e_open - _blocked_sum(c.stop - c.start, ip, c.ray_k, c.sphere_blocked,
                                                               blocked_radiance)

    run_tasks([functools.partial(chunk, c) for c in hits.chunks], sizes=[int(c.ptr[-1]) + 1 for c in hits.chunks])
    if hits.rows is not None:
        return (None if direct is None else _interpolated(direct, hits.rows, hits.weights),
                _interpolated(gathered, hits.rows, hits.weights))
    return direct, gathered


#: The widening of the spheres near which :func:`ground_hits_update` casts again, relative to ``r + |c|`` (beside
#: twice the origins' offset): the caster's float32 vertices may lie a rounding outside a float64 ball.
_UPDATE_MARGIN = 1e-5


def ground_hits_update(kept: GroundHits, points, blockers: MeshBlockers, moved, rule: GroundRayRule | None = None,
                       *, method: str = "embree", spacing: float = 0.0):
    """:func:`ground_light_hits` or :func:`ground_direct_hits` (as ``kept`` was made) of ``points`` against
    ``blockers``, the rays that cannot have changed taken from ``kept``: ``(hits, counts)``, ``hits`` equal to a
    fresh cast's, or None when ``kept`` cannot serve (no meshes; another rule, number of meshes or of their faces,
    opaque spheres or rays' offset; blockers not made by :func:`mesh_blockers`: cast afresh).

    ``moved (G,) bool``: the meshes whose vertices differ from ``kept``'s; the others, the points, the rays' frame
    and ``spacing`` must be those of ``kept`` (the caller compares them). A ray from a point cast in both frames
    (the same position, bit for bit) is kept when its direction lies outside the cones of the changed spheres: the
    bounding spheres in one frame and not the other and the balls around the moved meshes in both, each widened by
    :data:`_UPDATE_MARGIN` and twice the rays' offset. Outside them the ray's candidacy (the cone tests of the
    unchanged bounding spheres) and what it meets (no moved face; the unchanged faces keep their stacked numbers,
    the faces' counts being the same) are the same. The other candidate rays of those points and every ray of the
    new points are cast; each point's hit rays are merged in ray order, so the sums see the same inputs in the same
    order. ``counts``: ``{"points", "points_cast", "rays_cast", "hits_kept"}``."""
    rule = rule or ground_ray_rule()
    frame = kept.cast
    dirs = np.ascontiguousarray(rule.dirs, dtype=np.float64)
    n_faces = np.array([len(f) for f in blockers.faces], dtype=np.int64)
    moved = np.asarray(moved, dtype=bool).reshape(-1)
    if len(moved) != len(blockers.faces):
        raise ValueError(f"moved must give one flag per mesh ({len(blockers.faces)}), got {len(moved)}")
    if (frame is None or blockers.caster is None or blockers.mesh_balls is None
            or not _same_array(kept.rule.dirs, rule.dirs)
            or not _same_array(kept.rule.weights, rule.weights) or not _same_array(frame.n_faces, n_faces)
            or not _same_array(frame.spheres, blockers.spheres) or frame.epsilon != _epsilon(blockers)):
        return None
    closest = frame.closest
    p = _local_points(points, blockers)
    cast, rows, weights = _cast_points(p, blockers, spacing)
    cast = np.ascontiguousarray(cast)
    match = _match_rows(cast, frame.points)
    bounds = np.ascontiguousarray(blockers.bounds, dtype=np.float64).reshape(-1, 4)
    changed = np.concatenate([frame.bounds[_match_rows(frame.bounds, bounds) < 0],
                              bounds[_match_rows(bounds, frame.bounds) < 0], frame.mesh_balls[moved],
                              np.asarray(blockers.mesh_balls, dtype=np.float64)[moved]])
    changed[:, 3] += _UPDATE_MARGIN * (changed[:, 3] + np.linalg.norm(changed[:, :3], axis=1)) + 2.0 * frame.epsilon
    n_azimuth = _rings(dirs)
    changed = np.ascontiguousarray(changed)
    in_zone, n_cand = np.zeros(len(cast), dtype=np.int64), np.zeros(len(cast), dtype=np.int64)  # rays per point
    zone, cand = np.empty((len(cast), len(dirs)), dtype=np.bool_), np.empty((len(cast), len(dirs)), dtype=np.bool_)
    if n_azimuth and len(changed):  # the zone and its candidates in one pass
        _zone_candidates_kernel(cast, dirs, n_azimuth, changed, bounds, zone, cand, in_zone, n_cand)
    else:
        zone = _candidates(cast, dirs, changed, n_azimuth, in_zone) if len(changed) else np.zeros_like(zone)
        _candidates_within(cast, dirs, bounds, zone, cand, n_cand)
    new = np.nonzero(match < 0)[0]
    if len(new):  # a new point: every ray
        zone[new] = True
        in_zone[new] = len(dirs)
        part, part_n = np.empty((len(new), len(dirs)), dtype=np.bool_), np.empty(len(new), dtype=np.int64)
        _candidates_within(np.ascontiguousarray(cast[new]), dirs, bounds, np.ascontiguousarray(zone[new]), part,
                           part_n)
        cand[new], n_cand[new] = part, part_n
    todo = np.nonzero(in_zone)[0]
    whole = len(todo) == len(cast)  # every point has rays in the zone: no copies
    sub = cast if whole else np.ascontiguousarray(cast[todo])
    if not whole:
        cand, n_cand = np.ascontiguousarray(cand[todo]), n_cand[todo]
    ptr = np.zeros(len(todo) + 1, dtype=np.int64)
    np.cumsum(n_cand, out=ptr[1:])
    ip, ik = np.empty(ptr[-1], dtype=np.int64), np.empty(ptr[-1], dtype=np.int64)
    origins, ray_dirs = np.empty((ptr[-1], 3)), np.empty((ptr[-1], 3))
    _list_rays(sub, cand, dirs, ptr, frame.epsilon, ip, ik, origins, ray_dirs)
    hit = np.zeros(len(ip), dtype=bool)
    if closest:
        if len(ip):
            hits = blockers.caster.closest_hit(origins, ray_dirs, method=method)
            hit = hits.hit
        sub_ptr = np.zeros(len(todo) + 1, dtype=np.int64)
        np.cumsum(np.bincount(ip[hit], minlength=len(todo)), out=sub_ptr[1:])
        n = int(sub_ptr[-1])
        face_start = np.zeros(len(n_faces) + 1, dtype=np.int64)
        face_start[1:] = np.cumsum(n_faces)
        k_type = np.int16 if len(dirs) <= np.iinfo(np.int16).max else np.int64  # as ground_light_hits
        f_type = np.int32 if face_start[-1] <= np.iinfo(np.int32).max else np.int64
        new_k, new_face, new_u, new_v = np.empty(n, dtype=k_type), np.empty(n, dtype=f_type), np.empty(n), np.empty(n)
        if n:
            t_sphere = sphere_hits(sub, rule.dirs, blockers.spheres) if len(blockers.spheres) else np.zeros((0, 0))
            _compact_hits(ptr, ik, hit, hits.object, hits.triangle, hits.barycentric, hits.normal, hits.distance, dirs,
                          t_sphere, face_start, sub_ptr, new_k, new_face, new_u, new_v)
    else:
        if len(ip):
            hit = blockers.caster.occluded(origins, ray_dirs, method=method)
        sub_ptr = np.zeros(len(todo) + 1, dtype=np.int64)
        np.cumsum(np.bincount(ip[hit], minlength=len(todo)), out=sub_ptr[1:])
        new_k = ik[hit]
        new_face = new_u = new_v = None
    new_ptr = np.zeros(len(cast) + 1, dtype=np.int64)  # the cast hits' lists per point of ``cast``
    new_count = np.zeros(len(cast), dtype=np.int64)
    new_count[todo] = np.diff(sub_ptr)
    np.cumsum(new_count, out=new_ptr[1:])
    if frame.flat is not None:  # the hit lists of every cast point, as the last update left them
        old_ptr, old_k, old_face, old_u, old_v = frame.flat
    else:
        old_ptr = np.zeros(len(frame.points) + 1, dtype=np.int64)
        np.cumsum(np.concatenate([np.diff(c.ptr) for c in kept.chunks] or [np.zeros(0, dtype=np.int64)]),
                  out=old_ptr[1:])

        def flat(name, dtype):
            parts = [getattr(c, name) for c in kept.chunks]
            return np.concatenate(parts) if parts else np.zeros(0, dtype=dtype)

        old_k = flat("ray_k", new_k.dtype)
        old_face, old_u, old_v = ((flat("face", new_face.dtype), flat("u", np.float64), flat("v", np.float64))
                                  if closest else (None, None, None))
    count = np.empty(len(cast), dtype=np.int64)
    _merge_counts(match, old_ptr, old_k, zone, new_ptr, count)
    out_ptr = np.zeros(len(cast) + 1, dtype=np.int64)
    np.cumsum(count, out=out_ptr[1:])
    total = int(out_ptr[-1])
    out_k = np.empty(total, dtype=new_k.dtype)
    if closest:
        out_face, out_u, out_v = np.empty(total, dtype=new_face.dtype), np.empty(total), np.empty(total)
        _merge_hits(match, old_ptr, old_k, old_face, old_u, old_v, zone, new_ptr, new_k, new_face, new_u, new_v,
                    out_ptr, out_k, out_face, out_u, out_v)
    else:
        empty_i, empty_f = np.zeros(0, dtype=np.int64), np.zeros(0)
        _merge_hits(match, old_ptr, old_k, empty_i, empty_f, empty_f, zone, new_ptr, new_k, empty_i, empty_f, empty_f,
                    out_ptr, out_k, empty_i, empty_f, empty_f)
    chunks = []
    for s in range(0, len(cast), _CHUNK):
        e = min(s + _CHUNK, len(cast))
        a, b = out_ptr[s], out_ptr[e]
        sphere_blocked = (np.isfinite(sphere_hits(cast[s:e], rule.dirs, blockers.spheres)) if len(blockers.spheres)
                          else None)
        chunks.append(_ChunkHits(s, e, out_ptr[s:e + 1] - a, out_k[a:b], out_face[a:b] if closest else None,
                                 out_u[a:b] if closest else None, out_v[a:b] if closest else None, sphere_blocked))
    interpolate = len(cast) < len(p)
    frame = _cast_frame(cast, blockers, closest)._replace(
        flat=(out_ptr, out_k, out_face, out_u, out_v) if closest else (out_ptr, out_k, None, None, None))
    result = GroundHits(rule, len(p), rows if interpolate else None, weights if interpolate else None, tuple(chunks),
                        frame)
    return result, {"points": len(cast), "points_cast": len(todo), "rays_cast": len(ip),
                    "hits_kept": total - int(new_ptr[-1])}


def _same_array(a, b) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def _match_rows(rows, among) -> np.ndarray:
    """Per row of ``rows (N, D)`` float64 the index of a row of ``among (M, D)`` with the same bytes, else -1."""
    rows = np.ascontiguousarray(rows, dtype=np.float64)
    among = np.ascontiguousarray(among, dtype=np.float64)
    if rows.shape == among.shape and np.array_equal(rows.view(np.uint64), among.view(np.uint64)):
        return np.arange(len(rows), dtype=np.int64)  # the same rows in the same order (a ground that stays)
    out = np.full(len(rows), -1, dtype=np.int64)
    if not len(rows) or not len(among):
        return out
    key = np.dtype((np.void, 8 * rows.shape[1]))
    a, b = among.view(key).ravel(), rows.view(key).ravel()
    order = np.argsort(a, kind="stable")
    ranked = a[order]
    pos = np.minimum(np.searchsorted(ranked, b), len(ranked) - 1)
    found = ranked[pos] == b
    out[found] = order[pos[found]]
    return out


@numba.njit(cache=True, parallel=True, nogil=True)
def _candidates_within(points, dirs, spheres, zone, out, counts):
    """``out[q, k]``: ``zone[q, k]`` and the ray a candidate (``_candidates_kernel``'s test, so the rings kernel's
    result too), testing only the rays of ``zone``; ``counts[q]``: row ``q``'s candidates."""
    n_s = spheres.shape[0]
    for q in numba.prange(points.shape[0]):
        axis = np.empty((n_s, 3))
        cos_half = np.empty(n_s)
        inside = _cones(points[q], spheres, axis, cos_half)
        c = 0
        for k in range(dirs.shape[0]):
            out[q, k] = zone[q, k] and (inside or _in_a_cone(dirs, k, axis, cos_half))
            c += out[q, k]
        counts[q] = c


@numba.njit(cache=True, parallel=True, nogil=True)
def _merge_counts(match, old_ptr, old_k, zone, new_ptr, count):
    """Per point ``q``: its cast hits (``new_ptr``) and the hits of its kept point ``match[q]`` (-1: none) whose
    direction lies outside ``zone[q]``."""
    for q in numba.prange(match.shape[0]):
        c = new_ptr[q + 1] - new_ptr[q]
        m = match[q]
        if m >= 0:
            for i in range(old_ptr[m], old_ptr[m + 1]):
                if not zone[q, np.int64(old_k[i])]:
                    c += 1
        count[q] = c


@numba.njit(cache=True, parallel=True, nogil=True)
def _merge_hits(match, old_ptr, old_k, old_face, old_u, old_v, zone, new_ptr, new_k, new_face, new_u, new_v,
                out_ptr, out_k, out_face, out_u, out_v):
    """Per point ``q`` into ``out_ptr[q]:out_ptr[q + 1]``, in ray order: the kept hits of ``_merge_counts`` and the
    cast ones (with faces and barycentrics unless ``out_face`` is empty)."""
    with_face = out_face.shape[0] > 0
    for q in numba.prange(match.shape[0]):
        j = out_ptr[q]
        m = match[q]
        a, a_end = (old_ptr[m], old_ptr[m + 1]) if m >= 0 else (0, 0)
        b, b_end = new_ptr[q], new_ptr[q + 1]
        while True:
            while a < a_end and zone[q, np.int64(old_k[a])]:
                a += 1
            if a >= a_end and b >= b_end:
                break
            if b >= b_end or (a < a_end and old_k[a] < new_k[b]):
                out_k[j] = old_k[a]
                if with_face:
                    out_face[j], out_u[j], out_v[j] = old_face[a], old_u[a], old_v[a]
                a += 1
            else:
                out_k[j] = new_k[b]
                if with_face:
                    out_face[j], out_u[j], out_v[j] = new_face[b], new_u[b], new_v[b]
                b += 1
            j += 1


def _cast_points(p, blockers: MeshBlockers, spacing: float):
    """:func:`ground_ray_nodes` of local points ``p`` against the blockers' bounding and opaque spheres."""
    return ground_ray_nodes(p, np.concatenate([blockers.bounds.reshape(-1, 4), blockers.spheres.reshape(-1, 4)]),
                            spacing)


def _gather_reference(p, blockers, radiance, rule, method, env):
    """The gathered light at local points ``p`` and, given ``env``, the direct light (else None): the numpy
    specification of :func:`ground_light_sums`, chunk after chunk."""
    rad = [np.asarray(r, dtype=np.float64).reshape(-1, 3) for r in radiance]
    out = np.zeros((len(p), 3))
    direct = None
    if env is not None:
        order = math.isqrt(env.shape[0])
        e_open = sh.basis(_UP[None], order) @ sh.irradiance(env)
        blocked_radiance = (sh.basis(rule.dirs @ blockers.turn.T, order) @ env) * rule.weights[:, None]
        direct = np.empty((len(p), 3))
    rays = _chunk_rays(rule, blockers)
    for s in range(0, len(p), _CHUNK):
        sl, cand, ip, ik, t_sphere, origins, ray_dirs, ptr = rays(p, s)
        sphere_blocked = None if t_sphere is None else np.isfinite(t_sphere)
        if not len(ip):
            if env is not None:
                direct[sl] = e_open - _blocked_sum(len(cand), ip, ik, sphere_blocked, blocked_radiance)
            continue
        hits = blockers.caster.closest_hit(origins, ray_dirs, method=method)  # origins offset by _chunk_rays
        if env is not None:
            direct[sl] = e_open - _blocked_sum(len(cand), ip[hits.hit], ik[hits.hit], sphere_blocked,
                                               blocked_radiance)
        d = rule.dirs[ik]
        live = hits.hit & (np.einsum("ij,ij->i", hits.normal, d) < 0.0)
        if t_sphere is not None:
            live &= hits.distance < t_sphere[ip, ik]
        value = np.zeros((len(ip), 3))
        for g, mesh_faces in enumerate(blockers.faces):
            m = live & (hits.object == g)
            if not m.any():
                continue
            f = mesh_faces[hits.triangle[m]]
            u, v = hits.barycentric[m, :1], hits.barycentric[m, 1:]
            value[m] = (1.0 - u - v) * rad[g][f[:, 0]] + u * rad[g][f[:, 1]] + v * rad[g][f[:, 2]]
        np.add.at(out[sl], ip, value * rule.weights[ik, None])
    return direct, out


def _stacked_faces(faces, n_verts):
    """The objects' faces in one ``(F, 3)`` array (vertex indices into the stacked radiance) and each object's first
    face and first vertex."""
    face_start = np.zeros(len(faces) + 1, dtype=np.int64)
    face_start[1:] = np.cumsum([len(f) for f in faces])
    vert_start = np.zeros(len(faces) + 1, dtype=np.int64)
    vert_start[1:] = np.cumsum(n_verts)
    stacked = np.concatenate([np.asarray(f, dtype=np.int64).reshape(-1, 3) + vert_start[g]
                              for g, f in enumerate(faces)] or [np.zeros((0, 3), dtype=np.int64)])
    return np.ascontiguousarray(stacked), face_start, vert_start


@numba.njit(cache=True, parallel=True, nogil=True)
def _compact_hits(ptr, ik, hit, obj, tri, bary, normal, dist, dirs, t_sphere, face_start, hit_ptr, ray_k, face, u,
                  v):
    """Per point ``q`` (its rays ``ptr[q]:ptr[q + 1]``, rule directions ``ik``) its hit rays, in ray order, into
    ``hit_ptr[q]:hit_ptr[q + 1]``: the rule direction, the stacked face (``face_start[object] + triangle``) of a
    front-face hit closer than the opaque spheres (``t_sphere (P, K)``, empty: none), else -1, and the
    barycentrics."""
    with_spheres = t_sphere.shape[0] > 0
    for q in numba.prange(ptr.shape[0] - 1):
        j = hit_ptr[q]
        for i in range(ptr[q], ptr[q + 1]):
            if not hit[i]:
                continue
            k = ik[i]
            ray_k[j] = k
            live = not (normal[i, 0] * dirs[k, 0] + normal[i, 1] * dirs[k, 1] + normal[i, 2] * dirs[k, 2] >= 0.0)
            if live and with_spheres and not dist[i] < t_sphere[q, k]:
                live = False  # a back face (from inside a closed object) or a hit beyond an opaque sphere
            face[j] = face_start[obj[i]] + tri[i] if live else -1
            u[j], v[j] = bary[i, 0], bary[i, 1]
            j += 1


@numba.njit(cache=True, parallel=True, nogil=True)
def _hit_list_sums(ptr, ray_k, face, u_hit, v_hit, weights, blocked_radiance, faces, radiance, blocked, gathered):
    """Per point ``q`` (its hit rays ``ptr[q]:ptr[q + 1]``, :class:`_ChunkHits`), in ray order: ``blocked[q] +=
    blocked_radiance[k]`` (skipped if ``blocked_radiance`` is empty) and, for a face ``f >= 0``, ``gathered[q] +=
    w_k L_o``, ``L_o`` interpolated from ``radiance`` at the face's vertices."""
    with_env = blocked_radiance.shape[0] > 0
    for q in numba.prange(ptr.shape[0] - 1):
        # the point's six sums in registers (in memory, each add waited for the store before it)
        b0, b1, b2 = blocked[q, 0], blocked[q, 1], blocked[q, 2]
        g0, g1, g2 = gathered[q, 0], gathered[q, 1], gathered[q, 2]
        for i in range(ptr[q], ptr[q + 1]):
            k = np.int64(ray_k[i])
            if with_env:
                b0 += blocked_radiance[k, 0]
                b1 += blocked_radiance[k, 1]
                b2 += blocked_radiance[k, 2]
            f = np.int64(face[i])
            if f < 0:
                continue
            a, b, d = faces[f, 0], faces[f, 1], faces[f, 2]
            u, v = u_hit[i], v_hit[i]
            t, w = 1.0 - u - v, weights[k]
            g0 += (t * radiance[a, 0] + u * radiance[b, 0] + v * radiance[d, 0]) * w
            g1 += (t * radiance[a, 1] + u * radiance[b, 1] + v * radiance[d, 1]) * w
            g2 += (t * radiance[a, 2] + u * radiance[b, 2] + v * radiance[d, 2]) * w
        blocked[q, 0], blocked[q, 1], blocked[q, 2] = b0, b1, b2
        gathered[q, 0], gathered[q, 1], gathered[q, 2] = g0, g1, g2


def contact_radiance(points, normals, radiance, heights, tol: float) -> np.ndarray:
    """``radiance (V, 3)`` of an object's vertices as the ground sees them from above: at a vertex lying on a
    ground (``|y - h| <= tol`` for a height ``h`` of ``heights``) scaled by ``(1 + n_y) / 2``, the part of its
    cosine-weighted hemisphere above the ground (0 facing straight down, 1 facing up); elsewhere unchanged.

    A vertex at a ground's height is shaded as lying below it (the light from under the ground reaches it), while
    the faces around it, seen from the ground, lie above it: their radiance falls to what the horizon leaves. For
    the gather (:func:`ground_gather_rays`) only."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    out = np.array(radiance, dtype=np.float64).reshape(-1, 3)
    h = np.asarray(heights, dtype=np.float64).reshape(-1)
    if not len(h) or not len(p):
        return out
    on = np.any(np.abs(p[:, 1:2] - h[None]) <= tol, axis=1)
    ny = n[on, 1] / np.maximum(np.linalg.norm(n[on], axis=1), 1e-300)
    out[on] *= (0.5 * (1.0 + ny))[:, None]
    return out

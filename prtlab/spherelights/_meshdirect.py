"""The objects' direct light against the real meshes (an extension of Guerrero et al. 2008; option
``mesh_blockers``).

The paper's direct light at a receiver is ``V_n . T_n`` (Sec. 5.1): the order-n SH visibility of every blocker's
fitted spheres, exponentiated from their log sum. Around a multi-sphere object (the bunny of 16 lights) its
spheres' outside volume and the order-n truncation shadow where the object is not, both for the object's own
vertices (self-shadowing) and for its neighbours. Here, over a fixed set of ``M`` directions ``d_j`` of the unit
sphere in the receiving object's frame (a spherical Fibonacci set, weight ``4 pi / M`` each), with ``w_j = R d_j``
(``R`` the object's rotation),

.. math:: E(p) = \\int L(\\omega) \\max(0, n \\cdot \\omega)\\, d\\omega
          - \\frac{4\\pi}{M} \\sum_j \\max(0, n \\cdot w_j)\\, L(w_j)\\, B_p(w_j),

the first integral in closed form from the environment's SH (exact for the band-limited environment), ``B_p(w)``
whether the ray from ``p`` along ``w`` meets the receiver's own mesh, another object's mesh, a ground rectangle
or an opaque sphere (a local light). The receiver's own mesh is tested once per vertex in object space
(:func:`self_blocked`: a rigid motion turns the rays with the object, so the bits hold for every pose); another
object's mesh in that object's space (its caster built once), only along rays meeting one of its bounding
spheres (its lights: the spheres bound the mesh, ``_fit``), and not along the rays meeting one of its inner spheres
(balls inside the closed mesh: such a ray meets the mesh first).

Measured figures: ``docs/notes/spherelights.md``.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numba
import numpy as np

from prtlab import sh
from prtlab._tasks import run_tasks, task_threads

__all__ = ["fibonacci_directions", "self_blocked", "MeshOccluder", "mesh_occluder", "inner_spheres",
           "mesh_direct", "mesh_direct_visible", "mesh_direct_visible_update", "mesh_direct_sums"]

_CHUNK = 1024  # receivers per batch (bounds the (P, M) masks)


@functools.lru_cache(maxsize=None)
def fibonacci_directions(n: int) -> np.ndarray:
    """``(n, 3)`` unit directions of a spherical Fibonacci set (equal areas ``4 pi / n``; read-only)."""
    from prtlab._validate import check_int

    check_int(n, "n", 1)
    i = np.arange(n, dtype=np.float64)
    z = 1.0 - (2.0 * i + 1.0) / n
    phi = i * (math.pi * (3.0 - math.sqrt(5.0)))  # the golden angle
    s = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    out = np.stack([s * np.cos(phi), z, s * np.sin(phi)], -1)
    out.setflags(write=False)
    return out


def self_blocked(points, normals, vertices, faces, dirs, *, method: str = "embree") -> np.ndarray:
    """``(P, ceil(M / 8))`` uint8, bits packed along the directions (``np.packbits`` order): whether the ray from
    each receiver along each of ``dirs (M, 3)`` with ``n . d > 0`` meets the mesh ``(vertices, faces)`` (all in one
    frame: the object's). Rays leave the points offset by the caster's epsilon along their normals; directions
    below a receiver's tangent plane get 0.

    ``method``: the ray caster's engine (``"embree"``, or ``"numpy"``: its float64 brute-force specification).
    """
    from prtlab.geometry import RayCaster

    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    if p.shape != n.shape:
        raise ValueError(f"points and normals must have the same shape (P, 3), got {p.shape} and {n.shape}")
    bits = np.zeros((len(p), len(d)), dtype=bool)
    if len(p) and len(d) and len(faces):
        caster = RayCaster([(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64))])
        for s in range(0, len(p), _CHUNK):
            front = (n[s:s + _CHUNK] @ d.T) > 0.0
            ip, ij = np.nonzero(front)
            if len(ip):
                bits[s + ip, ij] = caster.occluded(p[s + ip], d[ij], normals=n[s + ip], method=method)
    return np.packbits(bits, axis=1)


class MeshOccluder(NamedTuple):
    """One blocking object: its mesh's caster in object space (``caster``), the object's pose (``rotation (3, 3)``,
    ``scale``, ``translate (3,)``: ``x_world = translate + scale R x``), its bounding spheres in world space
    (``bounds (B, 4)``, rows ``[x, y, z, r]``; every ray meeting the mesh meets one of them) and spheres inside
    the closed mesh (``inner (K, 4)``, world space; a ray from outside meeting one meets the mesh)."""

    caster: object
    rotation: np.ndarray
    scale: float
    translate: np.ndarray
    bounds: np.ndarray
    inner: np.ndarray = np.zeros((0, 4))


def mesh_occluder(vertices, faces, rotation=None, scale: float = 1.0, translate=(0.0, 0.0, 0.0),
                  bounds=None, inner=None) -> MeshOccluder:
    """:class:`MeshOccluder` of an object-space mesh at a pose; ``bounds`` default: one ball around the placed
    vertices; ``inner (K, 4)``: object-space spheres inside the closed mesh (:func:`inner_spheres`), default
    none."""
    from prtlab.geometry import RayCaster

    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    rot = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64).reshape(3, 3)
    t = np.asarray(translate, dtype=np.float64).reshape(3)
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be a finite number > 0, got {scale!r}")
    if bounds is None:
        w = v @ (scale * rot).T + t
        centre = 0.5 * (w.min(axis=0) + w.max(axis=0)) if len(w) else np.zeros(3)
        radius = 1.000001 * np.linalg.norm(w - centre, axis=1).max() if len(w) else 0.0
        bounds = np.append(centre, radius)[None]
    b = np.ascontiguousarray(bounds, dtype=np.float64).reshape(-1, 4)
    caster = RayCaster([(v, np.asarray(faces, dtype=np.int64))])
    inner = np.zeros((0, 4)) if inner is None else np.asarray(inner, dtype=np.float64).reshape(-1, 4)
    inner = np.concatenate([inner[:, :3] @ (scale * rot).T + t, scale * inner[:, 3:]], axis=1)
    return MeshOccluder(caster, rot, float(scale), t, b, inner)


def inner_spheres(vertices, faces, centres) -> np.ndarray:
    """``(K, 4)`` balls inside the closed mesh ``(vertices, faces)`` (outward faces) about those of ``centres (C, 3)``
    that lie inside it: radius 0.999 times the distance to the nearest face's plane (a lower bound of the distance
    to the surface). A centre is inside when the first face met along each of three axes faces away from it."""
    from prtlab.geometry import RayCaster

    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    c = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    if not len(c) or not len(f):
        return np.zeros((0, 4))
    caster = RayCaster([(v, f)])
    inside = np.ones(len(c), dtype=bool)
    for axis in np.eye(3):
        hits = caster.closest_hit(c, np.broadcast_to(axis, c.shape))
        inside &= hits.hit & (hits.normal @ axis > 0.0)
    a, e1, e2 = v[f[:, 0]], v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]
    unit = np.cross(e1, e2)
    norm = np.linalg.norm(unit, axis=1)
    unit, a = unit[norm > 0] / norm[norm > 0, None], a[norm > 0]
    depth = np.abs(np.einsum("fi,fi->f", unit, a)[None] - c @ unit.T).min(axis=1)
    keep = inside & (depth > 0)
    return np.concatenate([c[keep], 0.999 * depth[keep, None]], axis=1)


def mesh_direct(points, normals, env_sh, rotation, blocked_self, occluders=(), rectangles=None, spheres=None,
                dirs=None, *, method: str = "numba", cast: str = "embree") -> np.ndarray:
    """Direct irradiance ``(P, 3)`` from the environment at receivers of one object, every mesh blocking (see the
    module docstring): :func:`mesh_direct_sums` of :func:`mesh_direct_visible`.

    Parameters
    ----------
    points, normals : (P, 3) float
        Receivers (world space) and their unit normals.
    env_sh : (N*N, 3) float
        Environment radiance (world space).
    rotation : (3, 3) float
        The receiving object's rotation: the directions ``dirs`` are in its frame.
    blocked_self : (P, ceil(M / 8)) uint8
        :func:`self_blocked` of the receivers (object space) along ``dirs``.
    occluders : sequence of MeshOccluder
        The other objects.
    rectangles : (G, 7) float, optional
        Ground rectangles (``_ground.ground_rectangles`` rows ``y0, cx, cz, ux, uz, vx, vz``), opaque.
    spheres : (L, 4) float, optional
        Opaque spheres (rows ``[x, y, z, r]``): the local lights.
    dirs : (M, 3) float, optional
        Unit directions in the object's frame, default :func:`fibonacci_directions` ``(1024)``.
    method : {"numba", "reference"}
        The kernels or their float64 numpy specification.
    cast : {"embree", "numpy"}
        The ray caster's engine for the other objects' meshes.

    With more than one numba thread (:func:`prtlab._tasks.task_threads`) the ``"numba"`` tier finds the visible
    rays of interleaved parts of the receivers as tasks (every receiver's rays and sums are its own: the same result
    bit for bit).
    """
    env = _checked_env(env_sh)
    visible = mesh_direct_visible(points, normals, rotation, blocked_self, occluders, rectangles, spheres, dirs,
                                  method=method, cast=cast)
    return mesh_direct_sums(visible, normals, env, rotation, dirs, method=method)


def _checked_env(env_sh) -> np.ndarray:
    env = np.asarray(env_sh, dtype=np.float64)
    order = math.isqrt(env.shape[0])
    if order * order != env.shape[0]:
        raise ValueError(f"env_sh must have n*n rows, got {env.shape[0]}")
    return env


def _checked(points, normals, dirs):
    d = fibonacci_directions(1024) if dirs is None else np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    n = np.ascontiguousarray(normals, dtype=np.float64).reshape(-1, 3)
    if p.shape != n.shape:
        raise ValueError(f"points and normals must have the same shape (P, 3), got {p.shape} and {n.shape}")
    return p, n, d


def mesh_direct_visible(points, normals, rotation, blocked_self, occluders=(), rectangles=None, spheres=None,
                        dirs=None, *, method: str = "numba", cast: str = "embree") -> np.ndarray:
    """``(P, ceil(M / 8))`` uint8, bits packed along the directions (``np.packbits`` order): whether the ray from
    each receiver along ``w_j = R d_j`` lies above its tangent plane and meets nothing (its own mesh, another
    object's mesh, a ground rectangle, an opaque sphere). The geometry of :func:`mesh_direct` (arguments as there),
    evaluated for an environment by :func:`mesh_direct_sums`."""
    from prtlab._validate import check_choice

    check_choice(method, "method", ("numba", "reference"))
    check_choice(cast, "cast", ("embree", "numpy"))
    p, n, d = _checked(points, normals, dirs)
    bits = np.ascontiguousarray(blocked_self, dtype=np.uint8)
    if bits.shape != (len(p), (len(d) + 7) // 8):
        raise ValueError(f"blocked_self must be (P, ceil(M / 8)) = {(len(p), (len(d) + 7) // 8)} packed bits "
                         f"(self_blocked of these receivers along these directions), got {bits.shape}")
    rot = np.asarray(rotation, dtype=np.float64).reshape(3, 3)
    rects = np.ascontiguousarray(np.zeros((0, 7)) if rectangles is None else rectangles, dtype=np.float64)
    balls = np.ascontiguousarray(np.zeros((0, 4)) if spheres is None else spheres, dtype=np.float64).reshape(-1, 4)
    w = np.ascontiguousarray(d @ rot.T)  # world directions
    # a Fibonacci set's directions descend in height (``d_y``, object frame): the rays in a cone are a run of them
    heights = np.ascontiguousarray(rot[:, 1]) if np.array_equal(d, fibonacci_directions(len(d))) else None

    def visible_bits(p, n, bits):  # (P, ceil(M / 8)) the visible rays at these receivers, chunk after chunk
        out = np.empty((len(p), (len(w) + 7) // 8), dtype=np.uint8)
        for s in range(0, len(p), _CHUNK):
            ps, ns = p[s:s + _CHUNK], n[s:s + _CHUNK]
            if method == "reference":
                visible = _visible_reference(ps, ns, w, bits[s:s + _CHUNK], rects, balls)
            else:
                visible = np.empty((len(ps), len(w)), dtype=np.bool_)
                _visible_kernel(ps, ns, w, bits[s:s + _CHUNK], rects, balls, _ALL, visible)
            for occ in occluders:
                if method == "reference":
                    cand = _meets_reference(ps, w, occ.bounds, visible)
                    sure = _meets_reference(ps, w, occ.inner, visible)
                    visible &= ~sure
                    ip, ij = np.nonzero(cand & ~sure)
                    if len(ip):
                        hit = _occluder_hits(ps, ns, w, occ, ip, ij, cast)
                        visible[ip[hit], ij[hit]] = False
                else:
                    _occluder_visible(ps, ns, w, occ, visible, heights, cast)
            out[s:s + _CHUNK] = np.packbits(visible, axis=1)
        return out

    threads = task_threads() if method == "numba" else 1
    if threads > 1 and len(p) > _CHUNK // 4:
        # every receiver's rays are its own: interleaved parts of the receivers as tasks
        out = np.empty((len(p), (len(w) + 7) // 8), dtype=np.uint8)
        parts = [np.arange(k, len(p), threads) for k in range(threads)]
        for rows, part in zip(parts, run_tasks([functools.partial(visible_bits, p[rows], n[rows], bits[rows])
                                                for rows in parts])):
            out[rows] = part
        return out
    return visible_bits(p, n, bits)


def mesh_direct_visible_update(kept_visible, kept_occluders, points, normals, rotation, blocked_self, occluders,
                               moved, rectangles=None, spheres=None, dirs=None, *, cast: str = "embree"):
    """:func:`mesh_direct_visible` (numba tier) when only the occluders flagged ``moved (O,) bool`` changed since
    ``kept_visible`` was computed with ``kept_occluders`` (the receivers, their own bits, the rotation, the
    rectangles, the spheres and the other occluders the same: the caller compares them): ``(visible, counts)``.

    A ray outside the cones of the moved occluders' bounding and inner spheres, in both frames, is never tested
    against them (``_meets``' cone tests, the same arithmetic, and with a Fibonacci set only within the same runs of
    directions), so its bit is kept; the rays inside are computed afresh against every occluder, as
    :func:`mesh_direct_visible` does (each occluder clears the rays it blocks whatever the others do: the moved ones
    first, then the others at the receivers with a ray left), and merged into the kept bits as packed bytes.
    ``counts``: ``{"rays", "rays_recomputed"}``."""
    p, n, d = _checked(points, normals, dirs)
    moved = np.asarray(moved, dtype=bool).reshape(-1)
    if len(moved) != len(occluders) or len(kept_occluders) != len(occluders):
        raise ValueError(f"moved must give one flag per occluder ({len(occluders)}), got {len(moved)} (kept "
                         f"{len(kept_occluders)})")
    bits = np.ascontiguousarray(blocked_self, dtype=np.uint8)
    rot = np.asarray(rotation, dtype=np.float64).reshape(3, 3)
    rects = np.ascontiguousarray(np.zeros((0, 7)) if rectangles is None else rectangles, dtype=np.float64)
    balls = np.ascontiguousarray(np.zeros((0, 4)) if spheres is None else spheres, dtype=np.float64).reshape(-1, 4)
    w = np.ascontiguousarray(d @ rot.T)
    heights = np.ascontiguousarray(rot[:, 1]) if np.array_equal(d, fibonacci_directions(len(d))) else None
    changed = []
    for g in np.nonzero(moved)[0]:
        changed += [np.asarray(x, dtype=np.float64).reshape(-1, 4) for x in (occluders[g].bounds, occluders[g].inner,
                                                                            kept_occluders[g].bounds,
                                                                            kept_occluders[g].inner)]
    changed = np.ascontiguousarray(np.concatenate(changed or [np.zeros((0, 4))]))
    out = np.array(kept_visible, dtype=np.uint8)
    recomputed = 0
    for s in range(0, len(p), _CHUNK):
        ps, ns = p[s:s + _CHUNK], n[s:s + _CHUNK]
        zone = np.empty((len(ps), len(w)), dtype=np.bool_)
        _zone_kernel(ps, w, changed, np.zeros(3) if heights is None else heights, heights is not None, zone)
        rows = np.nonzero(zone.any(axis=1))[0]
        if not len(rows):
            continue
        ps, ns, zone = ps[rows], ns[rows], zone[rows]
        visible = np.empty((len(ps), len(w)), dtype=np.bool_)
        _visible_kernel(ps, ns, w, bits[s:s + _CHUNK][rows], rects, balls, zone, visible)  # False off the zone
        # each occluder clears the rays it blocks, whatever the others do: the moved ones first (the zone lies in
        # their cones), each at the receivers with a ray still visible
        live = np.arange(len(ps))
        for g in sorted(range(len(occluders)), key=lambda g: not moved[g]):
            live = live[visible[live].any(axis=1)]
            if not len(live):
                break
            part = visible[live]
            _occluder_visible(ps[live], ns[live], w, occluders[g], part, heights, cast)
            visible[live] = part
        out[s + rows] = (out[s + rows] & ~np.packbits(zone, axis=1)) | np.packbits(visible, axis=1)
        recomputed += int(np.count_nonzero(zone))
    return out, {"rays": len(p) * len(w), "rays_recomputed": recomputed}


@numba.njit(cache=True, parallel=True, nogil=True)
def _zone_kernel(points, dirs, spheres, heights, fibonacci, zone):
    """``zone[q, j]``: the ray from ``points[q]`` along ``dirs[j]`` lies in the cone of one of ``spheres`` (the
    point inside one: every ray), by ``_cones``' arithmetic; with ``fibonacci`` (``dirs`` a Fibonacci set turned by a
    rotation of second column ``heights``) each cone tested only in its run of directions (``_cone_run``, as
    ``_meets_kernel`` tests them)."""
    n_dirs = dirs.shape[0]
    for q in numba.prange(points.shape[0]):
        axis, cos_half = np.empty((spheres.shape[0], 3)), np.empty(spheres.shape[0])
        inside = _cones(points[q], spheres, axis, cos_half)
        for j in range(n_dirs):
            zone[q, j] = inside
        if inside:
            continue
        run = np.empty(2, dtype=np.int64)
        for s in range(spheres.shape[0]):
            run[0], run[1] = 0, n_dirs - 1
            if fibonacci:
                run[0], run[1] = n_dirs, -1
                _cone_run(axis[s], cos_half[s], heights, n_dirs, run)
            ax, ay, az, c = axis[s, 0], axis[s, 1], axis[s, 2], cos_half[s]
            for j in range(run[0], run[1] + 1):
                if ax * dirs[j, 0] + ay * dirs[j, 1] + az * dirs[j, 2] > c:
                    zone[q, j] = True


#: The zone of :func:`_visible_kernel` that holds every ray.
_ALL = np.zeros((0, 0), dtype=np.bool_)


def mesh_direct_sums(visible, normals, env_sh, rotation, dirs=None, *, method: str = "numba") -> np.ndarray:
    """Direct irradiance ``(P, 3)`` at receivers of normals ``normals (P, 3)`` whose visible rays are ``visible``
    (:func:`mesh_direct_visible` along ``dirs`` turned by ``rotation``) under ``env_sh (N*N, 3)``: the closed-form
    unshadowed irradiance less ``4 pi / M sum_j max(0, n . w_j) L(w_j)`` over the front rays that are not visible.
    ``method``: the numba kernel or the float64 numpy specification (per receiver the same sum)."""
    from prtlab._validate import check_choice

    check_choice(method, "method", ("numba", "reference"))
    _, n, d = _checked(normals, normals, dirs)
    env = _checked_env(env_sh)
    order = math.isqrt(env.shape[0])
    rot = np.asarray(rotation, dtype=np.float64).reshape(3, 3)
    vis = np.ascontiguousarray(visible, dtype=np.uint8)
    if vis.shape != (len(n), (len(d) + 7) // 8):
        raise ValueError(f"visible must be (P, ceil(M / 8)) = {(len(n), (len(d) + 7) // 8)} packed bits "
                         f"(mesh_direct_visible of these receivers), got {vis.shape}")
    w = np.ascontiguousarray(d @ rot.T)  # world directions
    radiance = np.ascontiguousarray((sh.basis(w, order) @ env) * (4.0 * math.pi / len(d)))  # (M, 3), weighted
    out = sh.basis(n, order) @ sh.irradiance(env) if len(n) else np.zeros((0, 3))
    lost = np.empty((len(n), 3))
    for s in range(0, len(n), _CHUNK):
        if method == "reference":
            lost[s:s + _CHUNK] = _blocked_reference(n[s:s + _CHUNK], w, _unpack(vis[s:s + _CHUNK], len(w)), radiance)
    if method != "reference":
        _blocked_kernel(n, w, vis, radiance, lost)
    return out - lost


def _occluder_visible(points, normals, dirs, occ, visible, heights, cast):
    """``visible`` (returned) with the rays blocked by the occluder ``occ`` cleared: those meeting one of its inner
    spheres, and those meeting one of its bounding spheres whose cast meets its mesh."""
    ip, ij = _meets(points, dirs, occ.bounds, occ.inner, visible, heights)  # the kernel clears the inner spheres'
    if len(ip):
        hit = _occluder_hits(points, normals, dirs, occ, ip, ij, cast)
        visible[ip[hit], ij[hit]] = False
    return visible


def _occluder_hits(points, normals, dirs, occ, ip, ij, cast):
    """Whether the rays from ``points[ip]`` along ``dirs[ij]`` meet the occluder's mesh (cast in its space)."""
    o = (points[ip] - occ.translate) @ occ.rotation / occ.scale
    return occ.caster.occluded(o, dirs[ij] @ occ.rotation, normals=normals[ip] @ occ.rotation, method=cast)


def _meets(points, dirs, bounds, inner, visible, heights=None):
    """The visible rays meeting an inner sphere are cleared in ``visible``; returns the receiver and direction
    indices ``(ip, ij)`` (in the order of ``np.nonzero``) of the other visible rays meeting a bounding sphere (to
    cast). ``heights (3,)``: ``dirs`` are :func:`fibonacci_directions` turned by a rotation whose second column
    this is (only the directions in a run around each cone are tested); None: every direction."""
    n = np.count_nonzero(visible)  # a bound of the rays listed (count_nonzero: a pass over bytes, no sum of ints)
    ip, ij = np.empty(n, dtype=np.int64), np.empty(n, dtype=np.int64)
    k = _meets_kernel(points, dirs, np.ascontiguousarray(bounds, dtype=np.float64).reshape(-1, 4),
                      np.ascontiguousarray(inner, dtype=np.float64).reshape(-1, 4),
                      np.zeros(3) if heights is None else heights, heights is not None, visible, ip, ij)
    return ip[:k], ij[:k]


# ---------------------------------------------------------------------------------------------- float64 reference


def _unpack(bits, m):
    return np.unpackbits(bits, axis=1, count=m).astype(bool)


def _rect_hits_reference(points, dirs, rects):
    """(P, M) bool: the ray meets one of the rectangles (the plane ``y = y0`` within ``|a|, |b| <= 1``)."""
    out = np.zeros((len(points), len(dirs)), dtype=bool)
    for y0, cx, cz, ux, uz, vx, vz in rects:
        dy = dirs[:, 1][None]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (y0 - points[:, 1:2]) / dy
        x = points[:, 0:1] + t * dirs[:, 0][None] - cx
        z = points[:, 2:3] + t * dirs[:, 2][None] - cz
        a = (x * ux + z * uz) / (ux * ux + uz * uz)
        b = (x * vx + z * vz) / (vx * vx + vz * vz)
        out |= (dy != 0.0) & (t > 0.0) & (np.abs(a) <= 1.0) & (np.abs(b) <= 1.0)
    return out


def _visible_reference(points, normals, dirs, bits, rects, balls):
    """(P, M) bool: above the tangent plane and not blocked by the own mesh, a rectangle or an opaque sphere."""
    from ._groundrays import sphere_hits

    vis = ((normals @ dirs.T) > 0.0) & ~_unpack(bits, len(dirs)) & ~_rect_hits_reference(points, dirs, rects)
    if len(balls):
        vis &= ~np.isfinite(sphere_hits(points, dirs, balls, method="reference"))
    return vis


def _meets_reference(points, dirs, bounds, visible):
    from ._groundrays import sphere_hits

    if not len(bounds):
        return np.zeros(visible.shape, dtype=bool)
    return visible & np.isfinite(sphere_hits(points, dirs, bounds, method="reference"))


def _blocked_reference(normals, dirs, visible, radiance):
    """(P, 3) the weighted radiance of the front rays that are not visible."""
    cos = normals @ dirs.T
    return (np.where((cos > 0.0) & ~visible, cos, 0.0)) @ radiance


# ---------------------------------------------------------------------------------------------- numba kernels


@numba.njit(cache=True, parallel=True, nogil=True)
def _visible_kernel(points, normals, dirs, bits, rects, balls, zone, out):
    """``_visible_reference``: per receiver and direction, the tangent plane, the own mesh's bit, the rectangles'
    slab test and the opaque spheres (a point inside one sees nothing); only the rays of ``zone (P, M)`` (the others
    False) unless it is empty (:data:`_ALL`)."""
    every = zone.shape[0] == 0
    for q in numba.prange(points.shape[0]):
        px, py, pz = points[q, 0], points[q, 1], points[q, 2]
        inside = False
        for b in range(balls.shape[0]):
            ox, oy, oz = balls[b, 0] - px, balls[b, 1] - py, balls[b, 2] - pz
            if ox * ox + oy * oy + oz * oz <= balls[b, 3] * balls[b, 3]:
                inside = True
        for j in range(dirs.shape[0]):
            if not every and not zone[q, j]:
                out[q, j] = False
                continue
            dx, dy, dz = dirs[j, 0], dirs[j, 1], dirs[j, 2]
            vis = normals[q, 0] * dx + normals[q, 1] * dy + normals[q, 2] * dz > 0.0 and not inside
            if vis and (bits[q, j >> 3] >> (7 - (j & 7))) & 1:
                vis = False
            g = 0
            while vis and g < rects.shape[0]:
                if dy != 0.0:
                    t = (rects[g, 0] - py) / dy
                    if t > 0.0:
                        x = px + t * dx - rects[g, 1]
                        z = pz + t * dz - rects[g, 2]
                        a = (x * rects[g, 3] + z * rects[g, 4]) / (rects[g, 3] ** 2 + rects[g, 4] ** 2)
                        b = (x * rects[g, 5] + z * rects[g, 6]) / (rects[g, 5] ** 2 + rects[g, 6] ** 2)
                        if abs(a) <= 1.0 and abs(b) <= 1.0:
                            vis = False
                g += 1
            b = 0
            while vis and b < balls.shape[0]:
                ox, oy, oz = balls[b, 0] - px, balls[b, 1] - py, balls[b, 2] - pz
                c2 = ox * ox + oy * oy + oz * oz - balls[b, 3] * balls[b, 3]
                h = ox * dx + oy * dy + oz * dz
                if h > 0.0 and h * h - c2 > 0.0:
                    vis = False
                b += 1
            out[q, j] = vis


@numba.njit(cache=True)
def _cones(point, spheres, axis, cos_half):
    """Each sphere's cone from ``point`` (unit axis, cosine of its half angle); True if the point lies in one."""
    for s in range(spheres.shape[0]):
        ox, oy, oz = spheres[s, 0] - point[0], spheres[s, 1] - point[1], spheres[s, 2] - point[2]
        d2 = ox * ox + oy * oy + oz * oz
        r2 = spheres[s, 3] * spheres[s, 3]
        if d2 <= r2:
            return True
        inv = 1.0 / math.sqrt(d2)
        axis[s, 0], axis[s, 1], axis[s, 2] = ox * inv, oy * inv, oz * inv
        cos_half[s] = math.sqrt(1.0 - r2 / d2)
    return False


@numba.njit(cache=True)
def _cone_run(axis, cos_half, heights, n_dirs, run):
    """Widen ``run`` (first and last index) by the directions of a Fibonacci set of ``n_dirs`` turned by a rotation
    of second column ``heights`` that can lie in the cone ``(axis, cos_half)``: those of object-frame height within
    the cone's, one index of margin each side."""
    h = min(1.0, max(-1.0, heights[0] * axis[0] + heights[1] * axis[1] + heights[2] * axis[2]))
    polar, half = math.acos(h), math.acos(min(1.0, max(-1.0, cos_half)))
    top, bottom = math.cos(max(0.0, polar - half)), math.cos(min(math.pi, polar + half))
    first = int(math.floor(((1.0 - top) * n_dirs - 1.0) / 2.0)) - 1  # d_y = 1 - (2 j + 1) / n
    last = int(math.ceil(((1.0 - bottom) * n_dirs - 1.0) / 2.0)) + 1
    run[0], run[1] = max(0, min(run[0], first)), min(n_dirs - 1, max(run[1], last))


@numba.njit(cache=True, nogil=True)
def _meets_kernel(points, dirs, bounds, inner, heights, fibonacci, visible, ip, ij):
    """``_meets``: per visible ray, the inner spheres' cones (cleared), else the bounding spheres' (listed); a point
    inside a sphere: every ray. With ``fibonacci`` only the run of directions around the cones is tested (the
    others meet none). Returns the number listed. Serial: a parallel region per call costs more than the work."""
    b_axis, b_cos = np.empty((bounds.shape[0], 3)), np.empty(bounds.shape[0])
    i_axis, i_cos = np.empty((inner.shape[0], 3)), np.empty(inner.shape[0])
    run = np.empty(2, dtype=np.int64)
    k = 0
    for q in range(points.shape[0]):
        b_in = _cones(points[q], bounds, b_axis, b_cos)
        i_in = _cones(points[q], inner, i_axis, i_cos)
        run[0], run[1] = 0, dirs.shape[0] - 1
        if fibonacci and not (b_in or i_in):
            run[0], run[1] = dirs.shape[0], -1
            for s in range(bounds.shape[0]):
                _cone_run(b_axis[s], b_cos[s], heights, dirs.shape[0], run)
            for s in range(inner.shape[0]):
                _cone_run(i_axis[s], i_cos[s], heights, dirs.shape[0], run)
        for j in range(run[0], run[1] + 1):
            if not visible[q, j]:
                continue
            dx, dy, dz = dirs[j, 0], dirs[j, 1], dirs[j, 2]
            sure = i_in
            s = 0
            while not sure and s < i_axis.shape[0]:
                sure = i_axis[s, 0] * dx + i_axis[s, 1] * dy + i_axis[s, 2] * dz > i_cos[s]
                s += 1
            if sure:
                visible[q, j] = False
                continue
            cand = b_in
            s = 0
            while not cand and s < b_axis.shape[0]:
                cand = b_axis[s, 0] * dx + b_axis[s, 1] * dy + b_axis[s, 2] * dz > b_cos[s]
                s += 1
            if cand:
                ip[k], ij[k] = q, j
                k += 1
    return k


@numba.njit(cache=True, parallel=True, nogil=True)
def _blocked_kernel(normals, dirs, visible, radiance, out):
    """``_blocked_reference`` (``visible``: packed bits, ``np.packbits`` order)."""
    for q in numba.prange(normals.shape[0]):
        r, g, b = 0.0, 0.0, 0.0
        for j in range(dirs.shape[0]):
            c = normals[q, 0] * dirs[j, 0] + normals[q, 1] * dirs[j, 1] + normals[q, 2] * dirs[j, 2]
            if c > 0.0 and not (visible[q, j >> 3] >> (7 - (j & 7))) & 1:
                r += c * radiance[j, 0]
                g += c * radiance[j, 1]
                b += c * radiance[j, 2]
        out[q, 0], out[q, 1], out[q, 2] = r, g, b

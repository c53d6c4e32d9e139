"""The ground in light transport: it hides what lies beyond it and reflects its own light (an extension of
Guerrero et al. 2008, whose ground only receives).

A ground is a horizontal, flat, receiving-only object (all world vertices at one height, normals ``+Y``),
represented by its height and a rectangle in ``x, z`` (centre and two half edges: the object-space bounding box
of its mesh, placed by its transform, so a rotated ground stays the same rectangle).

First pass (:func:`ground_blocked_transfer`): each surface sample's transfer loses the directions in which the
ground lies,

.. math:: \\mathbf T_q = P_n\\big(L\\, \\max(0, n_q\\cdot\\omega)\\big)
          - P_n\\big(L\\, G_q\\, \\max(0, n_q\\cdot\\omega)\\big),

``G_q(w) = 1`` where the ray ``q + t w`` hits a ground rectangle, the second term a quadrature over a fixed
product grid of the lower hemisphere (``W[q, j] = w_j G_q(w_j) max(0, n_q . w_j)``, a numba kernel), so the
samples' visibility multiplies it in SH. It is computed as the projection of each sample's ``W[q]`` to SH
(:func:`ground_hidden_projection`, geometry only, kept while the samples stay) times the sky's Gaunt coefficients
(:func:`hidden_transfer`): the grid's sum ``W @ A`` (``A[j] = L(w_j) y(w_j)``) up to rounding.

Second pass (:func:`ground_light`), at every receiver above a ground: over the directions ``H_q`` that meet the
ground before any spherical light (binary ray tests against the lights adjusted as in the second pass),

.. math:: E^{hid}_q = \\int_{H_q} L_2(\\omega) \\max(0, n_q\\cdot\\omega)\\, d\\omega, \\qquad
          E^{gnd}_q = \\int_{H_q} L_g(x_q(\\omega)) \\max(0, n_q\\cdot\\omega)\\, d\\omega,

``L_2`` the radiance the second pass gave those directions (the environment, or a local light beyond the
ground) and ``L_g`` the ground's exit radiance at the hit point ``x_q`` (its per-vertex radiance interpolated
over its mesh, :func:`ground_texture`). The pipeline subtracts ``E^hid`` from the direct irradiance and adds
``E^gnd`` to the indirect. The quadrature runs per azimuth over the exact elevation interval that meets the
rectangle above the receiver's tangent plane (Gauss-Legendre nodes), so the ground's edge and the horizon are
no source of error; the lights' silhouettes are (steps), and the binary visibility of the lights is not the SH
visibility of the direct term.

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

from ._libm import atan_nonneg, sincos_quarter
from ._reuse import kept_by_key
from ._shadows import _adjust, one_thread

__all__ = ["ground_rectangles", "ground_objects", "ground_blocked_transfer", "ground_hidden_projection",
           "hidden_transfer", "ground_light", "GroundSamples",
           "ground_samples", "ground_samples_update", "ground_sample_sums", "ground_raster", "ground_texture",
           "covered_texels", "fill_covered"]


def ground_rectangles(objects, transforms=None) -> np.ndarray:
    """Ground rectangles of the receiving-only, flat, horizontal objects: ``(G, 7)`` rows
    ``[y, c_x, c_z, u_x, u_z, v_x, v_z]`` (world space; centre ``c`` and half edges ``u, v``).

    Parameters
    ----------
    objects : iterable of prtlab.scene.SceneObject
        Candidates (the objects that carry no spherical lights).
    transforms : dict, optional
        ``{name: Transform}`` of the frame (default: each object's own).
    """
    return np.asarray([row for _, row in ground_objects(objects, transforms)], dtype=np.float64).reshape(-1, 7)


def ground_objects(objects, transforms=None) -> list:
    """``[(object, rectangle row (7,))]`` of the grounds among ``objects`` (see :func:`ground_rectangles`)."""
    out = []
    for obj in objects:
        tr = (transforms or {}).get(obj.name) or obj.transform
        v = np.asarray(obj.world_vertices(tr), dtype=np.float64)
        if v.shape[0] < 3:
            continue
        n = np.asarray(obj.world_normals(tr), dtype=np.float64)
        extent = float(np.ptp(v, axis=0).max())
        if extent <= 0 or np.ptp(v[:, 1]) > 1e-9 * extent or np.any(n[:, 1] < 1.0 - 1e-9):
            continue
        local = np.asarray(obj.mesh.vertices, dtype=np.float64)
        lo, hi = local.min(axis=0), local.max(axis=0)
        flat = int(np.argmin(hi - lo))
        a1, a2 = [k for k in range(3) if k != flat]
        centre = tr.apply_points(0.5 * (lo + hi)[None])[0]
        rot = np.asarray(tr.rotation, dtype=np.float64) * float(tr.scale)
        u = rot[:, a1] * 0.5 * (hi - lo)[a1]
        w = rot[:, a2] * 0.5 * (hi - lo)[a2]
        out.append((obj, np.array([v[0, 1], centre[0], centre[2], u[0], u[2], w[0], w[2]])))
    return out


@functools.lru_cache(maxsize=None)
def _lower_hemisphere_grid(n_azimuth: int, n_elevation: int):
    """Directions (K, 3) and solid-angle weights (K,) of the product grid of the lower hemisphere."""
    x, w = np.polynomial.legendre.leggauss(n_elevation)
    e = 0.25 * np.pi * (x + 1.0)  # elevation below the horizon, (0, pi/2)
    we = 0.25 * np.pi * w * np.cos(e)
    phi = (np.arange(n_azimuth) + 0.5) * (2.0 * np.pi / n_azimuth)
    ee, pp = np.meshgrid(e, phi, indexing="ij")
    dirs = np.stack([np.cos(ee) * np.cos(pp), -np.sin(ee), np.cos(ee) * np.sin(pp)], -1).reshape(-1, 3)
    weights = np.repeat(we, n_azimuth) * (2.0 * np.pi / n_azimuth)
    dirs.setflags(write=False)
    weights.setflags(write=False)
    return dirs, weights


#: Bytes of a block of rows of the weights in :func:`ground_blocked_transfer` (3 MiB: under numpy's 4 MiB, from
#: which it asks for huge pages).
_WEIGHT_BLOCK_BYTES = 3 << 20


@numba.njit(cache=True, parallel=True, error_model="numpy", nogil=True)
def _ground_weights(points, normals, dirs, weights, rects, out):
    """out[q, j] = weights[j] * hit(q, j) * max(0, n_q . d_j); hit: the ray from q along d_j meets a rectangle.

    Per point and rectangle one branch-free loop over the directions (held as coordinate rows), which LLVM
    vectorises; the values are those of the per-direction test."""
    n_pts = points.shape[0]
    n_dir = dirs.shape[0]
    d = np.empty((3, n_dir))
    for j in range(n_dir):
        d[0, j], d[1, j], d[2, j] = dirs[j, 0], dirs[j, 1], dirs[j, 2]
    for q in numba.prange(n_pts):
        px, py, pz = points[q, 0], points[q, 1], points[q, 2]
        nx, ny, nz = normals[q, 0], normals[q, 1], normals[q, 2]
        for j in range(n_dir):
            out[q, j] = 0.0
        for g in range(rects.shape[0]):
            h = py - rects[g, 0]
            if h <= 0.0:
                continue
            cx, cz, ux, uz, vx, vz = rects[g, 1], rects[g, 2], rects[g, 3], rects[g, 4], rects[g, 5], rects[g, 6]
            su = ux ** 2 + uz ** 2
            sv = vx ** 2 + vz ** 2
            for j in range(n_dir):
                c = nx * d[0, j] + ny * d[1, j] + nz * d[2, j]
                t = h / -d[1, j]
                dx = px + t * d[0, j] - cx
                dz = pz + t * d[2, j] - cz
                a = (dx * ux + dz * uz) / su
                b = (dx * vx + dz * vz) / sv
                if c > 0.0 and abs(a) <= 1.0 and abs(b) <= 1.0:
                    out[q, j] = weights[j] * c


def _ground_weights_reference(points, normals, dirs, weights, rects):
    """numpy specification of ``_ground_weights``."""
    cos = np.maximum(normals @ dirs.T, 0.0)
    hit = np.zeros(cos.shape, dtype=bool)
    for y0, cx, cz, ux, uz, vx, vz in rects:
        h = points[:, 1:2] - y0
        t = h / -dirs[None, :, 1]
        dx = points[:, 0:1] + t * dirs[None, :, 0] - cx
        dz = points[:, 2:3] + t * dirs[None, :, 2] - cz
        a = (dx * ux + dz * uz) / (ux * ux + uz * uz)
        b = (dx * vx + dz * vz) / (vx * vx + vz * vz)
        hit |= (h > 0) & (np.abs(a) <= 1.0) & (np.abs(b) <= 1.0)
    return np.where(hit, weights[None, :] * cos, 0.0)


def _grid_directions(phi0: float, n_azimuth: int, n_elevation: int) -> tuple[np.ndarray, np.ndarray]:
    """The product grid of the lower hemisphere (:func:`_lower_hemisphere_grid`, elevation-major) turned about
    ``+Y`` by ``phi0`` (the first ground's ``u`` edge, so that the result turns with the scene): directions
    ``(K, 3)`` and weights ``(K,)``."""
    dirs, weights = _lower_hemisphere_grid(int(n_azimuth), int(n_elevation))
    c0, s0 = math.cos(phi0), math.sin(phi0)
    dirs = np.stack([c0 * dirs[:, 0] - s0 * dirs[:, 2], dirs[:, 1], s0 * dirs[:, 0] + c0 * dirs[:, 2]], -1)
    return np.ascontiguousarray(dirs), np.ascontiguousarray(weights)


def _phi0(rectangles) -> float:
    return math.atan2(rectangles[0, 4], rectangles[0, 3])


def _checked_grid_inputs(points, normals, rectangles):
    p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    n = np.ascontiguousarray(normals, dtype=np.float64).reshape(-1, 3)
    return p, n, np.ascontiguousarray(rectangles, dtype=np.float64).reshape(-1, 7)


#: The frame of :func:`ground_hidden_projection`'s coefficients: ``u = UP_FRAME @ w`` takes ``+Y`` (the ground's
#: normal) to the SH's polar axis ``+Z``, so that the grid's elevations are polar angles and its azimuths azimuths.
UP_FRAME = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
UP_FRAME.setflags(write=False)


@functools.lru_cache(maxsize=16)
def _grid_factors(order: int, n_azimuth: int, n_elevation: int, phi0: float) -> tuple:
    """The SH basis at the grid's directions in :data:`UP_FRAME` as products of an azimuth and an elevation factor,
    ``y_l(UP_FRAME w_ik) = E[i, l] T[k, t_l]``: ``T (n_azimuth, 2 order - 1)`` the columns ``1, cos phi, sin phi,
    cos 2 phi, ...`` at the grid's azimuths, ``E (n_elevation, order**2)``, and per column ``t`` of ``T`` the
    coefficients ``l`` with ``t_l = t`` (``m = 0``: ``t = 0``; ``m > 0``: ``cos m phi``; ``m < 0``: ``sin |m| phi``).
    ``E`` is the grid's discrete Fourier coefficient, exact for ``order <= n_azimuth / 2``."""
    dirs, _ = _grid_directions(phi0, n_azimuth, n_elevation)
    u = dirs @ UP_FRAME.T
    phi = np.arctan2(u[:n_azimuth, 1], u[:n_azimuth, 0])  # elevation-major: the first row's azimuths
    cols = [np.ones_like(phi)]
    for m in range(1, order):
        cols += [np.cos(m * phi), np.sin(m * phi)]
    t = np.stack(cols, -1)
    y = sh.basis(u, order).reshape(n_elevation, n_azimuth, -1)
    m_of = np.concatenate([np.arange(-l, l + 1) for l in range(order)])
    col_of = np.where(m_of == 0, 0, np.where(m_of > 0, 2 * m_of - 1, -2 * m_of))
    scale = np.where(m_of == 0, 1.0, 2.0) / n_azimuth
    e = np.einsum("ikl,kl->il", y, t[:, col_of]) * scale
    groups = tuple(np.flatnonzero(col_of == c) for c in range(t.shape[1]))
    for x in (t, e, *groups):
        x.setflags(write=False)
    return t, e, groups


def ground_hidden_projection(points, normals, rectangles, order: int, *, n_azimuth: int = 128, n_elevation: int = 32,
                             threads: int | None = None) -> np.ndarray:
    """The SH projection of each point's hidden clamped cosine over the product grid of
    :func:`ground_blocked_transfer` (arguments as there): ``(B, order*order)`` rows
    ``v_q[l] = sum_j w_j G_q(w_j) max(0, n_q . w_j) y_l(UP_FRAME w_j)``, coefficients in the frame
    :data:`UP_FRAME`. Geometry only: :func:`hidden_transfer` turns it into that function's result for any sky of
    order ``N <= order - n + 1`` (``n`` the transfer's order), so a caller whose points stay keeps it while the sky
    changes. The grid's basis splits into azimuth and elevation factors (:func:`_grid_factors`), so a chunk of rows
    costs one product with the ``2 order - 1`` azimuth columns, then one small product per column; chunks of rows as
    tasks on ``threads`` (default numba's thread count here). The products' blocking depends on the number of points
    (not on the threads), so a point's values may differ in the last bits between calls with other points: a caller
    that keeps rows makes them in the same calls as a fresh one. Needs ``order <= n_azimuth / 2``."""
    p, n, rects = _checked_grid_inputs(points, normals, rectangles)
    order = int(order)
    if 2 * order > int(n_azimuth):
        raise ValueError(f"order {order} needs n_azimuth >= {2 * order}, got {n_azimuth}")
    out = np.zeros((p.shape[0], order * order))
    if p.shape[0] == 0 or rects.shape[0] == 0:
        return out
    phi0 = _phi0(rects)
    dirs, weights = _grid_directions(phi0, n_azimuth, n_elevation)
    t, e, groups = _grid_factors(order, int(n_azimuth), int(n_elevation), phi0)
    # the weights in blocks of rows, a task's azimuth sums in chunks of rows, each under 4 MiB: a fresh larger array
    # is backed by huge pages, whose faults (zeroing, compaction) cost more system time than the products
    # (an even number of chunks, for two threads, set by the number of points alone: the products' blocking, and
    # so the result's rounding, does not depend on the threads)
    n_dirs, n_el, n_t = dirs.shape[0], int(n_elevation), t.shape[1]
    n_chunks = 2 * -(-p.shape[0] // (2 * max(1, _WEIGHT_BLOCK_BYTES // (8 * n_el * n_t))))
    chunk = -(-p.shape[0] // n_chunks)
    rows = max(1, min(_WEIGHT_BLOCK_BYTES // (8 * n_dirs), chunk))

    def chunks(starts):  # a task of run_tasks: chunks of rows, one scratch for them
        w, f = np.empty((rows, n_dirs)), np.empty((chunk, n_el, n_t))  # f[q, i, c] = sum_k W[q, (i, k)] T[k, c]
        for s in starts:
            stop = min(p.shape[0], s + chunk)
            for b in range(s, stop, rows):
                e_b = min(stop, b + rows)
                _ground_weights(p[b:e_b], n[b:e_b], dirs, weights, rects, w[: e_b - b])
                np.matmul(w[: e_b - b].reshape(-1, t.shape[0]), t, out=f[b - s: e_b - s].reshape(-1, n_t))
            for c, ls in enumerate(groups):  # then per azimuth column
                out[s:stop, ls] = f[: stop - s, :, c] @ e[:, ls]

    starts = list(range(0, p.shape[0], chunk))
    k = min(len(starts), max(1, task_threads() if threads is None else threads))
    with one_thread():  # the tasks are the parallel work: small products on one BLAS thread
        run_tasks([functools.partial(chunks, starts[i::k]) for i in range(k)], threads=k)
    return out


@functools.lru_cache(maxsize=16)
def _triple_rule(n_proj: int, order: int, n_env: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An exact rule for ``y_l(UP_FRAME w) y_k(w) y_m(w)`` (``l < n_proj**2``, ``k < order**2``, ``m < n_env**2``):
    the weighted basis in :data:`UP_FRAME` ``(K, n_proj**2)``, and the bases ``(K, order**2)``, ``(K, n_env**2)`` at
    its nodes (read-only)."""
    dirs, w = sh.quadrature(1, degree=(n_proj - 1) + (order - 1) + (n_env - 1))
    y = sh.basis(dirs, max(order, n_env))
    out = (sh.basis(dirs @ UP_FRAME.T, n_proj) * w[:, None], y[:, : order * order].copy(),
           y[:, : n_env * n_env].copy())
    for a in out:
        a.setflags(write=False)
    return out


def hidden_transfer(projection, env_sh, order: int) -> np.ndarray:
    """:func:`ground_blocked_transfer` ``(B, order*order, C)`` from the points' :func:`ground_hidden_projection`
    ``(B, P*P)`` under the sky ``env_sh (N*N, C)``, ``P >= order + N - 1``: ``t[q, k, c] = sum_l v_q[l] int
    y_l(UP_FRAME w) y_k(w) L_c(w) dw``. ``y_k L_c`` is a spherical polynomial of degree ``order + N - 2 < P``, so it
    is its own order-``P`` projection (in any frame) and the sum equals the grid's ``sum_j W_qj y_k(w_j) L_c(w_j)`` up
    to rounding; the integrals are those of an exact rule (``sh.quadrature``)."""
    v = np.asarray(projection, dtype=np.float64)
    env = np.asarray(env_sh, dtype=np.float64)
    n_proj, n_env, order = math.isqrt(v.shape[1]), math.isqrt(env.shape[0]), int(order)
    if n_proj * n_proj != v.shape[1] or n_proj < order + n_env - 1:
        raise ValueError(f"the projection has {v.shape[1]} coefficients; the transfer of order {order} under a sky "
                         f"of order {n_env} needs order {order + n_env - 1} ({(order + n_env - 1) ** 2})")
    yw, yk, ym = _triple_rule(n_proj, order, n_env)
    with one_thread():  # small products: OpenBLAS's waiting workers would slow the numba kernels after them
        g = yw.T @ (yk[:, :, None] * (ym @ env)[:, None, :]).reshape(len(yk), -1)  # (P*P, order*order*C)
        return (v @ g).reshape(v.shape[0], order * order, env.shape[1])


def ground_blocked_transfer(points, normals, env_sh, rectangles, *, n_azimuth: int = 128, n_elevation: int = 32,
                            method: str = "numba", order: int | None = None, threads: int | None = None) -> np.ndarray:
    """The part of the environment transfer that the ground hides: ``P_n(L G_q max(0, n_q . w))``.

    Parameters
    ----------
    points, normals : (B, 3) float
        Surface samples (world space) and their unit normals.
    env_sh : (N*N, C) float
        Environment radiance (any order ``N``).
    rectangles : (G, 7) float
        :func:`ground_rectangles`.
    n_azimuth, n_elevation : int
        Product grid of the lower hemisphere.
    method : {"numba", "reference"}
        ``"numba"``: the points' :func:`ground_hidden_projection` at order ``n + N - 1``, then
        :func:`hidden_transfer`; ``"reference"``: the grid's sum as one numpy matrix product ``W @ A``
        (``A[j] = L(w_j) y(w_j)``), the specification. They agree up to rounding.
    order : int, optional
        Order ``n`` of the result (default: ``N``).
    threads : int, optional
        The ``"numba"`` tier's blocks of rows as tasks on this many threads (:func:`prtlab._tasks.run_tasks`, each
        block's products as one after another; default numba's thread count here).

    Returns
    -------
    t : (B, n*n, C) float64
        To subtract from :func:`prtlab.spherelights.environment_transfer`.

    Notes
    -----
    ``t_q[k] = sum_j w_j G_q(w_j) max(0, n_q . w_j) L(w_j) y_k(w_j)`` with ``L`` the order-``N``
    environment; the quadrature error comes from the step of ``G_q`` at the ground's edge and the
    kink of the clamped cosine (first order in the grid spacing).
    """
    if method not in ("numba", "reference"):
        raise ValueError(f"method must be 'numba' or 'reference', got {method!r}")
    p, n, rects = _checked_grid_inputs(points, normals, rectangles)
    env = np.asarray(env_sh, dtype=np.float64)
    n_env = math.isqrt(env.shape[0])
    order = n_env if order is None else int(order)
    if p.shape[0] == 0 or rects.shape[0] == 0:
        return np.zeros((p.shape[0], order * order, env.shape[1]))
    if method == "numba":
        v = ground_hidden_projection(p, n, rects, order + n_env - 1, n_azimuth=n_azimuth, n_elevation=n_elevation,
                                     threads=threads)
        return hidden_transfer(v, env, order)
    dirs, weights = _grid_directions(_phi0(rects), n_azimuth, n_elevation)
    y = sh.basis(dirs, max(order, n_env))
    a = (y[:, : order * order, None] * (y[:, : n_env * n_env] @ env)[:, None, :]).reshape(dirs.shape[0], -1)
    w = _ground_weights_reference(p, n, dirs, weights, rects)
    return (w @ a).reshape(p.shape[0], order * order, env.shape[1])


# --------------------------------------------------------------------------- the ground in the second pass


class GroundQuadrature(NamedTuple):
    """Directions of the per-receiver ground quadrature: azimuths ``phi_k = phi_0 + (k + 1/2) 2 pi / K`` (cos, sin),
    and Gauss-Legendre nodes and weights on ``[-1, 1]`` mapped per azimuth onto the elevations that see the ground."""

    cos_az: np.ndarray  # (K,)
    sin_az: np.ndarray  # (K,)
    nodes: np.ndarray  # (E,)
    weights: np.ndarray  # (E,)


class GroundScene(NamedTuple):
    """What a receiver's ground directions meet: the ground rectangles (``ground_rectangles``) with a radiance texture
    each, the spherical lights as opaque blockers (world space, adjusted per receiver as in the second pass) with the
    constant radiance of the local ones, and the environment's radiance at the quadrature's azimuths."""

    rects: np.ndarray  # (G, 7)
    texture: np.ndarray  # (G, R, R, 3) exit radiance over the rectangle's [-1, 1]^2 (texel centres)
    centres: np.ndarray  # (S, 3)
    radii: np.ndarray  # (S,)
    local_radiance: np.ndarray  # (S, 3) radiance of a local light (Sec. 7.3), 0 for an object's light
    is_local: np.ndarray  # (S,) bool
    env_table: np.ndarray  # (K, T + 1, 3) environment radiance at azimuth k, elevation pi/2 t / T below the horizon


@functools.lru_cache(maxsize=None)
def ground_quadrature(n_azimuth: int, n_elevation: int, phi0: float = 0.0) -> GroundQuadrature:
    """:class:`GroundQuadrature` of ``n_azimuth`` azimuths from ``phi0`` and ``n_elevation`` Gauss-Legendre nodes."""
    x, w = np.polynomial.legendre.leggauss(n_elevation)
    phi = phi0 + (np.arange(n_azimuth) + 0.5) * (2.0 * np.pi / n_azimuth)
    out = GroundQuadrature(np.cos(phi), np.sin(phi), x, w)
    for a in out:
        a.setflags(write=False)
    return out


@numba.njit(cache=True, inline="always")
def _rect_coordinates(px, pz, rect):
    """Edge coordinates ``(a, b)`` of ``(px, pz)`` in the rectangle ``rect = [y, c_x, c_z, u_x, u_z, v_x, v_z]``
    (``[-1, 1]^2`` inside) and its edges' ``1 / |u|^2, 1 / |v|^2``."""
    dx, dz = px - rect[1], pz - rect[2]
    inv_u = 1.0 / (rect[3] * rect[3] + rect[4] * rect[4])
    inv_v = 1.0 / (rect[5] * rect[5] + rect[6] * rect[6])
    return (dx * rect[3] + dz * rect[4]) * inv_u, (dx * rect[5] + dz * rect[6]) * inv_v, inv_u, inv_v


@numba.njit(cache=True, inline="always")
def _texture_at(tex, g, a, b):
    """Bilinear lookup of texture ``g`` at edge coordinates ``(a, b)`` in ``[-1, 1]^2`` (clamped to the texel
    centres); returns the three channels."""
    r = tex.shape[1]
    x = min(max(0.5 * (a + 1.0) * r - 0.5, 0.0), r - 1.0)
    y = min(max(0.5 * (b + 1.0) * r - 0.5, 0.0), r - 1.0)
    i = min(int(x), r - 2) if r > 1 else 0
    j = min(int(y), r - 2) if r > 1 else 0
    fx, fy = x - i, y - j
    i1, j1 = min(i + 1, r - 1), min(j + 1, r - 1)
    out0 = ((1 - fx) * (1 - fy) * tex[g, i, j, 0] + fx * (1 - fy) * tex[g, i1, j, 0]
            + (1 - fx) * fy * tex[g, i, j1, 0] + fx * fy * tex[g, i1, j1, 0])
    out1 = ((1 - fx) * (1 - fy) * tex[g, i, j, 1] + fx * (1 - fy) * tex[g, i1, j, 1]
            + (1 - fx) * fy * tex[g, i, j1, 1] + fx * fy * tex[g, i1, j1, 1])
    out2 = ((1 - fx) * (1 - fy) * tex[g, i, j, 2] + fx * (1 - fy) * tex[g, i1, j, 2]
            + (1 - fx) * fy * tex[g, i, j1, 2] + fx * fy * tex[g, i1, j1, 2])
    return out0, out1, out2


@numba.njit(cache=True, error_model="numpy", inline="always")
def _elevation_span(coords, h, nx, ny, nz, ux, uz, rect):
    """Elevations ``(lo, hi)`` below the horizon along the azimuth ``(ux, uz)`` whose rays from a receiver at the
    rectangle's edge coordinates ``coords`` (:func:`_rect_coordinates`), ``h`` above the rectangle ``rect``
    (normal ``n``), meet the rectangle in front of the receiver's tangent plane: one interval, empty when ``lo >=
    hi`` (then ``(1, 0)`` where the rays miss the rectangle). Selects, no branch, so a loop over azimuths
    vectorises; a quotient whose select is not taken divides by 1 instead of a zero."""
    # the horizontal distances [d_in, d_out] inside the rectangle (a slab test in its edge coordinates)
    d_in, d_out = 0.0, np.inf
    inside = True
    for e in range(2):
        a0 = coords[0] if e == 0 else coords[1]
        da = (ux * rect[3 + 2 * e] + uz * rect[4 + 2 * e]) * (coords[2] if e == 0 else coords[3])
        flat = da == 0.0  # parallel to the edge pair: inside it throughout, or never
        d = 1.0 if flat else da
        t1, t2 = (-1.0 - a0) / d, (1.0 - a0) / d
        t_near, t_far = (t2, t1) if t1 > t2 else (t1, t2)
        d_in = d_in if flat else max(d_in, t_near)
        d_out = d_out if flat else min(d_out, t_far)
        inside = inside and not (flat and abs(a0) > 1.0)
    meets = inside and d_in < d_out
    # where a cos e - b sin e > 0, e in [0, pi/2]: in front of the tangent plane
    a, b = nx * ux + nz * uz, ny
    t = atan_nonneg(a / (b if b != 0.0 else 1.0))
    c_lo = 0.0 if a > 0.0 else (t if b < 0.0 else 1.0)
    c_hi = (0.5 * np.pi if b <= 0.0 else t) if a > 0.0 else (0.5 * np.pi if b < 0.0 else 0.0)
    lo = max(atan_nonneg(h / (d_out if meets else 1.0)), c_lo)
    hi = min(atan_nonneg(h / (d_in if d_in > 0.0 else 1.0)) if d_in > 0.0 else 0.5 * np.pi, c_hi)
    return (lo, hi) if meets else (1.0, 0.0)


@numba.njit(cache=True, error_model="numpy", inline="always")
def _node_directions(px, pz, h, nx, ny, nz, cos_az, sin_az, nodes, rect, half, el, ce, se):
    """For a receiver (as :func:`_elevation_span`) and every azimuth ``k``: ``half[k]``, the half width of its
    elevation interval (negative: none), and at its Gauss-Legendre nodes the elevation ``el[k * E + i] = lo + half
    (x_i + 1)``, its cosine ``ce`` and sine ``se`` (``E`` nodes; unspecified for an azimuth without an interval).
    The intervals, and the sines and cosines, are loops of their own, which vectorise."""
    n_el = nodes.shape[0]
    coords = _rect_coordinates(px, pz, rect)
    for k in range(cos_az.shape[0]):  # ce[k]: the interval's start, until the sines and cosines below
        lo, hi = _elevation_span(coords, h, nx, ny, nz, cos_az[k], sin_az[k], rect)
        half[k] = 0.5 * (hi - lo) if lo < hi else -1.0
        ce[k] = lo
    for k in range(cos_az.shape[0]):
        for i in range(n_el):
            el[k * n_el + i] = ce[k] + half[k] * (nodes[i] + 1.0)
    for j in range(el.shape[0]):
        se[j], ce[j] = sincos_quarter(el[j])


@numba.njit(cache=True, inline="always")
def _lights_on_ray(wx, wy, wz, t_ground, live, live_id, cand, n_cand, is_local):
    """Along the ray ``p + t w`` (unit ``w``): whether a light (rows ``cand[:n_cand]`` of ``live``: centre, radius,
    the centre less ``p`` and ``|c - p|^2 - r^2``) is hit before ``t_ground``, and else the nearest local light hit
    beyond it (its index ``live_id[j]``, -1: none)."""
    t_beyond = np.inf
    beyond = -1
    for m in range(n_cand):
        j = cand[m]
        bb = live[j, 4] * wx + live[j, 5] * wy + live[j, 6] * wz
        disc = bb * bb - live[j, 7]
        if bb <= 0.0 or disc <= 0.0:
            continue
        t_hit = bb - math.sqrt(disc)
        if t_hit < t_ground:
            return True, -1
        if is_local[live_id[j]] and t_hit < t_beyond:
            t_beyond = t_hit
            beyond = live_id[j]
    return False, beyond


#: Receivers a task of the samples' kernels takes at a time (one scratch for them).
_SAMPLE_CHUNK = 16


@numba.njit(cache=True, inline="always")
def _sample_scratch(n_sph, n_az, n_el):
    """A task's scratch for :func:`_receiver_samples`: the live lights (:func:`_lights_on_ray`'s rows), their
    ids, the candidates of an azimuth, and per azimuth and node the interval's half width, the elevation, its
    cosine and sine."""
    return (np.empty((n_sph, 8)), np.empty(n_sph, dtype=np.int64), np.empty(n_sph, dtype=np.int64), np.empty(n_az),
            np.empty(n_az * n_el), np.empty(n_az * n_el), np.empty(n_az * n_el))


@numba.njit(cache=True, inline="always")
def _receiver_samples(px, py, pz, nx, ny, nz, quad, scene, n_tab, unadjusted, scratch, reals, ints, m):
    """The directions ``w`` from the receiver ``p, n`` that meet a ground rectangle before any (adjusted)
    spherical light, written to ``reals``, ``ints`` from row ``m`` in the order :func:`_sample_sums` adds them
    (:class:`GroundSamples`' columns): ``reals`` the weight ``max(0, n . w) dw``, the environment table's fraction
    (``n_tab`` elevation steps) and the hit point's edge coordinates; ``ints`` the azimuth, the table's cell
    (``-1 - s`` for the local light ``s`` seen beyond the ground) and the ground. Returns the row after the last.
    Over 60 lines: one loop nest (grounds, azimuths, elevation nodes); the interval and ray tests are inline
    helpers."""
    live, live_id, cand, half, el, ce, se = scratch
    n_az = quad.cos_az.shape[0]
    n_el = quad.nodes.shape[0]
    d_phi = 2.0 * np.pi / n_az
    n_live = 0  # adjusted lights reaching below the receiver
    for s in range(scene.radii.shape[0]):
        if not unadjusted[s]:
            cx, cy, cz, r = _adjust(px, py, pz, nx, ny, nz, scene.centres[s, 0], scene.centres[s, 1],
                                    scene.centres[s, 2], scene.radii[s])
        else:  # the true sphere, culled when it holds the receiver
            cx, cy, cz, r = scene.centres[s, 0], scene.centres[s, 1], scene.centres[s, 2], scene.radii[s]
            if (cx - px) ** 2 + (cy - py) ** 2 + (cz - pz) ** 2 < r * r:
                r = 0.0
        if r > 0.0 and cy - r < py:
            live[n_live, 0], live[n_live, 1], live[n_live, 2], live[n_live, 3] = cx, cy, cz, r
            ox, oy, oz = cx - px, cy - py, cz - pz
            live[n_live, 4], live[n_live, 5], live[n_live, 6] = ox, oy, oz
            live[n_live, 7] = ox * ox + oy * oy + oz * oz - r * r
            live_id[n_live] = s
            n_live += 1
    for g in range(scene.rects.shape[0]):
        h = py - scene.rects[g, 0]
        if h <= 0.0:
            continue
        _, _, inv_u, inv_v = _rect_coordinates(px, pz, scene.rects[g])
        _node_directions(px, pz, h, nx, ny, nz, quad.cos_az, quad.sin_az, quad.nodes, scene.rects[g], half, el,
                         ce, se)
        for k in range(n_az):
            if half[k] < 0.0:
                continue
            ux, uz = quad.cos_az[k], quad.sin_az[k]
            n_cand = 0  # the lights that meet the vertical half-plane of this azimuth
            for j in range(n_live):
                ox, oz = live[j, 4], live[j, 6]
                cand[n_cand] = j  # kept by the count (no branch)
                n_cand += (ox * ux + oz * uz > -live[j, 3]) & (abs(ox * uz - oz * ux) < live[j, 3])
            for i in range(n_el):
                c_e, s_e = ce[k * n_el + i], se[k * n_el + i]
                wx, wy, wz = c_e * ux, -s_e, c_e * uz
                wgt = half[k] * quad.weights[i] * d_phi * c_e * (nx * wx + ny * wy + nz * wz)
                if wgt <= 0.0:
                    continue
                t_ground = h / s_e
                blocked, beyond = _lights_on_ray(wx, wy, wz, t_ground, live, live_id, cand, n_cand, scene.is_local)
                if blocked:
                    continue
                reals[m, 0], ints[m, 0], ints[m, 2] = wgt, k, g
                if beyond >= 0:
                    ints[m, 1], reals[m, 1] = -1 - beyond, 0.0
                else:
                    u = el[k * n_el + i] * (2.0 * n_tab / np.pi)
                    t = min(int(u), n_tab - 1)
                    ints[m, 1], reals[m, 1] = t, u - t
                ax, az = px + t_ground * wx - scene.rects[g, 1], pz + t_ground * wz - scene.rects[g, 2]
                reals[m, 2] = (ax * scene.rects[g, 3] + az * scene.rects[g, 4]) * inv_u
                reals[m, 3] = (ax * scene.rects[g, 5] + az * scene.rects[g, 6]) * inv_v
                m += 1
    return m


@numba.njit(cache=True, parallel=True)
def _ground_samples(points, normals, quad, scene, n_tab, unadjusted, capacity, count, reals, ints):
    """Per receiver ``q``, its samples (:func:`_receiver_samples`) into the rows ``q * capacity + m``, ``count[q]``
    of them."""
    n_recv = points.shape[0]
    for c in numba.prange((n_recv + _SAMPLE_CHUNK - 1) // _SAMPLE_CHUNK):
        scratch = _sample_scratch(scene.radii.shape[0], quad.cos_az.shape[0], quad.nodes.shape[0])
        for q in range(c * _SAMPLE_CHUNK, min(n_recv, (c + 1) * _SAMPLE_CHUNK)):
            m = _receiver_samples(points[q, 0], points[q, 1], points[q, 2], normals[q, 0], normals[q, 1],
                                  normals[q, 2], quad, scene, n_tab, unadjusted, scratch, reals, ints, q * capacity)
            count[q] = m - q * capacity


@numba.njit(cache=True, parallel=True)
def _compact_samples(count, capacity, offset, reals, ints, out_reals, out_ints):
    """Receiver ``q``'s ``count[q]`` rows from ``q * capacity`` to ``offset[q]`` (the samples without the gaps)."""
    for q in numba.prange(count.shape[0]):
        for m in range(count[q]):
            for j in range(reals.shape[1]):
                out_reals[offset[q] + m, j] = reals[q * capacity + m, j]
            for j in range(ints.shape[1]):
                out_ints[offset[q] + m, j] = ints[q * capacity + m, j]


@numba.njit(cache=True, inline="always")
def _sample_sums(lo, hi, reals, ints, env_table, local_radiance, texture):
    """Over the samples ``lo:hi`` in order (:class:`GroundSamples`): the weighted radiance the second pass gave them
    (the environment table's, linear in elevation, or a local light's) and the ground's texture at the hit point;
    six sums (environment, ground)."""
    e0 = e1 = e2 = 0.0
    g0 = g1 = g2 = 0.0
    for m in range(lo, hi):
        wgt = reals[m, 0]
        t = np.int64(ints[m, 1])
        if t < 0:
            s_id = -1 - t
            e0 += wgt * local_radiance[s_id, 0]
            e1 += wgt * local_radiance[s_id, 1]
            e2 += wgt * local_radiance[s_id, 2]
        else:
            k = np.int64(ints[m, 0])
            f = reals[m, 1]
            e0 += wgt * ((1.0 - f) * env_table[k, t, 0] + f * env_table[k, t + 1, 0])
            e1 += wgt * ((1.0 - f) * env_table[k, t, 1] + f * env_table[k, t + 1, 1])
            e2 += wgt * ((1.0 - f) * env_table[k, t, 2] + f * env_table[k, t + 1, 2])
        t0, t1, t2 = _texture_at(texture, np.int64(ints[m, 2]), reals[m, 2], reals[m, 3])
        g0 += wgt * t0
        g1 += wgt * t1
        g2 += wgt * t2
    return e0, e1, e2, g0, g1, g2


@numba.njit(cache=True, parallel=True)
def _ground_sample_sums(ptr, reals, ints, env_table, local_radiance, texture, out_env, out_ground):
    """Per receiver ``q`` (``out_env``, ``out_ground`` (B, 3)): :func:`_sample_sums` over its samples
    ``ptr[q]:ptr[q + 1]``."""
    for q in numba.prange(ptr.shape[0] - 1):
        e0, e1, e2, g0, g1, g2 = _sample_sums(ptr[q], ptr[q + 1], reals, ints, env_table, local_radiance, texture)
        out_env[q, 0], out_env[q, 1], out_env[q, 2] = e0, e1, e2
        out_ground[q, 0], out_ground[q, 1], out_ground[q, 2] = g0, g1, g2


@numba.njit(cache=True, parallel=True)
def _ground_light_kernel(points, normals, quad, scene, n_tab, unadjusted, out_env, out_ground):
    """:func:`_ground_samples` then :func:`_ground_sample_sums` under ``scene``'s lighting, each receiver's samples
    summed as they are made (in a task's scratch, never stored): the same sums bit for bit."""
    n_recv = points.shape[0]
    capacity = scene.rects.shape[0] * quad.cos_az.shape[0] * quad.nodes.shape[0]
    for c in numba.prange((n_recv + _SAMPLE_CHUNK - 1) // _SAMPLE_CHUNK):
        scratch = _sample_scratch(scene.radii.shape[0], quad.cos_az.shape[0], quad.nodes.shape[0])
        reals, ints = np.empty((capacity, 4)), np.empty((capacity, 3), dtype=np.int32)
        for q in range(c * _SAMPLE_CHUNK, min(n_recv, (c + 1) * _SAMPLE_CHUNK)):
            m = _receiver_samples(points[q, 0], points[q, 1], points[q, 2], normals[q, 0], normals[q, 1],
                                  normals[q, 2], quad, scene, n_tab, unadjusted, scratch, reals, ints, 0)
            e0, e1, e2, g0, g1, g2 = _sample_sums(0, m, reals, ints, scene.env_table, scene.local_radiance,
                                                  scene.texture)
            out_env[q, 0], out_env[q, 1], out_env[q, 2] = e0, e1, e2
            out_ground[q, 0], out_ground[q, 1], out_ground[q, 2] = g0, g1, g2


@numba.njit(cache=True)
def _raster_faces(uv, faces, res, ids, bary):
    """For each texel centre ``(i, j)`` (integer coordinates of ``uv (V, 2)``), the face that holds it: its vertex
    ids and barycentric weights (ids -1 where no face does)."""
    for f in range(faces.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        ax, ay, bx, by, cx, cy = uv[a, 0], uv[a, 1], uv[b, 0], uv[b, 1], uv[c, 0], uv[c, 1]
        det = (by - cy) * (ax - cx) + (cx - bx) * (ay - cy)
        if det == 0.0:
            continue
        i0 = max(int(math.ceil(min(ax, bx, cx) - 1e-9)), 0)
        i1 = min(int(math.floor(max(ax, bx, cx) + 1e-9)), res - 1)
        j0 = max(int(math.ceil(min(ay, by, cy) - 1e-9)), 0)
        j1 = min(int(math.floor(max(ay, by, cy) + 1e-9)), res - 1)
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                l0 = ((by - cy) * (i - cx) + (cx - bx) * (j - cy)) / det
                l1 = ((cy - ay) * (i - cx) + (ax - cx) * (j - cy)) / det
                l2 = 1.0 - l0 - l1
                if min(l0, l1, l2) < -1e-9:
                    continue
                ids[i, j, 0], ids[i, j, 1], ids[i, j, 2] = a, b, c
                bary[i, j, 0], bary[i, j, 1], bary[i, j, 2] = l0, l1, l2


def ground_raster(mesh, resolution: int = 128) -> tuple[np.ndarray, np.ndarray]:
    """The texels of a ground's rectangle (``resolution`` per edge over the object-space bounding box of its flat
    mesh, as :func:`ground_rectangles` spans it): ``ids (R, R, 3)`` vertex ids of the face under each texel centre
    (-1: none) and ``bary (R, R, 3)`` its barycentric weights. A texture of per-vertex values is then
    ``sum_k bary[..., k] value[ids[..., k]]``: the mesh's linear interpolation at the texel centres."""
    v = np.asarray(mesh.vertices, dtype=np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    flat = int(np.argmin(hi - lo))
    a1, a2 = [k for k in range(3) if k != flat]
    ext = np.where(hi - lo > 0, hi - lo, 1.0)
    uv = np.stack([(v[:, a1] - lo[a1]) / ext[a1], (v[:, a2] - lo[a2]) / ext[a2]], -1) * resolution - 0.5
    ids = np.full((resolution, resolution, 3), -1, dtype=np.int64)
    bary = np.zeros((resolution, resolution, 3))
    _raster_faces(np.ascontiguousarray(uv), np.ascontiguousarray(mesh.faces, dtype=np.int64), resolution, ids,
                  bary)
    return ids, bary


def ground_texture(raster, radiance) -> np.ndarray:
    """``(R, R, 3)`` exit radiance at the texel centres from the per-vertex ``radiance (V, 3)`` (0 off the mesh)."""
    ids, bary = raster
    rad = np.asarray(radiance, dtype=np.float64)
    return np.where((ids[..., 0] >= 0)[..., None], np.einsum("ijk,ijkc->ijc", bary, rad[np.maximum(ids, 0)]), 0.0)


def environment_table(env_sh, quad: GroundQuadrature, n_elevation: int = 64) -> np.ndarray:
    """``(K, T + 1, 3)`` environment radiance ``L(w)`` at the quadrature's azimuths and the elevations
    ``pi/2 t / T`` below the horizon (``T = n_elevation``), from its SH ``(N*N, 3)``. The last few tables are kept
    (keyed by the SH's and the azimuths' bytes: a frame asks once per receiving object); the returned array is
    read-only."""
    env = np.ascontiguousarray(env_sh, dtype=np.float64)

    def make():
        e = 0.5 * np.pi * np.arange(n_elevation + 1) / n_elevation
        ce, se = np.cos(e), np.sin(e)
        dirs = np.stack([quad.cos_az[:, None] * ce[None], np.broadcast_to(-se, (len(quad.cos_az), len(e))),
                         quad.sin_az[:, None] * ce[None]], -1)
        return np.ascontiguousarray(sh.basis(dirs.reshape(-1, 3), math.isqrt(env.shape[0])) @ env).reshape(
            len(quad.cos_az), n_elevation + 1, -1)

    key = (env.shape, env.tobytes(), quad.cos_az.tobytes(), quad.sin_az.tobytes(), int(n_elevation))
    return kept_by_key(_ENV_TABLES, key, make)


#: The last environment tables (:func:`environment_table`).
_ENV_TABLES: dict = {}


def ground_light(points, normals, rectangles, textures, env_sh, centres=(), radii=(), local_radiance=None, *,
                 n_azimuth: int = 24, n_elevation: int = 6, unadjusted=None) -> tuple[np.ndarray, np.ndarray]:
    """The ground's part of the light at receivers above it: what it hides and what it reflects (an extension).

    Parameters
    ----------
    points, normals : (B, 3) float
        Receivers (world space) and their unit normals.
    rectangles : (G, 7) float
        :func:`ground_rectangles`.
    textures : (G, R, R, 3) float
        Exit radiance over each rectangle (:func:`ground_texture`).
    env_sh : (N*N, 3) float
        Environment radiance.
    centres, radii : (S, 3), (S,) float
        Spherical lights (world space) as opaque blockers, adjusted per receiver as in the second pass.
    unadjusted : (S,) bool, optional
        Lights tested as the true spheres (culled only where they hold the receiver), not adjusted: those the
        direct light takes exactly (the option ``near_blockers``). Default none.
    local_radiance : (S, 3) float, optional
        Constant radiance of the local lights (NaN rows: an object's light).
    n_azimuth, n_elevation : int
        Azimuths and Gauss-Legendre elevation nodes per azimuth (24 x 6: the default's quadrature error is
        1-4 % of each integral on the fidelity scenes, measured against 128 x 32; ``docs/notes/spherelights.md``).

    Returns
    -------
    hidden : (B, 3) float64
        ``int_H max(0, n.w) L_2(w) dw`` over the directions ``H`` that meet a ground before any light, ``L_2`` the
        radiance the second pass gives them: the environment's, or a local light's lying beyond the ground. To
        subtract from the direct irradiance.
    reflected : (B, 3) float64
        ``int_H max(0, n.w) L_g(x(w)) dw``, ``L_g`` the ground's exit radiance at the hit point: to add to the
        indirect irradiance.

    Notes
    -----
    Per azimuth the elevations whose ray meets the rectangle and lies above the receiver's tangent plane form
    one interval, found exactly (slab test, clamped cosine), and carry the Gauss-Legendre nodes; the rule is
    then exact for a smooth integrand up to the azimuth sum's error (uniform, the azimuths turn with the first
    ground). The lights block by ray-sphere tests (binary), not by the SH visibility. A receiver at or below a
    ground's height gets nothing from it; grounds seen through one another are each counted.
    """
    p, n, rects, c, r, is_local, exact, quad = _sample_inputs(points, normals, rectangles, centres, radii,
                                                              local_radiance, n_azimuth, n_elevation, unadjusted)
    _check_textures(textures, len(rects))
    hidden, reflected = np.zeros((len(p), 3)), np.zeros((len(p), 3))
    if len(p) == 0 or len(rects) == 0:
        return hidden, reflected
    scene = GroundScene(rects, np.ascontiguousarray(textures, dtype=np.float64), c, r,
                        _local_rows(local_radiance, len(r)), is_local, environment_table(env_sh, quad, _ENV_TABLE))
    _ground_light_kernel(p, n, quad, scene, _ENV_TABLE, exact, hidden, reflected)
    return hidden, reflected


def _local_rows(local_radiance, n_lights: int) -> np.ndarray:
    """The local lights' radiance ``(S, 3)`` the sums read (an object's light, a NaN row, reads as 0)."""
    if local_radiance is None:
        return np.zeros((n_lights, 3))
    return np.ascontiguousarray(np.nan_to_num(np.asarray(local_radiance, np.float64).reshape(-1, 3)))


def _check_textures(textures, n_rects: int) -> None:
    tex_shape = np.shape(textures)
    if len(tex_shape) != 4 or tex_shape[0] != n_rects or tex_shape[1] != tex_shape[2] or tex_shape[3] != 3 \
            or tex_shape[1] < 1:
        raise ValueError(f"textures must have shape (G, R, R, 3) with G = {n_rects} rectangles, got {tex_shape}")


#: Elevation steps of the environment table the ground's samples read (:func:`environment_table`).
_ENV_TABLE = 64
#: Bytes of the scratch of :func:`ground_samples` (its receivers' samples at most, before they are compacted): under
#: 4 MiB, as ``_WEIGHT_BLOCK_BYTES`` (a larger fresh array is backed by huge pages, whose faults cost more).
_SAMPLE_BLOCK_BYTES = 4 << 20


class GroundSamples(NamedTuple):
    """The quadrature directions of :func:`ground_light` that meet a ground before any light (the geometry, from
    :func:`ground_samples`; the lighting is :func:`ground_sample_sums`'): receiver ``q``'s samples ``ptr[q]:ptr[q +
    1]`` in the order they are summed, each with ``reals``: its weight ``max(0, n . w) dw``, the environment table's
    fraction between elevation cells, the hit point's edge coordinates ``a, b`` in ``[-1, 1]^2``; and ``ints``: the
    quadrature's azimuth, the table's elevation cell (``-1 - s``: the local light ``s`` seen beyond the ground), the
    ground hit."""

    quad: GroundQuadrature
    n_grounds: int
    ptr: np.ndarray  # (B + 1,) int64
    reals: np.ndarray  # (N, 4) float64
    ints: np.ndarray  # (N, 3) int32


def ground_samples(points, normals, rectangles, centres=(), radii=(), local_radiance=None, *, n_azimuth: int = 24,
                   n_elevation: int = 6, unadjusted=None) -> GroundSamples:
    """:class:`GroundSamples` of :func:`ground_light` (arguments as there; ``local_radiance``: only which lights
    are local, its NaN rows, matters here)."""
    p, n, rects, c, r, is_local, exact, quad = _sample_inputs(points, normals, rectangles, centres, radii,
                                                              local_radiance, n_azimuth, n_elevation, unadjusted)
    capacity = len(rects) * int(n_azimuth) * int(n_elevation)  # a receiver's samples at most
    count = np.zeros(len(p), dtype=np.int64)
    scene = GroundScene(rects, np.zeros((len(rects), 1, 1, 3)), c, r, np.zeros((len(r), 3)), is_local,
                        np.zeros((int(n_azimuth), _ENV_TABLE + 1, 3)))
    block = max(1, min(len(p), _SAMPLE_BLOCK_BYTES // (44 * max(capacity, 1))))  # receivers per call
    reals, ints = np.empty((block * capacity, 4)), np.empty((block * capacity, 3), dtype=np.int32)  # one scratch
    parts = []
    for start in range(0, len(p) if len(rects) else 0, block):
        stop = min(len(p), start + block)
        _ground_samples(p[start:stop], n[start:stop], quad, scene, _ENV_TABLE, exact, capacity, count[start:stop],
                        reals, ints)
        offset = np.zeros(stop - start + 1, dtype=np.int64)
        np.cumsum(count[start:stop], out=offset[1:])
        part = np.empty((offset[-1], 4)), np.empty((offset[-1], 3), dtype=np.int32)
        _compact_samples(count[start:stop], capacity, offset, reals, ints, *part)
        parts.append(part)
    ptr = np.zeros(len(p) + 1, dtype=np.int64)
    np.cumsum(count, out=ptr[1:])
    if len(parts) == 1:
        return GroundSamples(quad, len(rects), ptr, *parts[0])
    return GroundSamples(quad, len(rects), ptr, np.concatenate([x for x, _ in parts] or [np.zeros((0, 4))]),
                         np.concatenate([x for _, x in parts] or [np.zeros((0, 3), dtype=np.int32)]))


def _sample_inputs(points, normals, rectangles, centres, radii, local_radiance, n_azimuth, n_elevation, unadjusted):
    """The arguments of :func:`ground_samples` checked and coerced: points, unit normals, rectangles, centres, radii,
    which lights are local, which unadjusted, and the quadrature."""
    from prtlab._validate import check_int

    check_int(n_azimuth, "n_azimuth", 1)
    check_int(n_elevation, "n_elevation", 1)
    p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    n = np.ascontiguousarray(n / np.linalg.norm(n, axis=1, keepdims=True)) if len(n) else n
    rects = np.ascontiguousarray(rectangles, dtype=np.float64).reshape(-1, 7)
    c = np.ascontiguousarray(centres, dtype=np.float64).reshape(-1, 3)
    r = np.ascontiguousarray(radii, dtype=np.float64).reshape(-1)
    loc = np.full((len(r), 3), np.nan) if local_radiance is None else np.asarray(local_radiance, np.float64)
    is_local = np.ascontiguousarray(~np.isnan(loc).any(axis=1))
    exact = np.zeros(len(r), dtype=bool) if unadjusted is None else np.asarray(unadjusted, dtype=bool).reshape(-1)
    if exact.shape != (len(r),):
        raise ValueError(f"unadjusted must be a bool array of shape ({len(r)},), got {np.shape(unadjusted)}")
    phi0 = math.atan2(rects[0, 4], rects[0, 3]) if len(rects) else 0.0
    quad = ground_quadrature(int(n_azimuth), int(n_elevation), phi0)
    return p, n, rects, c, r, is_local, np.ascontiguousarray(exact), quad


#: Relative margin of :func:`ground_samples_update`'s ray tests, of the quantities compared: far above the rounding
#: in which its tests could differ from the kernel's (none: they are the same expressions), far below what matters.
_UPDATE_MARGIN = 1e-9


def ground_samples_update(kept: GroundSamples, kept_lights, points, normals, rectangles, centres=(), radii=(),
                          local_radiance=None, *, n_azimuth: int = 24, n_elevation: int = 6, unadjusted=None):
    """:func:`ground_samples` (arguments as there) from ``kept``, the samples of the same receivers and rectangles
    under other lights ``kept_lights = (centres, radii, local_radiance, unadjusted)`` (the same number of them):
    ``(samples, counts)``, ``samples`` equal to a fresh call's bit for bit, or None when ``kept`` cannot serve
    (another number of lights, receivers or grounds, another quadrature). The caller vouches that ``points``,
    ``normals`` and ``rectangles`` are ``kept``'s (it compares them).

    A receiver's samples depend on a light only through the sample rays it meets: per ray, whether a light is met
    before the ground (then no sample) and else the nearest local light met beyond it (a light met by no ray is
    skipped by every test; neither answer depends on the lights' order). So a receiver keeps its samples when every
    changed light (centre, radius, local or unadjusted differing) gives each of its sample rays the same answer in
    its old and its new form: met before the ground by both, or by neither (an object's light), or met by neither
    (a local light). :func:`_reached` tests that with the kernel's own expressions (the adjusted spheres, the
    azimuths' candidates, the elevation nodes and the ray tests) and counts any answer within
    :data:`_UPDATE_MARGIN` of changing as a change; the other receivers are recomputed (:func:`ground_samples` on
    them alone: a receiver's samples depend on nothing but its own point and normal) and the rows merged in receiver
    order. ``counts``: ``{"receivers", "receivers_recomputed", "lights_changed"}``."""
    p, n, rects, c, r, is_local, exact, quad = _sample_inputs(points, normals, rectangles, centres, radii,
                                                              local_radiance, n_azimuth, n_elevation, unadjusted)
    old_c, old_r, old_local, old_exact = kept_lights
    old_c = np.asarray(old_c, dtype=np.float64).reshape(-1, 3)
    old_r = np.asarray(old_r, dtype=np.float64).reshape(-1)
    if (len(old_r) != len(r) or len(kept.ptr) != len(p) + 1 or kept.n_grounds != len(rects)
            or kept.quad is not quad):
        return None
    old_loc = (np.zeros(len(r), dtype=bool) if old_local is None
               else ~np.isnan(np.asarray(old_local, np.float64).reshape(-1, 3)).any(axis=1))
    old_exact = (np.zeros(len(r), dtype=bool) if old_exact is None
                 else np.asarray(old_exact, dtype=bool).reshape(-1))
    same = ((old_c.view(np.uint64) == c.view(np.uint64)).all(axis=1) & (old_r.view(np.uint64) == r.view(np.uint64))
            & (old_loc == is_local) & (old_exact == exact))
    changed = np.nonzero(~same)[0]
    counts = {"receivers": len(p), "receivers_recomputed": 0, "lights_changed": len(changed)}
    if not len(changed):
        return kept, counts
    spheres = np.ascontiguousarray(np.stack([np.concatenate([old_c[changed], old_r[changed, None]], axis=1),
                                             np.concatenate([c[changed], r[changed, None]], axis=1)]))
    flags = np.ascontiguousarray(np.stack([np.stack([old_exact[changed], old_loc[changed]], axis=1),
                                           np.stack([exact[changed], is_local[changed]], axis=1)]))
    todo = np.zeros(len(p), dtype=bool)
    if len(p) and len(rects):
        _reached(p, n, quad, rects, spheres, flags, _UPDATE_MARGIN, todo)
    idx = np.nonzero(todo)[0]
    counts["receivers_recomputed"] = len(idx)
    raw = np.asarray(normals, dtype=np.float64).reshape(-1, 3)  # the subset normalised as a whole call does
    sub = ground_samples(p[idx], raw[idx], rects, c, r, local_radiance, n_azimuth=n_azimuth, n_elevation=n_elevation,
                         unadjusted=unadjusted)
    count = np.diff(kept.ptr)
    count[idx] = np.diff(sub.ptr)
    ptr = np.zeros(len(p) + 1, dtype=np.int64)
    np.cumsum(count, out=ptr[1:])
    source = np.full(len(p), -1, dtype=np.int64)
    source[idx] = np.arange(len(idx))
    reals, ints = np.empty((ptr[-1], 4)), np.empty((ptr[-1], 3), dtype=np.int32)
    _merge_samples(source, kept.ptr, kept.reals, kept.ints, sub.ptr, sub.reals, sub.ints, ptr, reals, ints)
    return GroundSamples(quad, len(rects), ptr, reals, ints), counts


@numba.njit(cache=True, parallel=True)
def _merge_samples(source, kept_ptr, kept_reals, kept_ints, sub_ptr, sub_reals, sub_ints, ptr, reals, ints):
    """Receiver ``q``'s rows into ``ptr[q]:ptr[q + 1]``: the kept ones, or (``source[q] >= 0``) those of the
    recomputed receiver ``source[q]``; runs of kept receivers copied as one block each (rows are contiguous)."""
    n_recv = source.shape[0]
    n_r, n_i = reals.shape[1], ints.shape[1]
    out_r, out_i = reals.reshape(-1), ints.reshape(-1)
    kept_r, kept_i = kept_reals.reshape(-1), kept_ints.reshape(-1)
    sub_r, sub_i = sub_reals.reshape(-1), sub_ints.reshape(-1)
    n_blocks = min(n_recv, 64)
    for block in numba.prange(n_blocks):
        q = block * n_recv // n_blocks
        stop = (block + 1) * n_recv // n_blocks
        while q < stop:
            a = ptr[q]
            if source[q] >= 0:
                b, s = ptr[q + 1], sub_ptr[source[q]]
                out_r[n_r * a:n_r * b] = sub_r[n_r * s:n_r * (s + b - a)]
                out_i[n_i * a:n_i * b] = sub_i[n_i * s:n_i * (s + b - a)]
                q += 1
                continue
            e = q + 1  # a run of kept receivers: their rows follow one another in kept as here
            while e < stop and source[e] < 0:
                e += 1
            b, s = ptr[e], kept_ptr[q]
            out_r[n_r * a:n_r * b] = kept_r[n_r * s:n_r * (s + b - a)]
            out_i[n_i * a:n_i * b] = kept_i[n_i * s:n_i * (s + b - a)]
            q = e


@numba.njit(cache=True, inline="always")
def _live_sphere(px, py, pz, nx, ny, nz, cx, cy, cz, r, unadjusted):
    """The sphere :func:`_ground_samples` tests at the receiver ``p, n`` (adjusted, or culled when it holds the
    receiver); radius 0: not live (culled, or wholly above the receiver)."""
    if not unadjusted:
        cx, cy, cz, r = _adjust(px, py, pz, nx, ny, nz, cx, cy, cz, r)
    elif (cx - px) ** 2 + (cy - py) ** 2 + (cz - pz) ** 2 < r * r:
        r = 0.0
    if not (r > 0.0 and cy - r < py):
        r = 0.0
    return cx, cy, cz, r


@numba.njit(cache=True, inline="always")
def _ray_answer(px, py, pz, wx, wy, wz, t_ground, cx, cy, cz, r, margin):
    """What the ray ``p + t w`` meets of the sphere in :func:`_lights_on_ray`'s test: 0 nothing, 1 the sphere
    before ``t_ground``, 2 beyond it; -1 when a quantity it compares lies within ``margin`` (relative) of its
    bound."""
    if r <= 0.0:
        return 0
    ox, oy, oz = cx - px, cy - py, cz - pz
    bb = ox * wx + oy * wy + oz * wz
    oo = ox * ox + oy * oy + oz * oz
    disc = bb * bb - (oo - r * r)
    tol_b = margin * (math.sqrt(oo) + r)
    tol_d = margin * (oo + r * r + bb * bb)
    if bb < -tol_b or disc < -tol_d:
        return 0
    if bb <= tol_b or disc <= tol_d:
        return -1
    t_hit = bb - math.sqrt(disc)
    tol_t = margin * (abs(t_ground) + abs(bb) + math.sqrt(oo) + r)
    if t_hit < t_ground - tol_t:
        return 1
    if t_hit > t_ground + tol_t:
        return 2
    return -1


@numba.njit(cache=True, parallel=True)
def _reached(points, normals, quad, rects, spheres, flags, margin, out):
    """``out[q]``: a changed light may give receiver ``q``'s samples another answer (the test of
    :func:`ground_samples_update`): ``spheres (2, M, 4)`` the changed lights' old and new centre and radius,
    ``flags (2, M, 2)`` whether unadjusted and local; the azimuths, elevation nodes and rays as
    :func:`_ground_samples` makes them (the same expressions), the rays below the tangent plane included."""
    n_az = quad.cos_az.shape[0]
    n_el = quad.nodes.shape[0]
    n_ch = spheres.shape[1]
    for q in numba.prange(points.shape[0]):
        px, py, pz = points[q, 0], points[q, 1], points[q, 2]
        nx, ny, nz = normals[q, 0], normals[q, 1], normals[q, 2]
        live = np.empty((2, n_ch, 4))
        any_live = False
        for f in range(2):
            for j in range(n_ch):
                cx, cy, cz, r = _live_sphere(px, py, pz, nx, ny, nz, spheres[f, j, 0], spheres[f, j, 1],
                                             spheres[f, j, 2], spheres[f, j, 3], flags[f, j, 0])
                live[f, j, 0], live[f, j, 1], live[f, j, 2], live[f, j, 3] = cx, cy, cz, r
                any_live = any_live or r > 0.0
        reached = False
        if not any_live:
            out[q] = False
            continue
        near = np.zeros(n_az, dtype=np.bool_)  # a live sphere (widened by the margin) meets the azimuth's half-plane
        for k in range(n_az):
            ux, uz = quad.cos_az[k], quad.sin_az[k]
            for f in range(2):
                for j in range(n_ch):
                    r = live[f, j, 3] * (1.0 + margin)
                    ox, oz = live[f, j, 0] - px, live[f, j, 2] - pz
                    if live[f, j, 3] > 0.0 and ox * ux + oz * uz > -r and abs(ox * uz - oz * ux) < r:
                        near[k] = True
        if not near.any():
            out[q] = False
            continue
        half, el, ce, se = np.empty(n_az), np.empty(n_az * n_el), np.empty(n_az * n_el), np.empty(n_az * n_el)
        for g in range(rects.shape[0]):
            h = py - rects[g, 0]
            if h <= 0.0:
                continue
            _node_directions(px, pz, h, nx, ny, nz, quad.cos_az, quad.sin_az, quad.nodes, rects[g], half, el, ce, se)
            for k in range(n_az):
                if not near[k] or half[k] < 0.0:
                    continue
                ux, uz = quad.cos_az[k], quad.sin_az[k]
                for i in range(n_el):
                    wx, wy, wz = ce[k * n_el + i] * ux, -se[k * n_el + i], ce[k * n_el + i] * uz
                    t_ground = h / se[k * n_el + i]
                    for j in range(n_ch):
                        a0 = _ray_answer(px, py, pz, wx, wy, wz, t_ground, live[0, j, 0], live[0, j, 1],
                                         live[0, j, 2], live[0, j, 3], margin)
                        a1 = _ray_answer(px, py, pz, wx, wy, wz, t_ground, live[1, j, 0], live[1, j, 1],
                                         live[1, j, 2], live[1, j, 3], margin)
                        if flags[0, j, 1] or flags[1, j, 1]:  # a local light: met at all, in either form
                            changes = a0 != 0 or a1 != 0
                            changes = changes and not (a0 == 1 and a1 == 1)
                        else:  # an object's light: met before the ground or not
                            changes = a0 < 0 or a1 < 0 or (a0 == 1) != (a1 == 1)
                        if changes:
                            reached = True
                            break
                    if reached:
                        break
                if reached:
                    break
            if reached:
                break
        out[q] = reached


def ground_sample_sums(samples: GroundSamples, textures, env_sh, local_radiance=None) -> tuple[np.ndarray, np.ndarray]:
    """``(hidden, reflected)`` of :func:`ground_light` from its geometry ``samples`` (:func:`ground_samples`) under
    the grounds' exit radiance ``textures (G, R, R, 3)``, the environment ``env_sh (N*N, 3)`` and the local lights'
    radiance ``local_radiance (S, 3)`` (NaN rows: an object's light)."""
    _check_textures(textures, samples.n_grounds)
    n_recv = len(samples.ptr) - 1
    hidden, reflected = np.zeros((n_recv, 3)), np.zeros((n_recv, 3))
    if n_recv == 0 or samples.n_grounds == 0:
        return hidden, reflected
    _ground_sample_sums(samples.ptr, samples.reals, samples.ints, environment_table(env_sh, samples.quad, _ENV_TABLE),
                        _local_rows(local_radiance, 0), np.ascontiguousarray(textures, dtype=np.float64),
                        hidden, reflected)
    return hidden, reflected


def _winding_numbers(points, vertices, faces, method: str = "numba") -> np.ndarray:
    """``(P,)`` generalised winding numbers of a triangle mesh at ``points (P, 3)`` (1 inside a closed, outward
    oriented mesh, 0 outside; Van Oosterom and Strackee's solid angle per triangle, summed over ``4 pi``). A point
    in a face's plane inside the face (``num = 0``, whose sign would pick ``+pi`` or ``-pi``) takes ``+pi``, so a
    point on a closed surface gets 1 (covered), not 0 or 1 by the sign of a rounded zero.
    ``method="numba"``: :func:`_winding_kernel` (parallel over the points, the faces summed in order);
    ``"reference"``: numpy, the specification (its sums pairwise: the two agree to rounding)."""
    if method == "numba":
        out = np.empty(len(points))
        _winding_kernel(np.ascontiguousarray(points, dtype=np.float64),
                        np.ascontiguousarray(np.asarray(vertices, dtype=np.float64)[faces]), out)
        return out
    tri = vertices[faces]  # (F, 3, 3)
    out = np.zeros(len(points))
    block = max(1, (1 << 21) // max(len(faces), 1))
    for s in range(0, len(points), block):
        d = tri[None] - points[s:s + block, None, None, :]  # (B, F, 3, 3)
        a, b, c = d[:, :, 0], d[:, :, 1], d[:, :, 2]
        la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
        num = np.einsum("pfi,pfi->pf", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("pfi,pfi->pf", a, b) * lc + np.einsum("pfi,pfi->pf", a, c) * lb
               + np.einsum("pfi,pfi->pf", b, c) * la)
        angle = np.arctan2(num, den)
        angle = np.where(num == 0.0, np.abs(angle), angle)  # a point in a face's plane: +pi inside it, not -0.0's -pi
        out[s:s + block] = angle.sum(axis=1) / (2.0 * np.pi)
    return out


@numba.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _winding_kernel(points, tri, out):
    """:func:`_winding_numbers` at each point of ``points (P, 3)`` over the triangles ``tri (F, 3, 3)``."""
    for q in numba.prange(points.shape[0]):
        px, py, pz = points[q, 0], points[q, 1], points[q, 2]
        total = 0.0
        for f in range(tri.shape[0]):
            ax, ay, az = tri[f, 0, 0] - px, tri[f, 0, 1] - py, tri[f, 0, 2] - pz
            bx, by, bz = tri[f, 1, 0] - px, tri[f, 1, 1] - py, tri[f, 1, 2] - pz
            cx, cy, cz = tri[f, 2, 0] - px, tri[f, 2, 1] - py, tri[f, 2, 2] - pz
            la = math.sqrt(ax * ax + ay * ay + az * az)
            lb = math.sqrt(bx * bx + by * by + bz * bz)
            lc = math.sqrt(cx * cx + cy * cy + cz * cz)
            num = ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)
            den = (la * lb * lc + (ax * bx + ay * by + az * bz) * lc + (ax * cx + ay * cy + az * cz) * lb
                   + (bx * cx + by * cy + bz * cz) * la)
            angle = math.atan2(num, den)
            total += abs(angle) if num == 0.0 else angle  # in the face's plane: the +0.0 side (see the tier)
        out[q] = total / (2.0 * np.pi)


def covered_texels(rectangle, resolution: int, meshes) -> np.ndarray:
    """``(R, R)`` bool: the texel centres of a ground rectangle (a :func:`ground_rectangles` row; ``R =
    resolution`` cells per edge, centres at ``c + a u + b v`` with ``a, b = -1 + (i + 1/2) 2 / R``, the layout
    :func:`ground_sample_sums` reads) that an object covers: inside a closed mesh resting on or sunk into the ground
    or on its surface (a winding number above ``1/2 - 1e-6``; tested just above the ground, at ``1e-6`` of the
    rectangle's size).

    Parameters
    ----------
    rectangle : (7,) float
    resolution : int
    meshes : iterable of ((V, 3) float, (F, 3) int)
        World vertices and faces of closed, outward-oriented meshes (other meshes give meaningless answers).
    """
    y0, cx, cz, ux, uz, vx, vz = (float(x) for x in np.asarray(rectangle, dtype=np.float64).reshape(7))
    k = int(resolution)
    a = -1.0 + (np.arange(k) + 0.5) * (2.0 / k)
    aa, bb = np.meshgrid(a, a, indexing="ij")
    size = 2.0 * max(math.hypot(ux, uz), math.hypot(vx, vz), 1e-300)
    lift = 1e-6 * size
    pts = np.stack([cx + aa * ux + bb * vx, np.full_like(aa, y0 + lift), cz + aa * uz + bb * vz], -1).reshape(-1, 3)
    covered = np.zeros(len(pts), dtype=bool)
    for verts, faces in meshes:
        verts = np.asarray(verts, dtype=np.float64).reshape(-1, 3)
        faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
        if len(faces) == 0 or verts[:, 1].min() > y0 + lift:
            continue  # above the ground: it covers nothing
        fy = verts[faces, 1]  # a point inside a closed mesh lies between faces that span its height, in x and z
        crossing = faces[(fy.min(axis=1) <= y0 + lift) & (fy.max(axis=1) >= y0 + lift)]
        if len(crossing) == 0:
            continue
        lo, hi = verts[crossing].reshape(-1, 3).min(axis=0), verts[crossing].reshape(-1, 3).max(axis=0)
        near = ~covered & (pts[:, 0] >= lo[0]) & (pts[:, 0] <= hi[0]) & (pts[:, 2] >= lo[2]) & (pts[:, 2] <= hi[2])
        idx = np.nonzero(near)[0]
        if len(idx):
            # on the surface the winding number is 1/2 up to rounding: a texel centre there counts as covered
            covered[idx] = _winding_numbers(pts[idx], verts, faces) > 0.5 - 1e-6
    return covered.reshape(k, k)


def covered_points(points, vertices, faces) -> np.ndarray:
    """``(P,)`` bool: which ``points`` lie inside (or on) the closed mesh ``(vertices, faces)``: a winding number
    above ``1/2 - 1e-6``, as :func:`covered_texels` decides for its texel centres."""
    return _winding_numbers(np.asarray(points, dtype=np.float64).reshape(-1, 3),
                            np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64)) > 0.5 - 1e-6


def fill_covered_vertices(values, edges, covered) -> np.ndarray:
    """Per-vertex ``values (V, C)`` whose ``covered (V,)`` vertices take the mean of their already known neighbours
    along ``edges (E, 2)``, ring by ring from the uncovered ones inward (:func:`fill_covered` on a mesh); the others
    unchanged, and a vertex with no known neighbour at all left as it is."""
    out = np.array(values, dtype=np.float64)
    known = ~np.asarray(covered, dtype=bool)
    if known.all() or not known.any():
        return out
    a, b = np.asarray(edges, dtype=np.int64).T
    while True:
        count = np.bincount(a, weights=known[b], minlength=len(out)) + np.bincount(b, weights=known[a],
                                                                                    minlength=len(out))
        ready = ~known & (count > 0)
        if not ready.any():
            return out
        total = np.zeros_like(out)
        np.add.at(total, a, np.where(known[b, None], out[b], 0.0))
        np.add.at(total, b, np.where(known[a, None], out[a], 0.0))
        out[ready] = total[ready] / count[ready, None]
        known = known | ready


def fill_covered(texture, covered) -> np.ndarray:
    """A ground texture ``(R, R, C)`` whose ``covered (R, R)`` texels (:func:`covered_texels`) take their uncovered
    neighbours' values: ring by ring from the footprint's edge inward, each texel the mean of its already known
    8-neighbours (the others unchanged, bit for bit).

    The covered ground is never seen; what a receiver beside the object sees is the ground at the footprint's
    edge, and the bilinear lookup there reads the texels on both sides of the edge, so a covered texel must hold the
    light just outside it, not its own darkness. A texture covered everywhere is returned unchanged.
    """
    tex = np.array(texture, dtype=np.float64)
    cov = np.asarray(covered, dtype=bool)
    if cov.shape != tex.shape[:2]:
        raise ValueError(f"covered must have shape {tex.shape[:2]} (the texture's first two axes), got {cov.shape}")
    known = ~cov
    if known.all() or not known.any():
        return tex
    r0, r1 = tex.shape[:2]
    while not known.all():
        pad_k = np.pad(known, 1)
        pad_v = np.pad(np.where(known[..., None], tex, 0.0), ((1, 1), (1, 1), (0, 0)))
        count = np.zeros((r0, r1))
        total = np.zeros(tex.shape)
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                if di or dj:
                    count += pad_k[1 + di:1 + di + r0, 1 + dj:1 + dj + r1]
                    total += pad_v[1 + di:1 + di + r0, 1 + dj:1 + dj + r1]
        ring = ~known & (count > 0)
        tex[ring] = total[ring] / count[ring][:, None]
        known = known | ring
    return tex

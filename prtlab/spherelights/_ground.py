"""The ground as an occluder of the environment for the first pass (an extension of Guerrero et al. 2008).

In the paper the ground plane only receives: it neither reflects nor blocks.
A reference renderer (Mitsuba, or :mod:`prtlab.reference`) lets the ground
hide the lower environment from the objects resting on it, so with the
paper's first pass the undersides of the objects are lit from below and
over-light the ground (measured: indirect light on the ground 57-83 % off).
This module hides, from each first-pass surface sample, exactly the
directions in which the ground's rectangle lies:

.. math:: \\mathbf T_q = P_n\\big(L\\, \\max(0, n_q\\cdot\\omega)\\big)
          - P_n\\big(L\\, G_q\\, \\max(0, n_q\\cdot\\omega)\\big),

``G_q(w) = 1`` where the ray ``q + t w`` hits a ground rectangle. The second
term is a quadrature over a fixed product grid of the lower hemisphere
(Gauss-Legendre in elevation, uniform in azimuth), written as one matrix
product ``W @ A`` with ``W[q, j] = w_j G_q(w_j) max(0, n_q . w_j)`` (a numba
kernel) and ``A[j] = L(w_j) y(w_j)``. A ground is a horizontal, flat,
receiving-only object (all world vertices at one height, normals ``+Y``),
represented by its height and a rectangle in ``x, z`` (centre and two half
edges: the object-space bounding box of its mesh, placed by its transform, so
a rotated ground stays the same rectangle).

Measured figures: ``docs/notes/spherelights.md``.
"""

from __future__ import annotations

import functools
import math

import numba
import numpy as np

from prtlab import sh

__all__ = ["ground_rectangles", "ground_blocked_transfer"]


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
    rows = []
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
        rows.append([v[0, 1], centre[0], centre[2], u[0], u[2], w[0], w[2]])
    return np.asarray(rows, dtype=np.float64).reshape(-1, 7)


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


@numba.njit(cache=True, parallel=True)
def _ground_weights(points, normals, dirs, weights, rects, out):
    """out[q, j] = weights[j] * hit(q, j) * max(0, n_q . d_j); hit: the ray from q along d_j meets a rectangle."""
    n_pts = points.shape[0]
    n_dir = dirs.shape[0]
    for q in numba.prange(n_pts):
        px, py, pz = points[q, 0], points[q, 1], points[q, 2]
        for j in range(n_dir):
            out[q, j] = 0.0
            c = normals[q, 0] * dirs[j, 0] + normals[q, 1] * dirs[j, 1] + normals[q, 2] * dirs[j, 2]
            if c <= 0.0:
                continue
            for g in range(rects.shape[0]):
                h = py - rects[g, 0]
                if h <= 0.0:
                    continue
                t = h / -dirs[j, 1]
                dx = px + t * dirs[j, 0] - rects[g, 1]
                dz = pz + t * dirs[j, 2] - rects[g, 2]
                a = (dx * rects[g, 3] + dz * rects[g, 4]) / (rects[g, 3] ** 2 + rects[g, 4] ** 2)
                b = (dx * rects[g, 5] + dz * rects[g, 6]) / (rects[g, 5] ** 2 + rects[g, 6] ** 2)
                if abs(a) <= 1.0 and abs(b) <= 1.0:
                    out[q, j] = weights[j] * c
                    break


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


def ground_blocked_transfer(points, normals, env_sh, rectangles, *, n_azimuth: int = 128, n_elevation: int = 32,
                            method: str = "numba", order: int | None = None) -> np.ndarray:
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
        Tier of the weight matrix ``W``.
    order : int, optional
        Order ``n`` of the result (default: ``N``).

    Returns
    -------
    t : (B, n*n, C) float64
        To subtract from :func:`prtlab.spherelights.environment_transfer`.

    Notes
    -----
    ``t_q[k] = sum_j w_j G_q(w_j) max(0, n_q . w_j) L(w_j) y_k(w_j)`` with ``L`` the order-``n``
    environment; the quadrature error comes from the step of ``G_q`` at the ground's edge and the
    kink of the clamped cosine (first order in the grid spacing).
    """
    if method not in ("numba", "reference"):
        raise ValueError(f"method must be 'numba' or 'reference', got {method!r}")
    p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    n = np.ascontiguousarray(normals, dtype=np.float64).reshape(-1, 3)
    env = np.asarray(env_sh, dtype=np.float64)
    rects = np.ascontiguousarray(rectangles, dtype=np.float64).reshape(-1, 7)
    n_env = math.isqrt(env.shape[0])
    order = n_env if order is None else int(order)
    out = np.zeros((p.shape[0], order * order, env.shape[1]))
    if p.shape[0] == 0 or rects.shape[0] == 0:
        return out
    dirs, weights = _lower_hemisphere_grid(int(n_azimuth), int(n_elevation))
    # azimuths measured from the first ground's u edge: the result turns with the scene about +Y
    phi0 = math.atan2(rects[0, 4], rects[0, 3])
    c0, s0 = math.cos(phi0), math.sin(phi0)
    dirs = np.stack([c0 * dirs[:, 0] - s0 * dirs[:, 2], dirs[:, 1], s0 * dirs[:, 0] + c0 * dirs[:, 2]], -1)
    y = sh.basis(dirs, max(order, n_env))
    a = (y[:, : order * order, None] * (y[:, : n_env * n_env] @ env)[:, None, :]).reshape(dirs.shape[0], -1)
    if method == "reference":
        w = _ground_weights_reference(p, n, dirs, weights, rects)
    else:
        w = np.empty((p.shape[0], dirs.shape[0]))
        _ground_weights(p, n, np.ascontiguousarray(dirs), np.ascontiguousarray(weights), rects, w)
    return (w @ a).reshape(out.shape)

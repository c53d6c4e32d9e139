"""Incident radiance of local area lights in SH at receiver points (the source radiance of Zhou et al. 2005).

Zhou et al. precompute a *source radiance field* (SRF): the SH of the radiance
arriving from a local light at points on concentric spheres around it. On a
CPU the same quantity is cheap to evaluate exactly at each receiver vertex
per frame: the light is a parallelogram (``center + s u + t v``,
``s, t in [-1, 1]``) emitting ``radiance`` on the side of ``cross(u, v)``, and
:func:`area_light_sh` integrates over its area (a Gauss-Legendre rule in
``(s, t)``), so lights move, turn and resize freely without a precomputed
field; the lookup of a sampled field (:func:`interpolate_field`)
would replace it unchanged. Occlusion is not included (multiply by the
visibility of :mod:`._direct`).

Point lights (:func:`point_light_direct`) are an exact delta: no field, no SH
projection of the light. Their visibility is needed in one direction only, so
they are routed through the exact or all-frequency visibility (the Haar path,
:func:`prtlab.shadowfields.haar_direct`, or a shadow ray);
:func:`sh_visibility_toward` offers the SH path's smooth visibility and the
tests measure what it costs (a point light's hard shadow seen through order-4
SH visibility is wrong by tens of percent near and inside the shadow).

References
----------
K. Zhou et al., "Precomputed shadow fields for dynamic scenes", SIGGRAPH 2005,
Sec. 3 (source radiance fields) and Sec. 4.
"""

from __future__ import annotations

import functools

import numba
import numpy as np

from prtlab import sh
from prtlab._validate import check_int, check_order

__all__ = ["area_light_sh", "point_light_direct", "sh_visibility_toward"]


@numba.njit(cache=True, parallel=True)
def _light_samples(points, ys, area_w, normal, dirs, weight):
    """Unit directions to the light points and their solid-angle weights ``dA cos_l / r^2``."""
    for p in numba.prange(points.shape[0]):
        for m in range(ys.shape[0]):
            dx = ys[m, 0] - points[p, 0]
            dy = ys[m, 1] - points[p, 1]
            dz = ys[m, 2] - points[p, 2]
            r2 = dx * dx + dy * dy + dz * dz
            if r2 > 0.0:
                r = np.sqrt(r2)
                dx /= r
                dy /= r
                dz /= r
                cos_l = -(dx * normal[0] + dy * normal[1] + dz * normal[2])
                weight[p, m] = area_w[m] * cos_l / r2 if cos_l > 0.0 else 0.0
                dirs[p, m, 0], dirs[p, m, 1], dirs[p, m, 2] = dx, dy, dz
            else:
                weight[p, m] = 0.0
                dirs[p, m, 0], dirs[p, m, 1], dirs[p, m, 2] = normal[0], normal[1], normal[2]


@functools.lru_cache(maxsize=8)
def _gauss_legendre(n: int):
    return np.polynomial.legendre.leggauss(n)


def area_light_sh(light, points, order: int, n_nodes: int = 12, method: str = "numba") -> np.ndarray:
    """SH of the radiance arriving from an area light at points (unoccluded).

    Parameters
    ----------
    light : prtlab.scene.AreaLight
    points : (..., 3) float
    order : int
    n_nodes : int
        Gauss-Legendre nodes per edge of the parallelogram (``n_nodes**2`` light points).
    method : {"numba", "reference"}
        Light-sample geometry by a parallel kernel or in numpy float64 (the specification).

    Returns
    -------
    coeffs : (..., n*n, 3) float64
        ``int L(p, w) Y_i(w) dw`` per colour channel.

    Notes
    -----
    The solid-angle integral is taken over the light's area,

    .. math::

        \\int L(p, w) Y_i(w) dw = L_e \\int_A Y_i(w_y) \\frac{\\max(0, -n_l \\cdot w_y)}{|y - p|^2} dA_y,
        \\qquad w_y = \\frac{y - p}{|y - p|},

    by a tensor Gauss-Legendre rule over ``(s, t)``; it is accurate for lights
    of any angular size except for points within about an edge / ``n_nodes``
    of the light.
    """
    order = check_order(order)
    check_int(n_nodes, "n_nodes", 1)
    if method not in ("numba", "reference"):
        raise ValueError(f"method must be 'numba' or 'reference', got {method!r}")
    points = np.asarray(points, dtype=np.float64)
    if points.ndim == 0 or points.shape[-1] != 3:
        raise ValueError(f"points must be a (..., 3) array, got shape {points.shape}")
    if not np.all(np.isfinite(points)):
        raise ValueError("points contain NaN or inf; pass finite points")
    batch = points.shape[:-1]
    flat = points.reshape(-1, 3)
    x, w = _gauss_legendre(int(n_nodes))
    u, v = np.asarray(light.u, float), np.asarray(light.v, float)
    ys = np.asarray(light.center, float) + x[:, None, None] * u + x[None, :, None] * v
    ys = ys.reshape(-1, 3)
    area_w = (w[:, None] * w[None, :]).reshape(-1) * np.linalg.norm(np.cross(u, v))  # dA = |u x v| ds dt
    normal = light.normal
    out = np.zeros((len(flat), order * order))
    step = max(1, (1 << 20) // len(ys))
    for a in range(0, len(flat), step):
        chunk = np.ascontiguousarray(flat[a : a + step])
        dirs = np.empty((len(chunk), len(ys), 3))
        weight = np.empty((len(chunk), len(ys)))
        if method == "reference":
            d = ys[None, :, :] - chunk[:, None, :]
            r2 = np.sum(d * d, axis=-1)
            r = np.sqrt(r2)
            cos_l = np.maximum(-(d @ normal) / np.where(r > 0, r, 1.0), 0.0)
            weight = np.where(r2 > 0, area_w * cos_l / np.where(r2 > 0, r2, 1.0), 0.0)
            dirs = np.where(r[..., None] > 0, d / np.where(r > 0, r, 1.0)[..., None], normal)
        else:
            _light_samples(chunk, np.ascontiguousarray(ys), area_w, np.asarray(normal, float), dirs, weight)
        out[a : a + step] = np.einsum("pm,pmi->pi", weight, sh.basis(dirs, order))
    return (out[:, :, None] * np.asarray(light.radiance, float)).reshape(batch + (order * order, 3))


def sh_visibility_toward(visibility, dirs) -> np.ndarray:
    """The SH visibility evaluated in given directions, clamped to [0, 1] (the smooth visibility of the SH path).

    Parameters
    ----------
    visibility : (V, n*n) float
        SH visibility per vertex (:func:`visibility_pass`).
    dirs : (V, 3) float
        A direction per vertex (e.g. toward a point light; normalised here).

    Returns
    -------
    values : (V,) float64
        ``clip(sum_i V_i Y_i(d), 0, 1)``. Order-n SH blur a shadow edge over about
        ``pi / n`` radians and ring around it: a point light's shadow, which
        needs the visibility in exactly one direction, is the worst case of the SH
        path (measured in ``tests/shadowfields/test_sources.py``); prefer the
        visibility of the Haar path (:func:`haar_direct`) or a shadow ray.
    """
    vis = np.asarray(visibility, dtype=np.float64)
    d = np.asarray(dirs, dtype=np.float64)
    if vis.ndim != 2:
        raise ValueError(f"visibility must be (V, n*n), got shape {vis.shape}")
    order = int(round(np.sqrt(vis.shape[1])))
    if order * order != vis.shape[1] or order < 1:
        raise ValueError(f"visibility must have n*n coefficients, got {vis.shape[1]}")
    if d.shape != (len(vis), 3):
        raise ValueError(f"dirs must be (V, 3) = ({len(vis)}, 3), got shape {d.shape}")
    if not (np.all(np.isfinite(vis)) and np.all(np.isfinite(d))):
        raise ValueError("visibility or dirs contain NaN or inf")
    if len(vis) == 0:
        return np.zeros(0)
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    d = np.where(norm > 0, d / np.where(norm > 0, norm, 1.0), np.array([0.0, 0.0, 1.0]))
    return np.clip(np.einsum("vi,vi->v", vis, sh.basis(d, order)), 0.0, 1.0)


def point_light_direct(light, points, normals, sep, visibility=None) -> np.ndarray:
    """Direct light ``L_k`` (V, K, C) of a point light through a separable BRDF: an exact delta.

    ``L_k = I / r^2 g_k(d) max(0, n . d) V(d)`` with ``d`` the unit direction to the light.
    Point lights need the visibility in one direction only, so both paths take it
    from the exact or all-frequency visibility: :func:`haar_direct` (the texel of
    ``d`` in the Haar visibility) or a shadow ray; :func:`sh_visibility_toward`
    gives the SH path's smooth visibility, at a cost measured in the tests.

    Parameters
    ----------
    light : prtlab.scene.PointLight
    points, normals : (V, 3) float
    sep : prtlab.brdf.SeparableBRDF
        ``"plain"``; ``g_k`` in the frame of :func:`prtlab.brdf.local_frame`.
    visibility : (V,) float, optional
        Visibility toward the light in [0, 1] (default 1: unoccluded).

    Returns
    -------
    light_k : (V, K, 3) float64
    """
    from prtlab.brdf import SeparableBRDF, to_local

    if not isinstance(sep, SeparableBRDF):
        raise TypeError(f"sep must be a SeparableBRDF (prtlab.brdf.separable), got {type(sep).__name__}")
    points = np.asarray(points, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or normals.shape != points.shape:
        raise ValueError(f"points and normals must be (V, 3) arrays of one shape, got {points.shape} and "
                         f"{normals.shape}")
    if not (np.all(np.isfinite(points)) and np.all(np.isfinite(normals))):
        raise ValueError("points or normals contain NaN or inf")
    vis = np.ones(len(points)) if visibility is None else np.asarray(visibility, dtype=np.float64)
    if vis.shape != (len(points),):
        raise ValueError(f"visibility must be (V,) = ({len(points)},), got shape {vis.shape}")
    if len(points) == 0:
        return np.zeros((0, sep.K, 3))
    d = np.asarray(light.position, float) - points
    r2 = np.einsum("vi,vi->v", d, d)
    safe = np.where(r2 > 0, r2, 1.0)
    unit = np.where(r2[:, None] > 0, d / np.sqrt(safe)[:, None], normals)
    n = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    cos = np.maximum(np.einsum("vi,vi->v", unit, n), 0.0)
    g = sep.g(to_local(unit, n))
    weight = np.where(r2 > 0, cos / safe, 0.0) * vis
    return (g * weight[:, None])[..., None] * np.asarray(light.intensity, float)

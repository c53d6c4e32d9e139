"""Interior lights and the light leaving through the portals (Yue et al. 2009, Section 9's future work).

The paper transfers light one way, from the exterior through the portals to the interior, and leaves "a
bidirectional light transfer (not only from the exterior to the interior but also from the interior to the
exterior)" and interior lights to future work. Here, with ``indirect="surface"``:

- **Interior lights** (:class:`prtlab.scene.PointLight`, one-sided :class:`prtlab.scene.AreaLight`), placed at
  precompute time, their emission (intensity or radiance, RGB) per frame. Per vertex the *light factor*
  ``f_v = int V(x_v, y) max(0, n_v . w) cos_y / r^2 dA_y`` (a point light: ``V max(0, n_v . w) / r^2``), so the
  direct radiance is ``rho_v / pi * E * f_v`` (``E``: intensity or radiance). The same factor averaged over each
  vertex's hat function drives the bounces through the interior-to-interior transfer of ``indirect="surface"``,
  exactly as the sky's direct light does; a gather ray that leaves through a portal carries no light, so the light
  reaching a portal leaves the room (is lost). Sky and interior lights add in one frame.
- **The light leaving through a portal**: the radiance leaving the window toward outward directions ``w``,
  averaged over the window, ``Lbar(w) = 1/A int_portal L(y, w) dA_y`` (``L(y, w)`` the radiance of the interior
  point seen from ``y`` looking along ``-w``), as SH coefficients ``c = int_{n_out . w > 0} Y(w) Lbar(w) dw``
  (zero over the inward hemisphere) per portal. Precomputed: ``W (n^2, V)`` from ``M`` stratified (portal point,
  uniform outward direction) rays, each reading the hit triangle's vertices by barycentrics; an area light seen
  straight through the window adds its own column. Per frame ``c = W L_total + W_light E``. Far from the window
  (a few window sizes) the window is then an area light of radiance ``Lbar(w)``.

Limits: positions of the lights are baked (a moved light is refused); lights do not occlude or reflect in the
interior transfer (a small light near a wall blocks little of a gather); an area light is one-sided; rays from a
portal that leave through another portal read nothing (the exterior seen through two windows is not in ``c``);
the SH truncation of a sharp ``Lbar`` (a lit patch seen through the window) rings. Measured in
``docs/notes/portals.md`` (section 14).
"""

from __future__ import annotations

import numpy as np

from prtlab.geometry import RayCaster, stratified_hemisphere
from prtlab.scene import AreaLight, PointLight

from ._indirect import front_hit_corners

__all__ = ["interior_light_factor", "leaving_transfer", "leaving_radiance", "INTERIOR_LIGHTS"]

#: the light types that may stand inside a portals room
INTERIOR_LIGHTS = (PointLight, AreaLight)


def _light_samples(light, n_samples: int, rng: np.random.Generator):
    """Points ``(S, 3)``, unit emitting normals ``(S, 3)`` (zero for a point light) and area weights ``(S,)``."""
    if isinstance(light, PointLight):
        return np.asarray(light.position, dtype=np.float64)[None], np.zeros((1, 3)), np.ones(1)
    from prtlab.geometry._sampling import _stratified_unit_square

    st = 2.0 * _stratified_unit_square(n_samples, rng, ()) - 1.0
    points = (np.asarray(light.center, float) + st[:, 0:1] * np.asarray(light.u, float)
              + st[:, 1:2] * np.asarray(light.v, float))
    return points, np.broadcast_to(light.normal, points.shape), np.full(len(points), light.area / len(points))


def interior_light_factor(caster: RayCaster, points, normals, light, n_samples: int = 64,
                          rng: np.random.Generator | None = None, chunk: int = 4096) -> np.ndarray:
    """The light factor ``f (N,)`` float64 of each point (module docstring): the direct radiance of a Lambertian
    point is ``rho / pi * E * f``, ``E`` the light's intensity (point) or radiance (area).

    Parameters
    ----------
    caster : RayCaster
        The interior (portals left out).
    points, normals : (N, 3) float
        Shading points and unit normals of their shaded side.
    light : PointLight or AreaLight
    n_samples : int
        Stratified points on an area light (a point light: one).
    rng : numpy.random.Generator
        Draws the area light's points (default seed 0).

    Notes
    -----
    ``f = sum_s a_s V(x, y_s) max(0, n . w_s) max(0, -n_y . w_s) / r_s^2`` with ``w_s = (y_s - x) / r_s``; a point
    light has ``a = 1`` and no ``cos_y`` factor. Unbiased for the area light (stratified by area).
    """
    if not isinstance(light, INTERIOR_LIGHTS):
        raise TypeError(f"light must be a PointLight or AreaLight, got {type(light).__name__}")
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    if points.shape != normals.shape:
        raise ValueError(f"points and normals must both be (N, 3), got {points.shape} and {normals.shape}")
    rng = np.random.default_rng(0) if rng is None else rng
    is_point = isinstance(light, PointLight)
    out = np.zeros(len(points))
    step = max(1, chunk // (1 if is_point else max(n_samples, 1)))
    for start in range(0, len(points), step):
        x, n = points[start : start + step], normals[start : start + step]
        y, ny, a = _light_samples(light, n_samples, rng)
        d = y[None, :, :] - x[:, None, :]  # (c, S, 3)
        r = np.linalg.norm(d, axis=2)
        w = d / np.where(r > 0, r, 1.0)[..., None]
        cos_x = np.einsum("csk,ck->cs", w, n)
        cos_y = np.ones_like(cos_x) if is_point else -np.einsum("csk,sk->cs", w, ny)
        weight = np.where((cos_x > 0) & (cos_y > 0) & (r > 0), a[None] * cos_x * cos_y / np.where(r > 0, r, 1.0)**2,
                          0.0)
        ci, si = np.nonzero(weight)
        if len(ci):
            # the light's own sample points sit on no surface: test the segment short of them
            blocked = caster.occluded(x[ci], w[ci, si], r[ci, si] * (1.0 - 1e-6), normals=n[ci])
            weight[ci[blocked], si[blocked]] = 0.0
        out[start : start + len(x)] = weight.sum(axis=1)
    return out


def leaving_transfer(caster: RayCaster, portal, vertex_offset, vertex_normals, order: int, n_rays: int,
                     rng: np.random.Generator, area_lights=(), chunk: int = 1 << 18):
    """``(W (n^2, N), W_light (n^2, L))`` float64: the SH coefficients of the radiance leaving ``portal`` (module
    docstring) are ``W L + W_light E`` for per-vertex radiance ``L (N, 3)`` (every caster vertex) and the area
    lights' radiances ``E (L, 3)``.

    ``n_rays`` rays, each a stratified portal point (:func:`prtlab.portals._direct._portal_points`, Sobol') and a
    stratified uniform direction over the outward hemisphere (pdf ``1 / (2 pi)``): ``W = 2 pi / M sum_j Y(w_j)
    e_hit_j`` with ``e_hit`` the hit triangle's barycentrics on its vertices (zero on a back face, or a miss).
    ``area_lights``: AreaLight objects seen straight from the window where nearer than the first surface (their
    front emits, their back is black; either hides what is behind).
    """
    import prtlab.sh as sh

    from ._direct import _portal_points

    n_vertices = int(vertex_offset[-1])
    n2 = order * order
    out = np.zeros((n2, n_vertices))
    out_light = np.zeros((n2, len(area_lights)))
    if n_rays <= 0:
        return out, out_light
    outward = -np.asarray(portal.normal, dtype=np.float64)  # the portal's normal faces the interior
    points, _ = _portal_points(portal, 1, n_rays, rng, "sobol")
    points = points.reshape(-1, 3)
    dirs, _ = stratified_hemisphere(n_rays, rng, outward)
    rng.shuffle(dirs)  # decorrelate the direction strata from the portal's
    faces_all = [caster.faces(i) for i in range(caster.n_objects)]
    for start in range(0, n_rays, chunk):
        y, w = points[start : start + chunk], dirs[start : start + chunk]
        basis = sh.basis(w, order)  # (c, n2)
        hits = caster.closest_hit(y, -w)
        sel, vid, bw = front_hit_corners(hits, -w, faces_all, vertex_offset, vertex_normals)
        distance = np.where(hits.hit, hits.distance, np.inf)
        for k, light in enumerate(area_lights):  # a light nearer than the surface hides it; its front emits
            t, met, front = _rectangle_hit(light, y, -w)
            met &= t < distance
            out_light[:, k] += basis[met & front].sum(axis=0)
            keep = ~met[sel]
            sel, vid, bw = sel[keep], vid[keep], bw[keep]
            distance = np.where(met, t, distance)
        b = basis[sel]
        for i in range(n2):
            out[i] += np.bincount(vid.ravel(), weights=(b[:, i:i + 1] * bw).ravel(), minlength=n_vertices)
    scale = 2.0 * np.pi / n_rays
    return out * scale, out_light * scale


def _rectangle_hit(light, origins, dirs):
    """Distance along each ray to an AreaLight's rectangle, whether the ray meets it, and whether on its emitting
    (front) face."""
    n = light.normal
    denom = dirs @ n
    safe = np.where(np.abs(denom) > 1e-12, denom, 1.0)
    t = np.einsum("rk,k->r", np.asarray(light.center) - origins, n) / safe
    p = origins + t[:, None] * dirs - np.asarray(light.center)
    u, v = np.asarray(light.u, float), np.asarray(light.v, float)
    s, q = p @ u / (u @ u), p @ v / (v @ v)
    met = (np.abs(denom) > 1e-12) & (t > 0) & (np.abs(s) <= 1) & (np.abs(q) <= 1)
    return t, met, denom < 0


def leaving_radiance(coeffs, dirs) -> np.ndarray:
    """The radiance ``(..., 3)`` leaving a portal toward world directions ``dirs (..., 3)`` from its SH
    coefficients ``coeffs (n^2, 3)`` (``shade(...).info["leaving_sh"][k]``): ``sum_i c_i Y_i(w)``, clamped at 0
    (the truncated series rings below zero near a sharp edge)."""
    import prtlab.sh as sh

    coeffs = np.asarray(coeffs, dtype=np.float64)
    if coeffs.ndim != 2 or coeffs.shape[1] != 3 or int(np.sqrt(coeffs.shape[0]))**2 != coeffs.shape[0]:
        raise ValueError(f"coeffs must be (n*n, 3) SH coefficients of one portal, got shape {coeffs.shape}")
    dirs = np.asarray(dirs, dtype=np.float64)
    if dirs.shape[-1:] != (3,):
        raise ValueError(f"dirs must be (..., 3) directions, got shape {dirs.shape}")
    if dirs.size == 0:
        return np.zeros(dirs.shape[:-1] + (3,))
    order = int(np.sqrt(coeffs.shape[0]))
    return np.maximum(sh.basis(dirs, order) @ coeffs, 0.0)

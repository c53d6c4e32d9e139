"""The residual gather: the part of a source's radiance that its PCA basis misses, gathered by ray casting.

An extension of Iwasaki et al. 2007 (issue 18). A source's outgoing radiance ``colour_k L_k`` reaches the
receivers through its basis radiance fields only as its projection ``P`` on the ``N`` PCA functions
(Eq. 14); what the basis cannot hold (the shadow of an object that moved since the basis was trained, a
light in a pose the training never saw) is lost. Per frame and bounce the residual
``r_k = colour_k L_k - P(colour_k L_k)`` at the sources' vertices is gathered instead, as a one-bounce
final gather of that residual alone:

* every receiver point casts ``n`` rays per source (stratified, a fixed seed) into the scene at the
  frame's poses: uniform in the cone of the source's bounding sphere, or cosine-weighted over the
  hemisphere from a point inside that sphere; a ray whose first hit is the front of the source carries
  the residual interpolated at the hit (barycentrically, as the basis radiance fields interpolate ``Psi``);
* ``L_k'(x) += sum_rays g_k'(w) (n . w)+ / (n pdf(w)) sum_k h_k(-w) r_k(hit)``: unbiased for the
  residual with exact visibility, near or far (a source 3 cm away as well as a small one far off).

The hits (:class:`ResidualHits`) depend on the poses only and are reused while they stand; per bounce
the gather is one weighted sum over them. The noise of ``n`` rays falls on the residual alone, which is
small where the basis holds the radiance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from prtlab import brdf
from prtlab.geometry import offset_origins

__all__ = ["ResidualHits", "cosine_directions", "residual_hits", "gather_residual"]


@dataclass(frozen=True)
class ResidualHits:
    """Rays of one receiver that hit the front of one source: ``rows`` (H,) receiver points, ``vertices``
    (H, 3) and ``bary`` (H, 3) of the hit on the source, ``factor`` (H, K', K) ``g_k'(w) h_k(-w)`` times the
    ray's weight ``(n . w)+ / (n pdf)``."""

    rows: np.ndarray
    vertices: np.ndarray
    bary: np.ndarray
    factor: np.ndarray


def _jittered(n_points: int, n: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """(V, m) pairs ``(u1, u2)`` of a jittered ``rows x side`` grid of the unit square, ``m = rows side <= n``."""
    side = max(1, int(np.sqrt(n)))
    rows = max(1, n // side)
    i, j = np.meshgrid(np.arange(rows), np.arange(side), indexing="ij")
    u1 = (i.ravel()[None] + rng.random((n_points, rows * side))) / rows
    u2 = (j.ravel()[None] + rng.random((n_points, rows * side))) / side
    return u1, u2


def cosine_directions(normals, n: int, seed: int = 0) -> np.ndarray:
    """(V, m, 3) cosine-weighted directions about each unit normal: a jittered grid of the unit square
    (:func:`_jittered`, ``m <= n``) lifted to the hemisphere (Malley)."""
    normals = np.asarray(normals, float)
    u1, u2 = _jittered(len(normals), n, np.random.default_rng(seed))
    r, phi = np.sqrt(u1), 2.0 * np.pi * u2
    local = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(1.0 - u1, 0.0))], axis=-1)
    return brdf.to_world(local, np.broadcast_to(normals[:, None], local.shape))


def _rays(points, normals, centre, radius, n: int, rng):
    """Directions (V, m, 3) and their weights ``max(n . w, 0) / (m pdf)`` (V, m) toward a source's bounding
    sphere: uniform in its cone from a point outside it, cosine-weighted on the hemisphere from inside."""
    d = centre[None] - points
    dist = np.linalg.norm(d, axis=1)
    inside = dist <= 1.0001 * radius
    u1, u2 = _jittered(len(points), n, rng)
    m = u1.shape[1]
    cos_max = np.sqrt(np.maximum(1.0 - (radius / np.maximum(dist, radius)) ** 2, 0.0))  # cone half-angle
    cos_t = 1.0 - u1 * (1.0 - cos_max)[:, None]
    sin_t, phi = np.sqrt(np.maximum(1.0 - cos_t**2, 0.0)), 2.0 * np.pi * u2
    local = np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], axis=-1)
    axis = np.where(inside[:, None], normals, d / np.maximum(dist, 1e-300)[:, None])
    dirs = brdf.to_world(local, np.broadcast_to(axis[:, None], local.shape))
    weight = np.maximum(np.einsum("vmi,vi->vm", dirs, normals), 0.0) * (2.0 * np.pi * (1.0 - cos_max))[:, None] / m
    if np.any(inside):
        cosine = cosine_directions(normals[inside], n, int(rng.integers(2**31)))
        dirs[inside], weight[inside] = cosine, np.pi / m
    return dirs, weight


def residual_hits(points, normals, receiver_sep, caster, sources: dict, n_rays: int, seed: int = 0) -> dict:
    """``{source index: ResidualHits}`` of ``n_rays`` rays per receiver point and source.

    ``caster`` holds every object at its pose (its object index is the key); ``sources`` maps the indices
    that are sources of this receiver to ``(faces, world vertex normals, separable BRDF, bounding-sphere
    centre, radius)``. Rays go uniformly into the cone of the source's bounding sphere (cosine-weighted
    over the hemisphere from a point inside it), so a small far source gets all of them; a ray counts
    when its first hit is the front of that source.
    """
    points = np.asarray(points, float)
    normals = np.asarray(normals, float)
    rng = np.random.default_rng(seed)
    out = {}
    if len(points) == 0:
        return out
    for s, (faces, vertex_normals, sep, centre, radius) in sources.items():
        dirs, weight = _rays(points, normals, np.asarray(centre, float), float(radius), n_rays, rng)
        origins = offset_origins(points[:, None], normals[:, None], dirs, caster.epsilon)
        hits = caster.closest_hit(origins, dirs)
        sel = np.nonzero(hits.hit & (hits.object == s) & (weight > 0))
        if not len(sel[0]):
            continue
        tri = np.asarray(faces, np.int64)[hits.triangle[sel]]
        uv = hits.barycentric[sel]
        bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
        shading = np.einsum("hc,hcx->hx", bary, vertex_normals[tri])
        shading /= np.maximum(np.linalg.norm(shading, axis=1, keepdims=True), 1e-300)
        w = dirs[sel]
        front = np.einsum("hx,hx->h", shading, w) < 0.0  # the back of a surface emits nothing
        if not np.any(front):
            continue
        rows, tri, bary, w, shading = sel[0][front], tri[front], bary[front], w[front], shading[front]
        g = receiver_sep.g(brdf.to_local(w, normals[rows]))  # (H, K')
        h = sep.h(brdf.to_local(-w, shading))  # (H, K)
        out[s] = ResidualHits(rows, tri, bary, weight[sel][front][:, None, None] * g[:, :, None] * h[:, None, :])
    return out


def gather_residual(hits: ResidualHits, residual, n_points: int) -> np.ndarray:
    """``L_k',c`` (n_points, K', C) gathered from a source's per-vertex ``residual`` (V_s, K, C)."""
    residual = np.asarray(residual, float)
    at_hit = np.einsum("hv,hvkc->hkc", hits.bary, residual[hits.vertices])
    per_ray = np.einsum("hqk,hkc->hqc", hits.factor, at_hit)
    out = np.zeros((n_points,) + per_ray.shape[1:])
    np.add.at(out, hits.rows, per_ray)
    return out

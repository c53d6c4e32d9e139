"""The residual gather: the part of a source's radiance that its PCA basis misses, gathered by ray casting.

An extension of Iwasaki et al. 2007 (issue 18). A source's outgoing radiance ``colour_k L_k`` reaches the
receivers through its basis radiance fields only as its projection ``P`` on the ``N`` PCA functions
(Eq. 14); what the basis cannot hold (the shadow of an object that moved since the basis was trained, a
light in a pose the training never saw) is lost. Per frame and bounce the residual
``r_k = colour_k L_k - P(colour_k L_k)`` at the sources' vertices is gathered instead, as a one-bounce
final gather of that residual alone:

* every receiver point casts ``n`` cosine-weighted rays (stratified, a fixed seed) into the scene at the
  frame's poses; a ray whose first hit is the front of a source carries the residual interpolated at the
  hit (barycentrically, as the basis radiance fields interpolate ``Psi``);
* ``L_k'(x) += (pi / n) sum_rays g_k'(w) sum_k h_k(-w) r_k(hit)``: unbiased for the residual with exact
  visibility, near or far (a source 3 cm away as well as a far wall).

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
    (H, 3) and ``bary`` (H, 3) of the hit on the source, ``factor`` (H, K', K) ``(pi / n) g_k'(w) h_k(-w)``."""

    rows: np.ndarray
    vertices: np.ndarray
    bary: np.ndarray
    factor: np.ndarray


def cosine_directions(normals, n: int, seed: int = 0) -> np.ndarray:
    """(V, n, 3) cosine-weighted directions about each unit normal: a jittered ``sqrt(n) x sqrt(n)``-ish
    grid of the unit square (``n`` rounded to a multiple of its side), lifted to the hemisphere (Malley)."""
    normals = np.asarray(normals, float)
    side = max(1, int(np.sqrt(n)))
    rows = max(1, n // side)
    rng = np.random.default_rng(seed)
    i, j = np.meshgrid(np.arange(rows), np.arange(side), indexing="ij")
    u1 = (i.ravel()[None] + rng.random((len(normals), rows * side))) / rows
    u2 = (j.ravel()[None] + rng.random((len(normals), rows * side))) / side
    r, phi = np.sqrt(u1), 2.0 * np.pi * u2
    local = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(1.0 - u1, 0.0))], axis=-1)
    return brdf.to_world(local, np.broadcast_to(normals[:, None], local.shape))


def residual_hits(points, normals, receiver_sep, caster, sources: dict, n_rays: int, seed: int = 0) -> dict:
    """``{source index: ResidualHits}`` of the ``n_rays`` cosine-weighted rays of every receiver point.

    ``caster`` holds every object at its pose (its object index is the key); ``sources`` maps the indices
    that are sources of this receiver to ``(faces, world vertex normals, separable BRDF)``.
    """
    points = np.asarray(points, float)
    normals = np.asarray(normals, float)
    if len(points) == 0:
        return {}
    dirs = cosine_directions(normals, n_rays, seed)  # (V, n, 3)
    n = dirs.shape[1]
    origins = offset_origins(points[:, None], normals[:, None], dirs, caster.epsilon)
    hits = caster.closest_hit(origins, dirs)
    out = {}
    for s, (faces, vertex_normals, sep) in sources.items():
        sel = np.nonzero(hits.hit & (hits.object == s))
        if not len(sel[0]):
            continue
        tri = np.asarray(faces, np.int64)[hits.triangle[sel]]
        uv = hits.barycentric[sel]
        bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
        shading = np.einsum("hc,hcx->hx", bary, vertex_normals[tri])
        shading /= np.maximum(np.linalg.norm(shading, axis=1, keepdims=True), 1e-300)
        w = dirs[sel]
        front = np.einsum("hx,hx->h", shading, w) < 0.0  # the back of a surface emits nothing
        rows, tri, bary, w, shading = sel[0][front], tri[front], bary[front], w[front], shading[front]
        if not len(rows):
            continue
        g = receiver_sep.g(brdf.to_local(w, normals[rows]))  # (H, K')
        h = sep.h(brdf.to_local(-w, shading))  # (H, K)
        out[s] = ResidualHits(rows, tri, bary, (np.pi / n) * g[:, :, None] * h[:, None, :])
    return out


def gather_residual(hits: ResidualHits, residual, n_points: int) -> np.ndarray:
    """``L_k',c`` (n_points, K', C) gathered from a source's per-vertex ``residual`` (V_s, K, C)."""
    residual = np.asarray(residual, float)
    at_hit = np.einsum("hv,hvkc->hkc", hits.bary, residual[hits.vertices])
    per_ray = np.einsum("hqk,hkc->hqc", hits.factor, at_hit)
    out = np.zeros((n_points,) + per_ray.shape[1:])
    np.add.at(out, hits.rows, per_ray)
    return out

"""Direct light of area and point lights by shadow rays at the frame's poses (``shadows="rays"``).

An extension of Iwasaki et al. 2007 (issue 18). The paper's direct light is the order-n SH product of the
light, the visibility and the clamped cosine (Eq. 8 with shadow fields); under a near area light that
product smears the light and its shadows (9-13 % per vertex on the open room corner at order 4, in
docs/FIDELITY.md). Here each vertex integrates the lights itself:

``L_k(x) = sum_lights integral L_e g_k(w) (n . w)+ V(x, w) dw``,

the term ``L_k`` (V, K, C) that the SH path computes as ``P_n(V G_k) . L`` (:meth:`direct_step`), with
``V`` from shadow rays against every object at the frame's poses (so self-shadows and a moved object's
shadow are exact). An area light is sampled by area, ``m`` points per vertex on a grid of the parallelogram
jittered per vertex (unbiased at each vertex, stratified across the light); the estimator is ``L_e A / m sum_j g_k cos_x cos_l V / d^2``. A point light takes one
shadow ray. The same samples give the radiance toward the camera with the material's BRDF itself, so a
glossy receiver's direct light is not limited by its K-term separable form (which still carries the light
into the bounces). The environment stays in SH (low frequency: the paper's form).
"""

from __future__ import annotations

import numpy as np

from prtlab import brdf
from prtlab.scene import AreaLight, PointLight

__all__ = ["ray_traced_direct"]

#: vertices per chunk: bounds the (chunk, m, 3) sample arrays (about 50 MB at m = 256)
_CHUNK = 8192


def _grid(m: int) -> tuple[np.ndarray, np.ndarray]:
    """``(corners (rows * side, 2), cell size (2,))`` of a ``rows x side`` grid of the unit square,
    ``rows * side <= m``."""
    side = max(1, int(np.sqrt(m)))
    rows = max(1, m // side)
    i, j = np.meshgrid(np.arange(rows), np.arange(side), indexing="ij")
    return np.stack([i.ravel() / rows, j.ravel() / side], axis=1), np.array([1.0 / rows, 1.0 / side])


def _area_light(x, n, wo, f, sep, caster, light: AreaLight, m: int, rng):
    """``L_k`` (V, K, C) and the radiance toward ``wo`` (V, C) of one area light at points ``x`` with normals
    ``n`` (``f``: the BRDF)."""
    corner, cell = _grid(m)
    st = (corner[None] + rng.random((len(x), len(corner), 2)) * cell) * 2.0 - 1.0  # (V, m, 2) in [-1, 1]^2
    c, u, v = (np.asarray(getattr(light, name), float) for name in ("center", "u", "v"))
    y = c + st[..., :1] * u + st[..., 1:] * v
    d = y - x[:, None]
    dist = np.linalg.norm(d, axis=-1)
    w = d / np.maximum(dist, 1e-300)[..., None]
    cos_x = np.einsum("vmi,vi->vm", w, n)
    cos_l = -w @ light.normal
    live = (cos_x > 0.0) & (cos_l > 0.0) & (dist > 0.0)
    weight = np.where(live, cos_x * cos_l / np.maximum(dist, 1e-300) ** 2, 0.0) * (light.area / len(corner))
    rows, cols = np.nonzero(live)
    if len(rows):
        blocked = caster.occluded(x[rows], w[rows, cols], dist[rows, cols] - caster.epsilon, normals=n[rows])
        weight[rows[blocked], cols[blocked]] = 0.0
    g = sep.g(brdf.to_local(w, np.broadcast_to(n[:, None], w.shape)))  # (V, m, K)
    radiance = np.asarray(light.radiance, float)
    out = np.einsum("vm,vmc,c->vc", weight, f.eval(w, wo[:, None], n[:, None]), radiance)
    return np.einsum("vm,vmk,c->vkc", weight, g, radiance), out


def _point_light(x, n, wo, f, sep, caster, light: PointLight):
    """``L_k`` (V, K, C) of one point light, ``I g_k cos_x V / d^2``, and the radiance toward ``wo`` (V, C)."""
    d = np.asarray(light.position, float) - x
    dist = np.linalg.norm(d, axis=1)
    w = d / np.maximum(dist, 1e-300)[:, None]
    cos_x = np.einsum("vi,vi->v", w, n)
    weight = np.where((cos_x > 0.0) & (dist > 0.0), cos_x / np.maximum(dist, 1e-300) ** 2, 0.0)
    lit = np.flatnonzero(weight > 0.0)
    if len(lit):
        blocked = caster.occluded(x[lit], w[lit], dist[lit] - caster.epsilon, normals=n[lit])
        weight[lit[blocked]] = 0.0
    g = sep.g(brdf.to_local(w, n))  # (V, K)
    intensity = np.asarray(light.intensity, float)
    return np.einsum("v,vk,c->vkc", weight, g, intensity), np.einsum("v,vc,c->vc", weight, f.eval(w, wo, n), intensity)


def ray_traced_direct(points, normals, wo, f, sep, caster, lights, samples: int, seed: int = 0):
    """``(L_k (V, K, C), radiance toward wo (V, C))`` at world ``points`` with unit ``normals`` from the area
    and point lights of ``lights`` (others are left out), with shadow rays against ``caster`` (every object at
    its pose).

    ``wo`` (V, 3): unit directions toward the camera, mirrored above a vertex's horizon where they are below
    it (the BRDFs are two-sided: a Lambertian vertex seen from behind keeps its radiance, as the separable
    form's horizon value does); ``f``: the receiver's BRDF (:mod:`prtlab.brdf`) and ``sep`` its separable
    form. ``samples`` points per vertex on each area light (a ``rows x side <= samples`` grid jittered per
    vertex; a fixed ``seed``, so a frame is deterministic).
    """
    x, n, wo = (np.asarray(a, float) for a in (points, normals, wo))
    below = np.minimum(np.einsum("vi,vi->v", wo, n), 0.0)
    wo = wo - 2.0 * below[:, None] * n
    light_k, radiance = np.zeros((len(x), sep.K, 3)), np.zeros((len(x), 3))
    rng = np.random.default_rng(seed)
    for lo in range(0, len(x), _CHUNK):
        part = slice(lo, lo + _CHUNK)
        for light in lights:
            args = (x[part], n[part], wo[part], f, sep, caster, light)
            if isinstance(light, AreaLight):
                lk, out = _area_light(*args, samples, rng)
            elif isinstance(light, PointLight):
                lk, out = _point_light(*args)
            else:
                continue
            light_k[part] += lk
            radiance[part] += out
    return light_k, radiance

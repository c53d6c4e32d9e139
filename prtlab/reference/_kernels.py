"""numba kernels of the Monte Carlo reference: BSDF evaluation and sampling.

Every path vertex carries a Lambert + normalised Phong BRDF (``kd``, ``ks``,
``exponent``; a diffuse material has ``ks = 0``) as in
:class:`prtlab.scene.Material`:

.. math::

    f(\\omega_i, \\omega_o) = \\frac{k_d}{\\pi}
        + k_s \\frac{e + 2}{2 \\pi} \\max(0, r_o \\cdot \\omega_i)^e,
    \\qquad r_o = 2 (n \\cdot \\omega_o) n - \\omega_o

(``r_o . w_i`` equals ``r_i . w_o`` of the Material docstring: reflection is a
symmetric isometry). Sampling picks the Phong lobe with probability
``p_s = sum(ks) / (sum(kd) + sum(ks))``, else the cosine lobe, so

.. math::

    p(\\omega_i) = (1 - p_s) \\frac{\\cos\\theta_i}{\\pi}
        + p_s \\frac{e + 1}{2 \\pi} \\max(0, r_o \\cdot \\omega_i)^e .

Directions below the shading normal (``n . w_i <= 0``) carry ``f cos = 0``.
The kernels take only arrays and check nothing; the float64 numpy tier
:func:`bsdf_eval_numpy` is their specification.
"""

from __future__ import annotations

import numba
import numpy as np

from prtlab.geometry._raycast import barycentric_normal

__all__ = ["bsdf_eval_kernel", "bsdf_sample_kernel", "bsdf_eval_numpy", "hit_frame_kernel"]

_INV_PI = 1.0 / np.pi


@numba.njit(cache=True, inline="always")
def _specular_probability(kd0, kd1, kd2, ks0, ks1, ks2):
    sd = kd0 + kd1 + kd2
    ss = ks0 + ks1 + ks2
    if sd + ss <= 0.0:
        return 0.0
    return ss / (sd + ss)


@numba.njit(cache=True)
def _eval_one(n, wo, wi, kd, ks, ex, out_fcos, i):
    """f cos into out_fcos[i]; returns the sampling pdf of wi."""
    cos_i = n[i, 0] * wi[i, 0] + n[i, 1] * wi[i, 1] + n[i, 2] * wi[i, 2]
    if cos_i <= 0.0:
        out_fcos[i, 0] = 0.0
        out_fcos[i, 1] = 0.0
        out_fcos[i, 2] = 0.0
        return 0.0
    ps = _specular_probability(kd[i, 0], kd[i, 1], kd[i, 2], ks[i, 0], ks[i, 1], ks[i, 2])
    spec = 0.0
    if ps > 0.0:
        c = n[i, 0] * wo[i, 0] + n[i, 1] * wo[i, 1] + n[i, 2] * wo[i, 2]
        rdot = 0.0
        for k in range(3):
            rdot += (2.0 * c * n[i, k] - wo[i, k]) * wi[i, k]
        if rdot > 0.0:
            spec = rdot ** ex[i]
    e = ex[i]
    for k in range(3):
        out_fcos[i, k] = (kd[i, k] * _INV_PI + ks[i, k] * (e + 2.0) * 0.5 * _INV_PI * spec) * cos_i
    return (1.0 - ps) * cos_i * _INV_PI + ps * (e + 1.0) * 0.5 * _INV_PI * spec


@numba.njit(cache=True, parallel=True)
def bsdf_eval_kernel(n, wo, wi, kd, ks, ex, out_fcos, out_pdf):
    """``f(wi, wo) * max(0, n . wi)`` and the sampling pdf of ``wi``; all (N, 3) / (N,)."""
    for i in numba.prange(n.shape[0]):
        out_pdf[i] = _eval_one(n, wo, wi, kd, ks, ex, out_fcos, i)


@numba.njit(cache=True, parallel=True)
def bsdf_sample_kernel(n, wo, kd, ks, ex, uniforms, out_wi, out_weight, out_pdf):
    """Sample ``wi`` from the mixture pdf; weight ``f cos / pdf`` (0 below the surface).

    ``uniforms`` is (N, 3): lobe choice, then two coordinates.
    """
    for i in numba.prange(n.shape[0]):
        ps = _specular_probability(kd[i, 0], kd[i, 1], kd[i, 2], ks[i, 0], ks[i, 1], ks[i, 2])
        if uniforms[i, 0] < ps:
            c = n[i, 0] * wo[i, 0] + n[i, 1] * wo[i, 1] + n[i, 2] * wo[i, 2]
            ax = 2.0 * c * n[i, 0] - wo[i, 0]
            ay = 2.0 * c * n[i, 1] - wo[i, 1]
            az = 2.0 * c * n[i, 2] - wo[i, 2]
            length = np.sqrt(ax * ax + ay * ay + az * az)
            ax /= length
            ay /= length
            az /= length
            cz = uniforms[i, 1] ** (1.0 / (ex[i] + 1.0))
        else:
            ax = n[i, 0]
            ay = n[i, 1]
            az = n[i, 2]
            cz = np.sqrt(max(0.0, 1.0 - uniforms[i, 1]))
        sz = np.sqrt(max(0.0, 1.0 - cz * cz))
        phi = 2.0 * np.pi * uniforms[i, 2]
        lx = sz * np.cos(phi)
        ly = sz * np.sin(phi)
        # Duff et al. 2017 orthonormal basis around (ax, ay, az)
        sign = 1.0 if az >= 0.0 else -1.0
        a = -1.0 / (sign + az)
        b = ax * ay * a
        tx, ty, tz = 1.0 + sign * ax * ax * a, sign * b, -sign * ax
        bx, by, bz = b, sign + ay * ay * a, -ay
        out_wi[i, 0] = lx * tx + ly * bx + cz * ax
        out_wi[i, 1] = lx * ty + ly * by + cz * ay
        out_wi[i, 2] = lx * tz + ly * bz + cz * az
        pdf = _eval_one(n, wo, out_wi, kd, ks, ex, out_weight, i)
        out_pdf[i] = pdf
        if pdf > 0.0:
            for k in range(3):
                out_weight[i, k] /= pdf
        else:
            for k in range(3):
                out_weight[i, k] = 0.0


def bsdf_eval_numpy(n, wo, wi, kd, ks, ex):
    """Float64 numpy specification of :func:`bsdf_eval_kernel`: returns ``(f cos (N, 3), pdf (N,))``."""
    n, wo, wi, kd, ks = (np.asarray(x, dtype=np.float64) for x in (n, wo, wi, kd, ks))
    ex = np.asarray(ex, dtype=np.float64)
    cos_i = np.sum(n * wi, axis=-1)
    r = 2.0 * np.sum(n * wo, axis=-1, keepdims=True) * n - wo
    rdot = np.sum(r * wi, axis=-1)
    spec = np.where(rdot > 0.0, np.maximum(rdot, 0.0) ** ex, 0.0)
    sd, ss = kd.sum(axis=-1), ks.sum(axis=-1)
    ps = np.where(sd + ss > 0, ss / np.where(sd + ss > 0, sd + ss, 1.0), 0.0)
    spec = np.where(ps > 0, spec, 0.0)
    f = kd / np.pi + ks * ((ex + 2.0) / (2.0 * np.pi) * spec)[..., None]
    above = cos_i > 0
    fcos = np.where(above[..., None], f * np.maximum(cos_i, 0.0)[..., None], 0.0)
    pdf = np.where(above, (1 - ps) * cos_i / np.pi + ps * (ex + 1.0) / (2.0 * np.pi) * spec, 0.0)
    return fcos, pdf


@numba.njit(cache=True, parallel=True)
def hit_frame_kernel(obj, tri, uv, ng, wi, face_offset, faces, vertex_normals, out_ns, out_ng, out_wo):
    """Frames of new path vertices: interpolated shading normal and geometric normal, both
    turned to the side of ``wo = -wi`` (the shading normal first follows the winding of ``ng``)."""
    for i in numba.prange(obj.shape[0]):
        f = face_offset[obj[i]] + tri[i]
        u, v = uv[i, 0], uv[i, 1]
        w = 1.0 - u - v
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        nx, ny, nz = barycentric_normal(vertex_normals, a, b, c, w, u, v)
        length = np.sqrt(nx * nx + ny * ny + nz * nz)
        if length < 1e-12:
            nx, ny, nz = ng[i, 0], ng[i, 1], ng[i, 2]
        else:
            nx, ny, nz = nx / length, ny / length, nz / length
        if nx * ng[i, 0] + ny * ng[i, 1] + nz * ng[i, 2] < 0.0:
            nx, ny, nz = -nx, -ny, -nz
        side = 1.0
        if ng[i, 0] * wi[i, 0] + ng[i, 1] * wi[i, 1] + ng[i, 2] * wi[i, 2] > 0.0:  # ng . wo < 0
            side = -1.0
        out_ns[i, 0], out_ns[i, 1], out_ns[i, 2] = side * nx, side * ny, side * nz
        for k in range(3):
            out_ng[i, k] = side * ng[i, k]
            out_wo[i, k] = -wi[i, k]

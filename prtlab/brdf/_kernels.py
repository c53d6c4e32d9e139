"""numba kernels of :mod:`prtlab.brdf`: batched BRDF and factor evaluation.

The kernels take only arrays and scalars and check nothing; the public
functions in ``_models.py`` and ``_separable.py`` validate, normalise and
allocate. Each kernel has a float64 numpy twin here (``*_numpy``) that is its
specification; the tests hold the kernels to them.
"""

from __future__ import annotations

import numba
import numpy as np

_INV_PI = 1.0 / np.pi


@numba.njit(cache=True, inline="always")
def tangent_frame_at(n0, n1, n2):
    """The unit normal ``a`` of ``n`` and its tangents ``t``, ``b`` (Duff et al. 2017, as
    :func:`prtlab.geometry.tangent_frame`), as nine scalars ``a0, a1, a2, t0, t1, t2, b0, b1, b2``."""
    length = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    a0, a1, a2 = n0 / length, n1 / length, n2 / length
    sign = 1.0 if a2 >= 0.0 else -1.0
    fa = -1.0 / (sign + a2)
    fb = a0 * a1 * fa
    return (a0, a1, a2, 1.0 + sign * a0 * a0 * fa, sign * fb, -sign * a0, fb, sign + a1 * a1 * fa, -a1)


@numba.njit(cache=True, parallel=True)
def phong_eval_kernel(wi, wo, n, kd, ks, exponent, out):
    """Two-sided normalised Phong ``f(wi, wo)`` into ``out (N, C)``; wi, wo, n (N, 3) unit."""
    n_channels = kd.shape[0]
    norm = (exponent + 2.0) * 0.5 * _INV_PI
    for p in numba.prange(wi.shape[0]):
        ci = n[p, 0] * wi[p, 0] + n[p, 1] * wi[p, 1] + n[p, 2] * wi[p, 2]
        co = n[p, 0] * wo[p, 0] + n[p, 1] * wo[p, 1] + n[p, 2] * wo[p, 2]
        if ci * co < 0.0:
            for c in range(n_channels):
                out[p, c] = 0.0
            continue
        rdot = 0.0
        for k in range(3):
            rdot += (2.0 * ci * n[p, k] - wi[p, k]) * wo[p, k]
        lobe = norm * rdot**exponent if rdot > 0.0 else 0.0
        for c in range(n_channels):
            out[p, c] = kd[c] * _INV_PI + ks[c] * lobe


def phong_eval_numpy(wi, wo, n, kd, ks, exponent):
    """Float64 numpy specification of :func:`phong_eval_kernel`; returns ``(N, C)``."""
    ci = np.sum(n * wi, axis=-1)
    co = np.sum(n * wo, axis=-1)
    r = 2.0 * ci[..., None] * n - wi
    rdot = np.sum(r * wo, axis=-1)
    lobe = np.where(rdot > 0.0, (exponent + 2.0) / (2.0 * np.pi) * np.maximum(rdot, 0.0) ** exponent, 0.0)
    f = kd / np.pi + ks * lobe[..., None]
    return np.where((ci * co < 0.0)[..., None], 0.0, f)


@numba.njit(cache=True, inline="always")
def factor_at(nodes, values, freq, parity, x, y, z, out):
    """``out[k]`` = the separable factors at one unit direction ``(x, y, z)`` (see :func:`factor_eval_kernel`)."""
    last = nodes.shape[0] - 1
    theta = np.arctan2(np.sqrt(x * x + y * y), z)
    azimuthal = False
    for k in range(freq.shape[0]):
        azimuthal = azimuthal or freq[k] != 0
    phi = np.arctan2(y, x) if azimuthal else 0.0  # freq 0: cos(0 phi) = 1, sin(0 phi) = 0 for any finite phi
    if theta <= nodes[0]:
        j = 0
        t = 0.0
    elif theta >= nodes[last]:
        j = last - 1
        t = 1.0
    else:
        j = np.searchsorted(nodes, theta) - 1
        t = (theta - nodes[j]) / (nodes[j + 1] - nodes[j])
    for k in range(values.shape[0]):
        a, b = values[k, j], values[k, j + 1]
        radial = a if a == b else (1.0 - t) * a + t * b  # equal nodes: their value exactly, as np.interp gives it
        angle = freq[k] * phi
        if angle == 0.0:  # cos(+-0) = 1 and sin(+-0) = +-0 exactly: no libm call (most terms have freq 0)
            out[k] = radial if parity[k] == 0 else radial * angle
        elif parity[k] == 0:
            out[k] = radial * np.cos(angle)
        else:
            out[k] = radial * np.sin(angle)


@numba.njit(cache=True, parallel=True)
def factor_eval_kernel(nodes, values, freq, parity, dirs, out):
    """Separable factors at unit directions.

    ``out[p, k] = interp(theta_p; nodes, values[k]) * trig_k(freq[k] * phi_p)``
    with ``trig = cos`` (parity 0) or ``sin`` (parity 1), ``theta`` clamped to
    ``[nodes[0], nodes[-1]]``; nodes (P,) increasing, values (K, P), dirs (N, 3).
    """
    for p in numba.prange(dirs.shape[0]):
        factor_at(nodes, values, freq, parity, dirs[p, 0], dirs[p, 1], dirs[p, 2], out[p])


def factor_eval_numpy(nodes, values, freq, parity, dirs):
    """Float64 numpy specification of :func:`factor_eval_kernel`; returns ``(N, K)``."""
    theta = np.arctan2(np.hypot(dirs[:, 0], dirs[:, 1]), dirs[:, 2])
    phi = np.arctan2(dirs[:, 1], dirs[:, 0])
    radial = np.stack([np.interp(theta, nodes, v) for v in values], axis=-1) if len(values) else np.zeros((len(dirs), 0))
    angle = phi[:, None] * freq[None, :]
    return radial * np.where(parity[None, :] == 0, np.cos(angle), np.sin(angle))

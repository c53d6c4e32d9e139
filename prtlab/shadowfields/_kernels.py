"""Numba kernels of the shadow fields: trilinear lookups of sphere-sampled fields, visibility projection.

Kernels take only arrays and scalars and check nothing; the public functions
in ``_grid.py`` / ``_occlusion.py`` validate and coerce.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, inline="always")
def sample_corners(rpos, s, t, n_r, res):
    """The eight samples around a point of a field on concentric cubemap-gridded spheres: the sphere indices
    ``r0, r1`` and weight ``fr`` of ``r1``, the texel rows ``i0, i1`` (weight ``fi``) and columns ``j0, j1``
    (weight ``fj``) at face coordinates ``(s, t)``, texel centres at ``(j + 0.5) / res``, clamped to the grid."""
    r0 = min(max(int(np.floor(rpos)), 0), n_r - 1)
    fr = rpos - r0
    r1 = r0 + 1 if r0 + 1 < n_r else r0
    x = min(max(s * res - 0.5, 0.0), res - 1.0)
    y = min(max(t * res - 0.5, 0.0), res - 1.0)
    j0 = int(np.floor(x))
    i0 = int(np.floor(y))
    j1 = j0 + 1 if j0 + 1 < res else j0
    i1 = i0 + 1 if i0 + 1 < res else i0
    return r0, r1, fr, i0, i1, y - i0, j0, j1, x - j0


@numba.njit(cache=True, parallel=True, nogil=True)
def trilinear_kernel(values, rpos, face, s, t, out):
    """Trilinear interpolation of a field sampled on concentric cubemap-gridded spheres.

    values : (n_r, 6, res, res, F) float64, C-contiguous
    rpos : (Q,) float64, fractional sphere index in [0, n_r - 1]
    face : (Q,) int64; s, t : (Q,) float64 in [0, 1] (cubemap face coordinates)
    out : (Q, F) float64
    """
    n_r = values.shape[0]
    res = values.shape[2]
    n_f = values.shape[4]
    for q in numba.prange(rpos.shape[0]):
        r0, r1, fr, i0, i1, fi, j0, j1, fj = sample_corners(rpos[q], s[q], t[q], n_r, res)
        f = face[q]
        for k in range(n_f):
            acc = 0.0
            for a in range(2):
                rr = r0 if a == 0 else r1
                wr = (1.0 - fr) if a == 0 else fr
                if wr == 0.0:
                    continue
                v00 = values[rr, f, i0, j0, k]
                v01 = values[rr, f, i0, j1, k]
                v10 = values[rr, f, i1, j0, k]
                v11 = values[rr, f, i1, j1, k]
                acc += wr * ((1.0 - fi) * ((1.0 - fj) * v00 + fj * v01) + fi * ((1.0 - fj) * v10 + fj * v11))
            out[q, k] = acc


@numba.njit(cache=True, parallel=True)
def project_visibility_kernel(blocked, wy, out):
    """SH of visibility: ``out[p] = sum_d (1 - blocked[p, d]) wy[d]``.

    blocked : (P, D) bool; wy : (D, n2) float64 (quadrature weight times basis); out : (P, n2)
    """
    n2 = wy.shape[1]
    for p in numba.prange(blocked.shape[0]):
        for k in range(n2):
            out[p, k] = 0.0
        for d in range(blocked.shape[1]):
            if not blocked[p, d]:
                for k in range(n2):
                    out[p, k] += wy[d, k]


@numba.njit(cache=True, inline="always")
def _interp_index(x, xp):
    """``np.interp(x, xp, arange(len(xp)))`` for finite ``x`` and increasing ``xp`` (``len(xp) >= 2``), by numpy's
    own steps: the end values outside ``xp``, ``j`` at ``x == xp[j]``, else ``slope (x - xp[j]) + j``."""
    last = xp.shape[0] - 1
    if x > xp[last]:
        return float(last)
    if x < xp[0]:
        return 0.0
    j = np.searchsorted(xp, x, side="right") - 1  # the largest j with xp[j] <= x
    if j >= last or xp[j] == x:
        return float(j)
    slope = (float(j + 1) - float(j)) / (xp[j + 1] - xp[j])
    value = slope * (x - xp[j]) + float(j)
    if np.isnan(value):
        value = slope * (x - xp[j + 1]) + float(j + 1)
    return value


@numba.njit(cache=True, fastmath=False, nogil=True)  # set: callees inherit a caller's fastmath unless set
def locate_point(x, y, z, radii):
    """One point of :func:`locate_kernel`, given relative to the spheres' centre: ``(rpos, face, s, t, r)``."""
    r = np.sqrt((x * x + y * y) + z * z)
    if not r > 0.0:
        x, y, z = 0.0, 0.0, 1.0
    ax, ay, az = abs(x), abs(y), abs(z)
    if ax >= ay and ax >= az:
        f, ma = (0 if x >= 0.0 else 1), ax
    elif ay >= az:
        f, ma = (2 if y >= 0.0 else 3), ay
    else:
        f, ma = (4 if z >= 0.0 else 5), az
    if f == 0:
        sc, tc = -z, -y
    elif f == 1:
        sc, tc = z, -y
    elif f == 2:
        sc, tc = x, z
    elif f == 3:
        sc, tc = x, -z
    elif f == 4:
        sc, tc = x, -y
    else:
        sc, tc = -x, -y
    s = min(max(0.5 * (sc / ma + 1.0), 0.0), 1.0)
    t = min(max(0.5 * (tc / ma + 1.0), 0.0), 1.0)
    return _interp_index(r, radii), f, s, t, r


@numba.njit(cache=True, parallel=True, nogil=True)
def locate_kernel(points, center, radii, rpos, face, s, t, beyond):
    """``SphereGrid.locate`` of object-space ``points`` (Q, 3), the same floating-point steps as its numpy path: the
    radius ``sqrt((x^2 + y^2) + z^2)`` of ``points - center``, ``rpos`` by ``np.interp`` over ``radii`` (at least
    two), the cube face and face coordinates of the direction (``direction_to_cubemap``; ``+z`` at the centre)."""
    for q in numba.prange(points.shape[0]):
        rpos[q], face[q], s[q], t[q], r = locate_point(points[q, 0] - center[0], points[q, 1] - center[1],
                                                        points[q, 2] - center[2], radii)
        beyond[q] = r > radii[radii.shape[0] - 1]

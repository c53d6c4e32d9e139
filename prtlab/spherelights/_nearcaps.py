"""Direct light with the nearest blockers as exact caps (option ``near_blockers``; an extension).

The paper's direct light (Sec. 5.1, Ren et al. 2006) is ``E = V_n . T_n`` with ``V_n = exp*(sum_i G_i)`` the
order-``n`` visibility of every blocker and ``T_n = P_n(L max(0, n . w))``. Beside a large blocker (a neighbouring
sphere covering much of the hemisphere) the order-``n`` truncation of its visibility dominates the error. Here the
``k`` blockers of largest angular radius (at least ``MIN_ANGLE_DEG``) at each receiver are taken out of the log
sum and their visibility enters exactly (binary, the true spheres, no horizon adjustment: the clamped cosine
removes what lies below the tangent plane):

.. math:: E = \\mathbf V^{rest}_n \\cdot \\big(\\mathbf T_n - \\mathbf Q\\big), \\qquad
          Q_k = \\int_{C_1 \\cup \\dots \\cup C_k} y_k(w)\\, L(w)\\, \\max(0, n \\cdot w)\\, dw,

``V^rest_n`` the exponentiated log sum of the other (adjusted) blockers and ``C_j`` the caps subtended by the
near spheres. It is exact when the other blockers are absent (``V^rest = 1``) up to the quadrature of ``Q``; in
general it replaces ``P_n(V_near V_rest) . T`` by ``P_n(V_rest) . P_n(L c V_near)``.

``Q`` is a product quadrature per cap (Gauss-Legendre in ``cos alpha`` over ``[cos theta, 1]`` times uniform
azimuths about the cap's axis); points of a later cap lying inside an earlier one are skipped (the union). The
environment radiance at the nodes is read bilinearly from a cube map of its SH (:func:`environment_cube`).
"""

from __future__ import annotations

import collections
import math
from typing import NamedTuple

import numba
import numpy as np

from prtlab import sh
from prtlab.sh._kernels import _A, _B, _PMM, LOW_BANDS, _high_bands, _low_bands

from ._reuse import kept_by_key
from ._shadows import BlockerLanes, LaneScratch, _as_spheres, _blocker_log_knots, _blocker_lanes, _check_order, \
    _receivers, blocker_log_table, environment_transfer, one_thread_below

__all__ = ["environment_cube", "has_near_blocker", "near_blocker_direct", "NearVisibility",
           "near_blocker_visibility", "near_blocker_visibility_update", "near_blocker_sums"]

#: Cube-map face resolution of the environment table (an order-10 SH environment varies over ~18 degrees; a texel
#: of 32 per face spans under 3 degrees).
CUBE_RES = 32
#: The smallest angular radius (degrees) of a blocker taken exactly: smaller ones stay in the log sum, where the
#: order-n truncation of their visibility costs little (see docs/notes/spherelights.md).
MIN_ANGLE_DEG = 10.0
#: Gauss-Legendre nodes in cos(alpha) and azimuths per cap.
N_RADIAL = 4
N_AZIMUTH = 12
#: The Gauss-Legendre rule of ``N_RADIAL`` nodes, made once (``leggauss`` costs about 0.4 ms a call); only read.
_RADIAL_RULE = np.polynomial.legendre.leggauss(N_RADIAL)
#: Receivers below which :func:`near_blocker_direct` runs on one thread (about 4 us of work each: the pipeline's
#: calls at the surface samples and at small objects), and :func:`has_near_blocker` (about 50 ns each).
_SERIAL_BELOW = 1024
_SERIAL_BELOW_TEST = 16384


def _cube_dirs(res: int) -> np.ndarray:
    """``(6, res, res, 3)`` unit directions at the texel centres; face ``2 a + s`` has dominant axis ``a``, sign
    ``+`` (s = 0) or ``-`` (s = 1), and coordinates ``(u, v)`` on the next two axes in cyclic order."""
    t = -1.0 + (2.0 * np.arange(res) + 1.0) / res
    u, v = np.meshgrid(t, t, indexing="ij")
    out = np.empty((6, res, res, 3))
    for a in range(3):
        for s in range(2):
            d = np.empty((res, res, 3))
            d[..., a] = 1.0 if s == 0 else -1.0
            d[..., (a + 1) % 3] = u
            d[..., (a + 2) % 3] = v
            out[2 * a + s] = d / np.linalg.norm(d, axis=-1, keepdims=True)
    return out


def environment_cube(env_sh, res: int = CUBE_RES) -> np.ndarray:
    """``(6, res, res, C)`` environment radiance from its SH ``(N*N, C)`` at the texel centres of a cube map
    (faces as :func:`_cube_dirs`), read back by :func:`_cube_lookup`. The last few maps are kept (keyed by the
    SH's bytes; a frame calls it once per receiver set); the returned array is read-only."""
    env = np.ascontiguousarray(env_sh, dtype=np.float64)
    return kept_by_key(_CUBE_CACHE, (env.shape, env.tobytes(), int(res)), lambda: np.ascontiguousarray(
        (sh.basis(_cube_dirs(res).reshape(-1, 3), math.isqrt(env.shape[0])) @ env).reshape(6, res, res, -1)),
        _CUBE_CACHE_SIZE)


#: Cube maps of the last environments (:func:`environment_cube`).
_CUBE_CACHE: dict = {}
_CUBE_CACHE_SIZE = 4


@numba.njit(cache=True, inline="always")
def _cube_lookup(cube, wx, wy, wz, out):
    """Bilinear read of ``cube`` at unit direction ``w`` into ``out (C,)`` (clamped at the face borders)."""
    ax, ay, az = abs(wx), abs(wy), abs(wz)
    if ax >= ay and ax >= az:
        f = 0 if wx > 0 else 1
        m, u, v = ax, wy, wz
    elif ay >= az:
        f = 2 if wy > 0 else 3
        m, u, v = ay, wz, wx
    else:
        f = 4 if wz > 0 else 5
        m, u, v = az, wx, wy
    res = cube.shape[1]
    fu = (u / m + 1.0) * 0.5 * res - 0.5
    fv = (v / m + 1.0) * 0.5 * res - 0.5
    i = min(max(int(math.floor(fu)), 0), res - 2)
    j = min(max(int(math.floor(fv)), 0), res - 2)
    a = min(max(fu - i, 0.0), 1.0)
    b = min(max(fv - j, 0.0), 1.0)
    for c in range(cube.shape[3]):
        out[c] = ((1.0 - a) * (1.0 - b) * cube[f, i, j, c] + a * (1.0 - b) * cube[f, i + 1, j, c]
                  + (1.0 - a) * b * cube[f, i, j + 1, c] + a * b * cube[f, i + 1, j + 1, c])


#: Receivers per block of the lane kernels (the SIMD lanes, as the fused second pass).
_LANES = 32
#: The tables :func:`_blocker_lanes` reads.
_SplitTables = collections.namedtuple("_SplitTables", ["blocker_log", "blocker_knots"])


@numba.njit(cache=True, parallel=True, error_model="numpy")
def _near_split(points, normals, centres, radii, eligible, min_sin, tables, order, n_near, g_rest, near_axis,
                near_cos):
    """Per receiver: the ``n_near`` kept spheres of largest angular radius (kept: the receiver outside it and the
    sphere not wholly below the tangent plane; ``eligible[s]``; ``sin theta >= min_sin``) as caps (unit axis,
    ``cos theta``; ``cos = 2`` where none), and the log sum (Eqs. 6-7, adjusted blockers) of the other spheres.

    Blocks of ``_LANES`` receivers as SIMD lanes: every sphere's log by :func:`_blocker_lanes` (the fused second
    pass's), then per lane the choice and the sum of the others' logs in sphere order (a chosen sphere's log
    enters times 0)."""
    n_recv = points.shape[0]
    n_sph = centres.shape[0]
    n2 = order * order
    n_blocks = (n_recv + _LANES - 1) // _LANES
    for block in numba.prange(n_blocks):
        first = block * _LANES
        n_valid = min(_LANES, n_recv - first)
        recv = np.empty((6, _LANES))
        logs = BlockerLanes(np.empty((n_sph, n2, _LANES)), np.empty((n2, _LANES)), np.empty((n_sph, _LANES)),
                            np.empty((n_sph, _LANES)), np.empty((n_sph, _LANES)), np.empty((n_sph, _LANES)),
                            np.empty((n_sph, 3, _LANES)))
        work = LaneScratch(np.empty((order, _LANES)), np.empty((n2, _LANES)), np.empty((7, _LANES)))
        keep = np.empty((n_sph, _LANES))
        sin_t = np.empty(n_sph)
        for q in range(_LANES):  # a partial block repeats its last receiver
            b = first + min(q, n_valid - 1)
            for t in range(3):
                recv[t, q] = points[b, t]
                recv[3 + t, q] = normals[b, t]
        _blocker_lanes(recv, centres, radii, tables, order, logs, work)
        log = logs.log
        for q in range(n_valid):
            b = first + q
            px, py, pz = recv[0, q], recv[1, q], recv[2, q]
            nx, ny, nz = recv[3, q], recv[4, q], recv[5, q]
            for s in range(n_sph):
                keep[s, q] = 1.0
                ex, ey, ez = centres[s, 0] - px, centres[s, 1] - py, centres[s, 2] - pz
                d2 = ex * ex + ey * ey + ez * ez
                r = radii[s]
                h = nx * ex + ny * ey + nz * ez
                culled = d2 < r * r or h <= -r or d2 <= 0.0 or r <= 0.0 or not eligible[s]
                sin_t[s] = -1.0 if culled else min(r / math.sqrt(d2), 1.0)
                if sin_t[s] < min_sin:
                    sin_t[s] = -1.0
            for j in range(n_near):
                best, bs = -1, 0.0
                for s in range(n_sph):
                    if keep[s, q] > 0.0 and sin_t[s] > bs:
                        best, bs = s, sin_t[s]
                if best < 0:
                    near_cos[b, j] = 2.0
                    near_axis[b, j, 0] = 0.0
                    near_axis[b, j, 1] = 0.0
                    near_axis[b, j, 2] = 1.0
                    continue
                keep[best, q] = 0.0
                ex, ey, ez = centres[best, 0] - px, centres[best, 1] - py, centres[best, 2] - pz
                inv = 1.0 / math.sqrt(ex * ex + ey * ey + ez * ez)
                near_axis[b, j, 0], near_axis[b, j, 1], near_axis[b, j, 2] = ex * inv, ey * inv, ez * inv
                near_cos[b, j] = math.sqrt(max(1.0 - bs * bs, 0.0))
        for q in range(n_valid, _LANES):
            for s in range(n_sph):
                keep[s, q] = 0.0
        total = logs.total_log  # reused: the others' sum, in sphere order as the reference tier
        for k in range(n2):
            for q in range(_LANES):
                total[k, q] = 0.0
        for s in range(n_sph):
            for k in range(n2):
                for q in range(_LANES):
                    total[k, q] += keep[s, q] * log[s, k, q]
        for q in range(n_valid):
            for k in range(n2):
                g_rest[first + q, k] = total[k, q]


@numba.njit(cache=True, inline="always")
def _frame(ax, ay, az):
    """Two unit vectors completing the unit ``a`` to an orthonormal frame."""
    if abs(ax) < 0.9:
        tx, ty, tz = 0.0, az, -ay  # a x (1, 0, 0)
    else:
        tx, ty, tz = -az, 0.0, ax  # a x (0, 1, 0)
    inv = 1.0 / math.sqrt(tx * tx + ty * ty + tz * tz)
    tx, ty, tz = tx * inv, ty * inv, tz * inv
    return tx, ty, tz, ay * tz - az * ty, az * tx - ax * tz, ax * ty - ay * tx


@numba.njit(cache=True, parallel=True)
def _cap_integrals(normals, near_axis, near_cos, cube, order, gl_nodes, gl_weights, n_az, out):
    """``out[b, k, c] = int_{union of the caps} y_k(w) L_c(w) max(0, n_b . w) dw`` (the module's quadrature)."""
    n_recv = normals.shape[0]
    n_near = near_cos.shape[1]
    n_ch = cube.shape[3]
    n_rad = gl_nodes.shape[0]
    n2 = order * order
    dphi = 2.0 * math.pi / n_az
    cos_az = np.empty(n_az)
    sin_az = np.empty(n_az)
    for q in range(n_az):
        cos_az[q] = math.cos((q + 0.5) * dphi)
        sin_az[q] = math.sin((q + 0.5) * dphi)
    n_blocks = (n_recv + _LANES - 1) // _LANES
    for block in numba.prange(n_blocks):  # scratch per block of receivers, not per receiver
        ybuf = np.empty((1, n2))
        lval = np.empty(n_ch)
        acc = np.empty((n_ch, n2))
        for b in range(block * _LANES, min(n_recv, (block + 1) * _LANES)):
            _cap_integral(normals, near_axis, near_cos, cube, order, gl_nodes, gl_weights, cos_az, sin_az, dphi, b,
                          ybuf, lval, acc, out)


@numba.njit(cache=True, inline="always")
def _cap_integral(normals, near_axis, near_cos, cube, order, gl_nodes, gl_weights, cos_az, sin_az, dphi, b, ybuf,
                  lval, acc, out):
    """``out[b]`` of :func:`_cap_integrals`; ``ybuf (1, n*n)``, ``lval (C,)``, ``acc (C, n*n)`` scratch."""
    n_near = near_cos.shape[1]
    n_ch = cube.shape[3]
    n_rad = gl_nodes.shape[0]
    n_az = cos_az.shape[0]
    n2 = order * order
    if near_cos[b, 0] > 1.0:  # no cap (the caps are filled first)
        for k in range(n2):
            for c in range(n_ch):
                out[b, k, c] = 0.0
        return
    for c in range(n_ch):
        for k in range(n2):
            acc[c, k] = 0.0
    nx, ny, nz = normals[b, 0], normals[b, 1], normals[b, 2]
    for j in range(n_near):
        ct = near_cos[b, j]
        if ct > 1.0:
            continue
        ax, ay, az = near_axis[b, j, 0], near_axis[b, j, 1], near_axis[b, j, 2]
        # the cap wholly below the tangent plane adds nothing
        if nx * ax + ny * ay + nz * az <= -math.sqrt(max(1.0 - ct * ct, 0.0)):
            continue
        t1x, t1y, t1z, t2x, t2y, t2z = _frame(ax, ay, az)
        half = 0.5 * (1.0 - ct)
        for i in range(n_rad):
            u = ct + half * (gl_nodes[i] + 1.0)
            sa = math.sqrt(max(1.0 - u * u, 0.0))
            wr = half * gl_weights[i] * dphi
            bx, by, bz = u * ax, u * ay, u * az
            for q in range(n_az):
                cp, sp = cos_az[q] * sa, sin_az[q] * sa
                wx = bx + cp * t1x + sp * t2x
                wy = by + cp * t1y + sp * t2y
                wz = bz + cp * t1z + sp * t2z
                cosn = nx * wx + ny * wy + nz * wz
                if cosn <= 0.0:
                    continue
                dup = False
                for jj in range(j):
                    if near_cos[b, jj] <= 1.0 and (wx * near_axis[b, jj, 0] + wy * near_axis[b, jj, 1]
                                                    + wz * near_axis[b, jj, 2]) > near_cos[b, jj]:
                        dup = True
                        break
                if dup:
                    continue
                _low_bands(wx, wy, wz, order, ybuf, 0)
                if order > LOW_BANDS:
                    _high_bands(wx, wy, wz, order, _PMM, _A, _B, ybuf, 0)
                _cube_lookup(cube, wx, wy, wz, lval)
                f = wr * cosn
                for c in range(n_ch):
                    fc = f * lval[c]
                    for k in range(n2):
                        acc[c, k] += fc * ybuf[0, k]
    for k in range(n2):
        for c in range(n_ch):
            out[b, k, c] = acc[c, k]


def _cap_integrals_reference(normals, near_axis, near_cos, env_sh, order):
    """The numpy tier of :func:`_cap_integrals`: the same nodes, the radiance from the SH (no cube map)."""
    x, w = _RADIAL_RULE
    env = np.asarray(env_sh, dtype=np.float64)
    out = np.zeros((len(normals), order * order, env.shape[1]))
    dphi = 2.0 * np.pi / N_AZIMUTH
    phi = (np.arange(N_AZIMUTH) + 0.5) * dphi
    for b in range(len(normals)):
        for j in range(near_cos.shape[1]):
            ct = near_cos[b, j]
            a = near_axis[b, j]
            if ct > 1.0 or normals[b] @ a <= -math.sqrt(max(1 - ct * ct, 0.0)):
                continue
            t = np.cross(a, [1.0, 0, 0]) if abs(a[0]) < 0.9 else np.cross(a, [0, 1.0, 0])
            t1 = t / np.linalg.norm(t)
            t2 = np.cross(a, t1)
            half = 0.5 * (1 - ct)
            u = ct + half * (x + 1)
            sa = np.sqrt(np.maximum(1 - u * u, 0))
            dirs = (u[:, None, None] * a + (sa[:, None] * np.cos(phi))[..., None] * t1
                    + (sa[:, None] * np.sin(phi))[..., None] * t2).reshape(-1, 3)
            wt = np.repeat(half * w * dphi, N_AZIMUTH) * np.maximum(dirs @ normals[b], 0)
            for jj in range(j):
                if near_cos[b, jj] <= 1.0:
                    wt = np.where(dirs @ near_axis[b, jj] > near_cos[b, jj], 0.0, wt)
            y = sh.basis_reference(dirs, order)
            radiance = sh.basis_reference(dirs, math.isqrt(env.shape[0])) @ env
            out[b] += np.einsum("d,dk,dc->kc", wt, y, radiance)
    return out


def _min_sin() -> float:
    return math.sin(math.radians(MIN_ANGLE_DEG))


@numba.njit(cache=True, parallel=True)
def _has_near(points, normals, centres, radii, eligible, min_sin, out):
    for b in numba.prange(points.shape[0]):
        px, py, pz = points[b, 0], points[b, 1], points[b, 2]
        found = False
        for s in range(centres.shape[0]):
            if not eligible[s]:
                continue
            ex, ey, ez = centres[s, 0] - px, centres[s, 1] - py, centres[s, 2] - pz
            d2 = ex * ex + ey * ey + ez * ez
            r = radii[s]
            h = normals[b, 0] * ex + normals[b, 1] * ey + normals[b, 2] * ez
            if d2 >= r * r and h > -r and d2 > 0.0 and r > 0.0 and r * r >= min_sin * min_sin * d2:
                found = True
                break
        out[b] = found


def has_near_blocker(points, normals, centres, radii, eligible=None) -> np.ndarray:
    """``(B,) bool``: receivers with at least one blocker :func:`near_blocker_direct` takes exactly (eligible, the
    receiver outside it, not wholly below its tangent plane, angular radius at least ``MIN_ANGLE_DEG``); at the
    others it equals the paper's direct light."""
    p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    n = np.ascontiguousarray(normals, dtype=np.float64).reshape(-1, 3)
    c = np.ascontiguousarray(centres, dtype=np.float64).reshape(-1, 3)
    r = np.ascontiguousarray(radii, dtype=np.float64).reshape(-1)
    elig = np.ones(len(r), dtype=bool) if eligible is None else np.ascontiguousarray(eligible, dtype=bool).reshape(-1)
    out = np.zeros(len(p), dtype=bool)
    if len(r) and len(p):
        with one_thread_below(len(p), _SERIAL_BELOW_TEST):
            _has_near(p, n, c, r, elig, _min_sin(), out)
    return out


def near_blocker_direct(points, normals, centres, radii, env_sh, order: int, n_near: int = 2, *,
                        eligible=None, exp_method: str = "hyb", method: str = "numba") -> np.ndarray:
    """Direct irradiance from the environment with the ``n_near`` nearest blockers as exact caps (module docstring).

    Parameters
    ----------
    points, normals : (B, 3) float
    centres, radii : (S, 3), (S,) float
        Every spherical light as a blocker (world space).
    env_sh : (N*N, C) float
        Environment radiance (``N = 3 order - 2``: the exact transfer).
    order : int
        SH order ``n`` of the visibility (1..8).
    n_near : int
        Blockers per receiver taken exactly (0: the paper's ``V_n . T_n``).
    eligible : (S,) bool, optional
        The spheres that may be taken exactly (default all); the others always stay in the log sum. The pipeline
        leaves out the receiving object's own lights: a bounding sphere set's outside volume would shadow its own
        surface exactly (measured: the cube's direct error 0.042 -> 0.127, the bunny's 0.099 -> 0.149).
    exp_method : {"hyb", "ol", "exact"}
    method : {"numba", "reference"}
        ``"reference"``: the log sum by :func:`blocker_log_sum`'s numpy tier over the other spheres and ``Q``
        with the radiance evaluated from the SH at each node (no cube map).

    Returns
    -------
    (B, C) float64 irradiance (not clamped; the ground's hidden light not subtracted).
    """
    vis = near_blocker_visibility(points, normals, centres, radii, order, n_near, eligible=eligible,
                                  exp_method=exp_method, method=method)
    return near_blocker_sums(vis, env_sh, method=method)


class NearVisibility(NamedTuple):
    """The geometry of :func:`near_blocker_direct` at ``B`` receivers (:func:`near_blocker_visibility`): their unit
    normals ``(B, 3)``, the exponentiated SH visibility of the blockers left in the log sum ``(B, n*n)``, and per
    receiver the axes ``(B, k, 3)`` and half-angle cosines ``(B, k)`` of the caps taken exactly (2: none)."""

    normals: np.ndarray
    visibility: np.ndarray
    axis: np.ndarray
    cos_half: np.ndarray
    order: int


def near_blocker_visibility(points, normals, centres, radii, order: int, n_near: int = 2, *, eligible=None,
                            exp_method: str = "hyb", method: str = "numba") -> NearVisibility:
    """:class:`NearVisibility` of :func:`near_blocker_direct` (arguments as there): what does not depend on the
    environment, evaluated for one by :func:`near_blocker_sums`."""
    from prtlab._validate import check_int

    p, n, _ = _receivers(points, normals)
    p, n = np.ascontiguousarray(p.reshape(-1, 3)), np.ascontiguousarray(n.reshape(-1, 3))
    c, r = _as_spheres(centres, radii)
    order = _check_order(order)
    n_near = check_int(n_near, "n_near", 0)
    if method not in ("numba", "reference"):
        raise ValueError(f"method must be 'numba' or 'reference', got {method!r}")
    B = len(p)
    k = min(n_near, len(r))
    elig = np.ones(len(r), dtype=bool) if eligible is None else np.asarray(eligible, dtype=bool).reshape(-1)
    if elig.shape != (len(r),):
        raise ValueError(f"eligible must be a bool array of shape ({len(r)},), got {np.shape(eligible)}")
    with one_thread_below(B, _SERIAL_BELOW):
        g_rest = np.zeros((B, order * order))
        axis = np.zeros((B, k, 3))
        cosq = np.full((B, k), 2.0)
        if B and len(r):
            if method == "numba":
                _near_split(p, n, c, r, np.ascontiguousarray(elig), _min_sin(),
                            _SplitTables(blocker_log_table(order), _blocker_log_knots()), order, k,
                            g_rest, axis, cosq)
            else:
                g_rest, axis, cosq = _near_split_reference(p, n, c, r, elig, order, k)
        v = sh.exp(g_rest, method=exp_method, channels=False)
    return NearVisibility(n, v, axis, cosq, order)


#: Relative margin of :func:`near_blocker_visibility_update`'s test (of the lengths compared): far above the rounding
#: of the kernel's own test, far below what matters.
_UPDATE_MARGIN = 1e-9


def near_blocker_visibility_update(kept: NearVisibility, kept_lights, points, normals, centres, radii, order: int,
                                   n_near: int = 2, *, eligible=None, kept_from=None, exp_method: str = "hyb",
                                   method: str = "numba"):
    """:func:`near_blocker_visibility` (arguments as there) from ``kept``, made with the same ``order``, ``n_near``,
    ``exp_method`` and ``method`` under other lights ``kept_lights = (centres, radii, eligible)`` (the same number of
    them): ``(vis, counts)``, ``vis`` equal to a fresh call's bit for bit, or None when ``kept`` cannot serve.
    ``kept_from (B,) int``: per receiver the row of ``kept`` made at the same point and normal (the caller compares
    them; -1: none; default ``arange(B)``).

    A light wholly below a receiver's tangent plane (or holding the receiver) is culled there: its log enters the
    sum as zeros, which leave it as it is, and it is no cap. So a receiver keeps its row when every changed light
    (centre, radius or eligibility differing) lies below its tangent plane by :data:`_UPDATE_MARGIN` of the lengths
    involved in its old and its new form; the others, and those with no kept row, are computed
    (:func:`near_blocker_visibility` on them alone: a receiver's row depends on nothing but its own point and
    normal). ``counts``: ``{"receivers", "receivers_recomputed", "lights_changed"}``."""
    from prtlab._validate import check_int

    p, n, _ = _receivers(points, normals)
    p, n = np.ascontiguousarray(p.reshape(-1, 3)), np.ascontiguousarray(n.reshape(-1, 3))
    c, r = _as_spheres(centres, radii)
    old_c, old_r, old_elig = kept_lights
    old_c, old_r = _as_spheres(old_c, old_r)
    k = min(check_int(n_near, "n_near", 0), len(r))
    if len(old_r) != len(r) or kept.order != _check_order(order) or kept.axis.shape[1] != k:
        return None
    elig = np.ones(len(r), dtype=bool) if eligible is None else np.asarray(eligible, dtype=bool).reshape(-1)
    old_elig = np.ones(len(r), dtype=bool) if old_elig is None else np.asarray(old_elig, dtype=bool).reshape(-1)
    rows = np.arange(len(p)) if kept_from is None else np.asarray(kept_from, dtype=np.int64).reshape(-1)
    if rows.shape != (len(p),) or rows.max(initial=-1) >= len(kept.cos_half):
        raise ValueError(f"kept_from must give one row of kept (or -1) per receiver ({len(p)})")
    changed = ~((old_c.view(np.uint64) == c.view(np.uint64)).all(axis=1)
                & (old_r.view(np.uint64) == r.view(np.uint64)) & (old_elig == elig))
    spheres = np.concatenate([np.concatenate([old_c[changed], old_r[changed, None]], axis=1),
                              np.concatenate([c[changed], r[changed, None]], axis=1)])
    todo = (rows < 0) | _reached(p, n, spheres, _UPDATE_MARGIN)
    idx = np.nonzero(todo)[0]
    counts = {"receivers": len(p), "receivers_recomputed": len(idx), "lights_changed": int(changed.sum())}
    keep = np.nonzero(~todo)[0]
    parts = [np.empty((len(p),) + old.shape[1:], dtype=old.dtype) for old in kept[1:4]]
    for old, out in zip(kept[1:4], parts):
        out[keep] = old[rows[keep]]
    if len(idx):
        sub = near_blocker_visibility(p[idx], np.asarray(normals, dtype=np.float64).reshape(-1, 3)[idx], c, r,
                                      order, n_near, eligible=eligible, exp_method=exp_method, method=method)
        for new, out in zip(sub[1:4], parts):
            out[idx] = new
    return NearVisibility(n, *parts, kept.order), counts


def _reached(points, normals, spheres, margin) -> np.ndarray:
    """``(B,) bool``: a sphere of ``spheres (M, 4)`` reaches above the receiver's tangent plane, or lies within
    ``margin`` (relative, of the lengths involved) of it (the test of :func:`near_blocker_visibility_update`)."""
    e = spheres[None, :, :3] - points[:, None]  # (B, M, 3)
    h = np.einsum("bmk,bk->bm", e, normals)
    size = (np.linalg.norm(e, axis=2) + np.abs(spheres[None, :, 3]) + np.abs(points).sum(axis=1)[:, None]
            + np.abs(spheres[None, :, :3]).sum(axis=2))
    return ~(h < -(spheres[None, :, 3] + margin * size)).all(axis=1)


def near_blocker_sums(vis: NearVisibility, env_sh, *, method: str = "numba") -> np.ndarray:
    """Direct irradiance ``(B, C)`` of :func:`near_blocker_direct` from its geometry ``vis``
    (:func:`near_blocker_visibility`) under the environment ``env_sh (N*N, C)``: ``V_rest . (T_n - Q)``."""
    if method not in ("numba", "reference"):
        raise ValueError(f"method must be 'numba' or 'reference', got {method!r}")
    env = np.asarray(env_sh, dtype=np.float64)
    n, order = vis.normals, vis.order
    B, k = vis.axis.shape[:2]
    with one_thread_below(B, _SERIAL_BELOW):
        t = environment_transfer(n, env, order) if method == "reference" else _environment_transfer(n, env, order)
        q = np.zeros_like(t)
        if B and k:
            if method == "numba":
                x, w = _RADIAL_RULE
                _cap_integrals(n, vis.axis, vis.cos_half, environment_cube(env), order, x, w, N_AZIMUTH, q)
            else:
                q = _cap_integrals_reference(n, vis.axis, vis.cos_half, env, order)
    return np.einsum("bk,bkc->bc", vis.visibility, t - q)


def _environment_transfer(normals, env, order):
    """:func:`environment_transfer` with the product ``cos_{2n-1}(n) @ M`` in a numba kernel instead of BLAS (a
    small product that BLAS threads spin on; equal to rounding)."""
    from ._shadows import transfer_matrix

    hi = 2 * order - 1
    cos = np.ascontiguousarray(sh.zh_rotate(sh.clamped_cosine_zh(hi), normals))
    m = np.ascontiguousarray(transfer_matrix(env, order))
    out = np.empty((cos.shape[0], m.shape[1]))
    if cos.shape[0]:
        _rows_times_matrix(cos, m, out)
    return out.reshape(cos.shape[0], order * order, env.shape[1])


@numba.njit(cache=True, parallel=True, error_model="numpy")
def _rows_times_matrix(rows, matrix, out):
    """``out = rows @ matrix``, rows in parallel, each a sum over the matrix's rows in order (vectorised over its
    columns)."""
    n_cols = matrix.shape[1]
    for b in numba.prange(rows.shape[0]):
        for j in range(n_cols):
            out[b, j] = 0.0
        for i in range(matrix.shape[0]):
            f = rows[b, i]
            for j in range(n_cols):
                out[b, j] += f * matrix[i, j]


def _near_split_reference(p, n, c, r, elig, order, k):
    """The numpy tier of :func:`_near_split`."""
    from ._shadows import blocker_log_sum

    e = c[None] - p[:, None]
    d2 = np.sum(e * e, axis=2)
    h = np.einsum("bsk,bk->bs", e, n)
    kept = ~((d2 < r[None] ** 2) | (h <= -r[None]) | (d2 <= 0) | (r[None] <= 0)) & elig[None]
    sin_t = np.where(kept, np.minimum(r[None] / np.sqrt(np.maximum(d2, 1e-300)), 1.0), -1.0)
    sin_t = np.where(sin_t < _min_sin(), -1.0, sin_t)
    g = np.zeros((len(p), order * order))
    axis = np.zeros((len(p), k, 3))
    axis[..., 2] = 1.0
    cosq = np.full((len(p), k), 2.0)
    for b in range(len(p)):
        ranked = [s for s in np.argsort(-sin_t[b], kind="stable") if sin_t[b, s] > 0][:k]
        for j, s in enumerate(ranked):
            axis[b, j] = e[b, s] / np.sqrt(d2[b, s])
            cosq[b, j] = math.sqrt(max(1 - sin_t[b, s] ** 2, 0.0))
        rest = np.array([s for s in range(len(r)) if s not in ranked], dtype=np.int64)
        if len(rest):
            g[b] = blocker_log_sum(p[b], n[b], c[rest], r[rest], order, method="reference")
    return g, axis, cosq

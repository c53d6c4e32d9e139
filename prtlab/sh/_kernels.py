"""Numba kernels of the SH core: basis evaluation and block rotation.

Kernels take only arrays and scalars and check nothing; the public functions
in ``_eval.py`` and ``_rotate.py`` validate, allocate and call them. Every
constant is generated here from its exact expression (no pasted literals), and
the tests hold each kernel to its float64 reference tier.
"""

from __future__ import annotations

import math

import numba
import numpy as np

# --------------------------------------------------------------------------- helpers


def kernel_array(a, dtype=np.float64) -> np.ndarray:
    """``a`` as a C-contiguous, writable array of ``dtype`` (copied only if needed).

    Numba compiles a separate specialisation for read-only or non-contiguous
    arrays; feeding kernels one array type keeps compilation to one signature.
    """
    a = np.ascontiguousarray(a, dtype=dtype)
    return a if a.flags.writeable else a.copy()


# --------------------------------------------------------------------------- constants

_PI = math.pi

# Hand-written low bands (l <= 3), unit (x, y, z); constants from K_lm.
_C00 = 0.5 * math.sqrt(1.0 / _PI)
_C1 = math.sqrt(3.0 / (4.0 * _PI))
_C2A = math.sqrt(15.0 / (4.0 * _PI))  # Y_2,-2 = C2A x y, Y_2,-1 = C2A y z, Y_2,1 = C2A x z
_C20 = math.sqrt(5.0 / (16.0 * _PI))  # Y_2,0 = C20 (3 z^2 - 1)
_C22 = math.sqrt(15.0 / (16.0 * _PI))  # Y_2,2 = C22 (x^2 - y^2)
_C33 = math.sqrt(35.0 / (32.0 * _PI))  # Y_3,+-3 = C33 {x(x^2 - 3y^2), y(3x^2 - y^2)}
_C32A = math.sqrt(105.0 / (4.0 * _PI))  # Y_3,-2 = C32A x y z
_C32B = math.sqrt(105.0 / (16.0 * _PI))  # Y_3,2 = C32B z (x^2 - y^2)
_C31 = math.sqrt(21.0 / (32.0 * _PI))  # Y_3,+-1 = C31 {x, y} (5 z^2 - 1)
_C30 = math.sqrt(7.0 / (16.0 * _PI))  # Y_3,0 = C30 z (5 z^2 - 3)

LOW_BANDS = 4  # bands l < LOW_BANDS are hand-written polynomials


def legendre_tables(order: int):
    """Coefficients of the normalised Legendre recurrence.

    With ``p_lm = N_lm P_l^m(z) / sin^m(theta)`` (``N_lm = K_lm``, times
    ``sqrt(2)`` for ``m > 0``): ``p_mm = pmm[m]``,
    ``p_lm = a[l, m] z p_(l-1)m - b[l, m] p_(l-2)m`` for ``l > m``.

    Returns
    -------
    pmm : (order,) float64
    a, b : (order, order) float64
    """
    pmm = np.zeros(order)
    a = np.zeros((order, order))
    b = np.zeros((order, order))
    pmm[0] = math.sqrt(1.0 / (4.0 * _PI))
    for m in range(1, order):
        # N_mm (2m-1)!! = sqrt((2m+1)/(4 pi) ((2m-1)!!)^2/(2m)!), ratio (2m+1)/(2m) per step.
        pmm[m] = pmm[m - 1] * math.sqrt((2 * m + 1) / (2.0 * m))
        if m == 1:
            pmm[m] *= math.sqrt(2.0)
    for m in range(order):
        for l in range(m + 1, order):
            a[l, m] = math.sqrt((4.0 * l * l - 1.0) / ((l - m) * (l + m)))
            if l >= m + 2:
                b[l, m] = math.sqrt(
                    (2.0 * l + 1.0) * (l + m - 1.0) * (l - m - 1.0) / ((2.0 * l - 3.0) * (l - m) * (l + m))
                )
    return pmm, a, b


_TABLE_ORDER = 64
_PMM, _A, _B = legendre_tables(_TABLE_ORDER)


# --------------------------------------------------------------------------- basis


@numba.njit(cache=True, inline="always")
def _low_bands(x, y, z, order, out, i):
    out[i, 0] = _C00
    if order < 2:
        return
    out[i, 1] = _C1 * y
    out[i, 2] = _C1 * z
    out[i, 3] = _C1 * x
    if order < 3:
        return
    xx = x * x
    yy = y * y
    zz = z * z
    out[i, 4] = _C2A * x * y
    out[i, 5] = _C2A * y * z
    out[i, 6] = _C20 * (3.0 * zz - 1.0)
    out[i, 7] = _C2A * x * z
    out[i, 8] = _C22 * (xx - yy)
    if order < 4:
        return
    t = 5.0 * zz - 1.0
    out[i, 9] = _C33 * y * (3.0 * xx - yy)
    out[i, 10] = _C32A * x * y * z
    out[i, 11] = _C31 * y * t
    out[i, 12] = _C30 * z * (5.0 * zz - 3.0)
    out[i, 13] = _C31 * x * t
    out[i, 14] = _C32B * z * (xx - yy)
    out[i, 15] = _C33 * x * (xx - 3.0 * yy)


@numba.njit(cache=True, inline="always")
def _high_bands(x, y, z, order, pmm, a, b, out, i):
    """Bands LOW_BANDS..order-1 by the normalised recurrence (bands below are stepped over)."""
    c = 1.0
    s = 0.0
    for m in range(order):
        if m > 0:
            c, s = c * x - s * y, c * y + s * x
        p2 = 0.0
        p1 = pmm[m]
        if m >= LOW_BANDS:
            base = m * m + m
            out[i, base + m] = p1 * c
            out[i, base - m] = p1 * s
        for l in range(m + 1, order):
            p = a[l, m] * z * p1 - b[l, m] * p2
            p2 = p1
            p1 = p
            if l >= LOW_BANDS:
                base = l * l + l
                if m == 0:
                    out[i, base] = p
                else:
                    out[i, base + m] = p * c
                    out[i, base - m] = p * s


@numba.njit(cache=True, parallel=True, nogil=True)
def _sh_basis(dirs, order, pmm, a, b, out):
    n = dirs.shape[0]
    n_bad = 0
    for i in numba.prange(n):
        x = dirs[i, 0]
        y = dirs[i, 1]
        z = dirs[i, 2]
        r2 = x * x + y * y + z * z
        if r2 > 0.0 and r2 < np.inf:
            inv = 1.0 / math.sqrt(r2)
            x *= inv
            y *= inv
            z *= inv
            _low_bands(x, y, z, order, out, i)
            if order > LOW_BANDS:
                _high_bands(x, y, z, order, pmm, a, b, out, i)
        else:
            n_bad += 1
            for k in range(order * order):
                out[i, k] = np.nan
    return n_bad


def sh_basis(dirs: np.ndarray, order: int, out: np.ndarray) -> int:
    """Fill ``out (N, order**2)`` with the SH of ``dirs (N, 3)``; returns the number of invalid rows.

    A row is invalid (and set to NaN) if its direction is zero or not finite.
    """
    if order <= _TABLE_ORDER:
        pmm, a, b = _PMM, _A, _B
    else:
        pmm, a, b = legendre_tables(order)
    return int(_sh_basis(dirs, order, pmm, a, b, out))


# --------------------------------------------------------------------------- rotation (Ivanic-Ruedenberg)


def block_offsets(order: int) -> np.ndarray:
    """(order + 1,) int64: start of band l's ``(2l+1)^2`` block in the packed layout."""
    sizes = (2 * np.arange(order) + 1) ** 2
    return np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)


@numba.njit(cache=True)
def _blk(blocks, r, off, l, m, mp):
    """Entry (m, m') of band l's block, m and m' in -l..l."""
    d = 2 * l + 1
    return blocks[r, off + (m + l) * d + (mp + l)]


@numba.njit(cache=True)
def _ir_p(blocks, r, off1, offp, l, i, a, bb):
    """Ivanic-Ruedenberg P(i, l, a, b) from the band-1 block and band l-1's block."""
    r1 = _blk(blocks, r, off1, 1, i, 1)
    rm1 = _blk(blocks, r, off1, 1, i, -1)
    if bb == l:
        return r1 * _blk(blocks, r, offp, l - 1, a, l - 1) - rm1 * _blk(blocks, r, offp, l - 1, a, -l + 1)
    elif bb == -l:
        return r1 * _blk(blocks, r, offp, l - 1, a, -l + 1) + rm1 * _blk(blocks, r, offp, l - 1, a, l - 1)
    else:
        return _blk(blocks, r, off1, 1, i, 0) * _blk(blocks, r, offp, l - 1, a, bb)


@numba.njit(cache=True, nogil=True)
def ivanic_ruedenberg(rot, order, offsets, blocks):
    """Packed per-band rotation blocks of ``rot (B, 3, 3)`` into ``blocks (B, offsets[order])``.

    Band 1 is ``P R P^T`` with ``P`` the (y, z, x) permutation; bands l >= 2 by
    the recurrence of Ivanic & Ruedenberg (1996, Tables 1-2, with the 1998 erratum).
    Serial: a few microseconds per rotation at order 4 (a parallel loop here
    tripled the compile time for no measurable gain at typical batch sizes).
    """
    for r in range(rot.shape[0]):
        _ivanic_ruedenberg_one(rot, r, order, offsets, blocks)


@numba.njit(cache=True)
def _ivanic_ruedenberg_one(rot, r, order, offsets, blocks):
    """Blocks of rotation ``r`` (kept out of the parallel loop: compiles fast)."""
    blocks[r, 0] = 1.0
    if order >= 2:
        # (y, z, x) <- (1, 2, 0)
        perm = (1, 2, 0)
        for a in range(3):
            for bb in range(3):
                blocks[r, 1 + a * 3 + bb] = rot[r, perm[a], perm[bb]]
        off1 = offsets[1]
        for l in range(2, order):
            off = offsets[l]
            offp = offsets[l - 1]
            d = 2 * l + 1
            for m in range(-l, l + 1):
                am = abs(m)
                for mp in range(-l, l + 1):
                    if abs(mp) < l:
                        denom = float((l + mp) * (l - mp))
                    else:
                        denom = float((2 * l) * (2 * l - 1))
                    dm0 = 1.0 if m == 0 else 0.0
                    u = math.sqrt((l + m) * (l - m) / denom)
                    v = 0.5 * math.sqrt((1.0 + dm0) * (l + am - 1) * (l + am) / denom) * (1.0 - 2.0 * dm0)
                    w = -0.5 * math.sqrt((l - am - 1) * (l - am) / denom) * (1.0 - dm0)
                    val = 0.0
                    if u != 0.0:
                        val += u * _ir_p(blocks, r, off1, offp, l, 0, m, mp)
                    if v != 0.0:
                        if m == 0:
                            vv = _ir_p(blocks, r, off1, offp, l, 1, 1, mp) + _ir_p(blocks, r, off1, offp, l, -1, -1, mp)
                        elif m > 0:
                            if m == 1:
                                vv = _ir_p(blocks, r, off1, offp, l, 1, 0, mp) * math.sqrt(2.0)
                            else:
                                vv = _ir_p(blocks, r, off1, offp, l, 1, m - 1, mp) - _ir_p(
                                    blocks, r, off1, offp, l, -1, -m + 1, mp
                                )
                        else:
                            if m == -1:
                                vv = _ir_p(blocks, r, off1, offp, l, -1, 0, mp) * math.sqrt(2.0)
                            else:
                                vv = _ir_p(blocks, r, off1, offp, l, 1, m + 1, mp) + _ir_p(
                                    blocks, r, off1, offp, l, -1, -m - 1, mp
                                )
                        val += v * vv
                    if w != 0.0:
                        if m > 0:
                            ww = _ir_p(blocks, r, off1, offp, l, 1, m + 1, mp) + _ir_p(
                                blocks, r, off1, offp, l, -1, -m - 1, mp
                            )
                        else:
                            ww = _ir_p(blocks, r, off1, offp, l, 1, m - 1, mp) - _ir_p(
                                blocks, r, off1, offp, l, -1, -m + 1, mp
                            )
                        val += w * ww
                    blocks[r, off + (m + l) * d + (mp + l)] = val


_TILE = 64  # vectors per tile in apply_blocks


@numba.njit(cache=True, parallel=True, nogil=True)
def apply_blocks(blocks, offsets, rot_index, coeffs, out):
    """``out[i, band l, c] = block_l(rot_index[i]) @ coeffs[i, band l, c]`` for ``coeffs (N, n*n, C)``.

    Vectors are processed in tiles of ``_TILE``; a tile is transposed into a
    ``(n*n, tile * C)`` buffer so that, when the whole tile shares one rotation
    (the common case), the inner loop runs over contiguous columns (SIMD)
    instead of a serial dot product. Summation order is the same in both paths.
    """
    n = coeffs.shape[0]
    k = coeffs.shape[1]
    nc = coeffs.shape[2]
    order = offsets.shape[0] - 1
    n_tiles = (n + _TILE - 1) // _TILE
    for t in numba.prange(n_tiles):
        start = t * _TILE
        stop = min(start + _TILE, n)
        width = (stop - start) * nc
        src = np.empty((k, _TILE * nc))
        dst = np.empty((k, _TILE * nc))
        for j in range(stop - start):
            for q in range(k):
                for c in range(nc):
                    src[q, j * nc + c] = coeffs[start + j, q, c]
        r0 = rot_index[start]
        shared = True
        for j in range(start, stop):
            if rot_index[j] != r0:
                shared = False
        if shared:
            blk = blocks[r0]
            for col in range(width):
                dst[0, col] = blk[0] * src[0, col]
            for l in range(1, order):
                d, base, off = 2 * l + 1, l * l, offsets[l]  # band l: size, first index, block offset
                for a in range(d):
                    row = off + a * d
                    w = blk[row]
                    for col in range(width):
                        dst[base + a, col] = w * src[base, col]
                    for bb in range(1, d):
                        w = blk[row + bb]
                        for col in range(width):
                            dst[base + a, col] += w * src[base + bb, col]
        else:
            for col in range(width):
                blk = blocks[rot_index[start + col // nc]]
                dst[0, col] = blk[0] * src[0, col]
                for l in range(1, order):
                    d, base, off = 2 * l + 1, l * l, offsets[l]  # band l: size, first index, block offset
                    for a in range(d):
                        row = off + a * d
                        acc = blk[row] * src[base, col]
                        for bb in range(1, d):
                            acc += blk[row + bb] * src[base + bb, col]
                        dst[base + a, col] = acc
        for j in range(stop - start):
            for q in range(k):
                for c in range(nc):
                    out[start + j, q, c] = dst[q, j * nc + c]

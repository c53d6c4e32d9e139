"""Numba kernels of the SH algebra: sparse Gaunt products, product matrices, OL / HYB exponentials.

Kernels take only contiguous float64 / int64 arrays and scalars and check
nothing; the public functions in ``_product.py`` and ``_explog.py`` validate,
reshape to ``(batch, coefficients, channels)`` and allocate. Every kernel has a
float64 numpy reference tier next to its caller.
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__: list[str] = []


#: Batch items processed together by the product kernels: the inner loop runs
#: over a tile of items (SIMD-friendly), the tile's coefficients stay in L1.
_TILE = 64


@numba.njit(cache=True, inline="always")
def _tile_product_prefix(at, bt, gi, gj, gk, gv, ot, width):
    """``ot[k, q] = sum_e gv[e] at[gi[e], q] bt[gj[e], q]`` over the first ``width`` items q of a tile (those
    columns of ot zeroed here, the others untouched)."""
    for k in range(ot.shape[0]):
        for q in range(width):
            ot[k, q] = 0.0
    for e in range(gv.shape[0]):
        i = gi[e]
        j = gj[e]
        k = gk[e]
        v = gv[e]
        for q in range(width):
            ot[k, q] += v * at[i, q] * bt[j, q]


@numba.njit(cache=True)
def _tile_product(at, bt, gi, gj, gk, gv, ot):
    """``ot[k, q] = sum_e gv[e] at[gi[e], q] bt[gj[e], q]`` over a tile of items q (ot zeroed here)."""
    _tile_product_prefix(at, bt, gi, gj, gk, gv, ot, ot.shape[1])


@numba.njit(cache=True, parallel=True, nogil=True)
def _sparse_product(a, b, gi, gj, gk, gv, out):
    """Batched SH product over the sparse Gaunt tensor.

    a : (B, na2, C), b : (B, nb2, C), out : (B, nc2, C); (gi, gj, gk, gv) the
    COO entries with ``gi < na2, gj < nb2, gk < nc2``. Parallel over tiles of
    ``_TILE`` items times channels; each tile is transposed to
    ``(coefficients, items)`` so the innermost loop runs over items.
    """
    n_items, nc2, n_chan = out.shape
    na2 = a.shape[1]
    nb2 = b.shape[1]
    tile = max(1, min(_TILE, n_items))  # no idle lanes for small batches
    n_tiles = (n_items + tile - 1) // tile
    for task in numba.prange(n_tiles * n_chan):
        c = task % n_chan
        start = (task // n_chan) * tile
        width = min(tile, n_items - start)
        at = np.zeros((na2, tile))
        bt = np.zeros((nb2, tile))
        ot = np.empty((nc2, tile))
        for q in range(width):
            for i in range(na2):
                at[i, q] = a[start + q, i, c]
            for j in range(nb2):
                bt[j, q] = b[start + q, j, c]
        _tile_product(at, bt, gi, gj, gk, gv, ot)
        for q in range(width):
            for k in range(nc2):
                out[start + q, k, c] = ot[k, q]


@numba.njit(cache=True, parallel=True)
def _sparse_product_matrix(f, gi, gj, gk, gv, out):
    """``out[t, k, j] = sum_i G_ijk f[t, i]``: f (B, nf2), out (B, n2, n2)."""
    for t in numba.prange(out.shape[0]):
        out[t, :, :] = 0.0
        for e in range(gv.shape[0]):
            out[t, gk[e], gj[e]] += gv[e] * f[t, gi[e]]


@numba.njit(cache=True)
def _ol_one(f, r_max, tab_a, tab_b, out):
    """Optimal-linear exponential of one coefficient vector per channel, with DC isolation.

    f, out : (n2, C). ``exp*(f) ~ exp(f_0 / sqrt(4 pi)) (a(|fh|) 1 + b(|fh|) fh)``
    with ``a, b`` linearly interpolated (in ``r``) from tables on knots
    ``r_j = r_max (j / (K - 1))^2`` and clamped beyond ``r_max``.
    """
    n2 = f.shape[0]
    sqrt4pi = math.sqrt(4.0 * math.pi)
    n_tab = tab_a.shape[0]
    for c in range(f.shape[1]):
        norm2 = 0.0
        for i in range(1, n2):
            norm2 += f[i, c] * f[i, c]
        r = math.sqrt(norm2)
        if r >= r_max:
            a = tab_a[n_tab - 1]
            b = tab_b[n_tab - 1]
        else:
            j = min(int(math.sqrt(r / r_max) * (n_tab - 1)), n_tab - 2)
            r0 = r_max * (j / (n_tab - 1)) ** 2
            r1 = r_max * ((j + 1) / (n_tab - 1)) ** 2
            s = (r - r0) / (r1 - r0)
            a = (1.0 - s) * tab_a[j] + s * tab_a[j + 1]
            b = (1.0 - s) * tab_b[j] + s * tab_b[j + 1]
        scale = math.exp(f[0, c] / sqrt4pi)
        out[0, c] = scale * a * sqrt4pi
        for i in range(1, n2):
            out[i, c] = scale * b * f[i, c]


@numba.njit(cache=True, parallel=True)
def _exp_ol(f, r_max, tab_a, tab_b, out):
    """Batched OL exponential: f, out (B, n2, C)."""
    for t in numba.prange(f.shape[0]):
        _ol_one(f[t], r_max, tab_a, tab_b, out[t])


@numba.njit(cache=True, parallel=True)
def _exp_hyb(f, r_max, tab_a, tab_b, threshold, gi, gj, gk, gv, out):
    """Batched hybrid exponential (scaling and squaring over OL): f, out (B, n2, C).

    Per vector and channel: ``k = max(0, ceil(log2(|fh| / threshold)))``,
    ``v = OL(fh / 2^k)``, then ``v <- v * v`` (SH product truncated to the
    order) ``k`` times, then the DC factor ``exp(f_0 / sqrt(4 pi))``. Tiled as
    :func:`_sparse_product`: all lanes of a tile are squared together and a
    lane keeps its square only while it still needs squarings.
    """
    n_items, n2, n_chan = f.shape
    sqrt4pi = math.sqrt(4.0 * math.pi)
    tile = max(1, min(_TILE, n_items))
    n_tiles = (n_items + tile - 1) // tile
    for task in numba.prange(n_tiles * n_chan):
        c = task % n_chan
        start = (task // n_chan) * tile
        width = min(tile, n_items - start)
        h = np.zeros((n2, 1))
        v1 = np.empty((n2, 1))
        vt = np.zeros((n2, tile))
        wt = np.empty((n2, tile))
        ks = np.zeros(tile, dtype=np.int64)
        k_max = 0
        for q in range(width):
            norm2 = 0.0
            for i in range(1, n2):
                norm2 += f[start + q, i, c] * f[start + q, i, c]
            norm = math.sqrt(norm2)
            k = 0
            if norm > threshold:
                k = max(0, int(math.ceil(math.log2(norm / threshold))))
                while norm / 2.0**k > threshold:  # guard against rounding in log2
                    k += 1
            ks[q] = k
            k_max = max(k_max, k)
            scale = 1.0 / 2.0**k
            for i in range(1, n2):
                h[i, 0] = f[start + q, i, c] * scale
            _ol_one(h, r_max, tab_a, tab_b, v1)
            for i in range(n2):
                vt[i, q] = v1[i, 0]
        for step in range(k_max):
            _tile_product(vt, vt, gi, gj, gk, gv, wt)
            for q in range(width):
                if step < ks[q]:
                    for i in range(n2):
                        vt[i, q] = wt[i, q]
        for q in range(width):
            dc = math.exp(f[start + q, 0, c] / sqrt4pi)
            for i in range(n2):
                out[start + q, i, c] = dc * vt[i, q]

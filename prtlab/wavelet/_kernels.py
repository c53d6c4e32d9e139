"""Numba kernels of the wavelet subpackage: 2D Haar transforms, Haar triple
products and products, and the per-vertex sparse dot product.

Kernels take only C-contiguous float64 arrays (and the integer arrays of the
sparse container) and check nothing; the public functions in ``_haar.py``,
``_triple.py`` and ``_quantize.py`` validate, allocate and call them. Faces are
flattened to ``(F, r, r)``; every kernel is a ``prange`` over faces (or
vertices), with no ``fastmath``.

Layout of one face's coefficients (see :func:`prtlab.wavelet.haar2d`): ``[0, 0]``
the scaling coefficient; the node ``(p, q)`` of level ``l`` (``h = 2**l``) keeps
its three wavelets at ``[p, h + q]`` (type "01", varies along the column
index j), ``[h + p, q]`` (type "10", varies along the row index i) and
``[h + p, h + q]`` (type "11"). On the quadrant ``(di, dj)`` of the node the
wavelets have the signs ``s01 = (-1)**dj``, ``s10 = (-1)**di``,
``s11 = (-1)**(di + dj)``, so ``s01 * s10 * s11 = 1``.
"""

from __future__ import annotations

import numba
import numpy as np

# --------------------------------------------------------------------------- transforms


@numba.njit(cache=True, inline="always")
def _details(f, p, q, h, inv_r):
    """The three detail coefficients of the square ``(p, q)`` at level ``h`` (horizontal, vertical,
    diagonal), scaled by ``inv_r``."""
    return f[p, h + q] * inv_r, f[h + p, q] * inv_r, f[h + p, h + q] * inv_r


@numba.njit(cache=True, parallel=True)
def haar_forward(faces, out):
    """Orthonormal non-standard 2D Haar transform of ``faces (F, r, r)`` into ``out``."""
    n_faces = faces.shape[0]
    r = faces.shape[1]
    for f in numba.prange(n_faces):
        if r == 1:
            out[f, 0, 0] = faces[f, 0, 0]
            continue
        src = faces[f]
        dst = out[f]
        work = np.empty((r // 2, r // 2))
        n = r
        first = True
        while n > 1:
            h = n // 2
            for p in range(h):
                for q in range(h):
                    if first:
                        a = src[2 * p, 2 * q]
                        b = src[2 * p, 2 * q + 1]
                        c = src[2 * p + 1, 2 * q]
                        d = src[2 * p + 1, 2 * q + 1]
                    else:
                        a = work[2 * p, 2 * q]
                        b = work[2 * p, 2 * q + 1]
                        c = work[2 * p + 1, 2 * q]
                        d = work[2 * p + 1, 2 * q + 1]
                    dst[p, h + q] = 0.5 * ((a - b) + (c - d))
                    dst[h + p, q] = 0.5 * ((a + b) - (c + d))
                    dst[h + p, h + q] = 0.5 * ((a - b) - (c - d))
                    # in place is safe: (p, q) is read by block (p//2, q//2), already done
                    work[p, q] = 0.5 * ((a + b) + (c + d))
            first = False
            n = h
        dst[0, 0] = work[0, 0]


@numba.njit(cache=True, inline="always")
def _inverse_block(s, d01, d10, d11, dst, p, q):
    dst[2 * p, 2 * q] = 0.5 * ((s + d01) + (d10 + d11))
    dst[2 * p, 2 * q + 1] = 0.5 * ((s - d01) + (d10 - d11))
    dst[2 * p + 1, 2 * q] = 0.5 * ((s + d01) - (d10 + d11))
    dst[2 * p + 1, 2 * q + 1] = 0.5 * ((s - d01) - (d10 - d11))


@numba.njit(cache=True, parallel=True)
def haar_inverse(coeffs, out):
    """Inverse of :func:`haar_forward` (its transpose): ``coeffs (F, r, r)`` into ``out``."""
    n_faces = coeffs.shape[0]
    r = coeffs.shape[1]
    for f in numba.prange(n_faces):
        src = coeffs[f]
        dst = out[f]
        if r == 1:
            dst[0, 0] = src[0, 0]
            continue
        # coarse levels in a small scratch, in place in reverse order (block (p, q)
        # overwrites scaling values of blocks >= (p, q), which have been read already)
        work = np.empty((r // 2, r // 2))
        work[0, 0] = src[0, 0]
        h = 1
        while 2 * h < r:
            for p in range(h - 1, -1, -1):
                for q in range(h - 1, -1, -1):
                    _inverse_block(work[p, q], src[p, h + q], src[h + p, q], src[h + p, h + q], work, p, q)
            h *= 2
        # finest level straight into the output, in memory order
        for p in range(h):
            for q in range(h):
                _inverse_block(work[p, q], src[p, h + q], src[h + p, q], src[h + p, h + q], dst, p, q)


# --------------------------------------------------------------------------- triple products


@numba.njit(cache=True, inline="always")
def _child_means(mean, h, p, q, scale, d01, d10, d11, nxt):
    """Means of the four children of node (p, q): ``mean + scale * sum_t d_t s_t(quadrant)``."""
    nxt[2 * p, 2 * q] = mean + scale * ((d01 + d10) + d11)
    nxt[2 * p, 2 * q + 1] = mean + scale * ((-d01 + d10) - d11)
    nxt[2 * p + 1, 2 * q] = mean + scale * ((d01 - d10) - d11)
    nxt[2 * p + 1, 2 * q + 1] = mean + scale * ((-d01 - d10) + d11)


@numba.njit(cache=True, inline="always")
def _root_mean(face, inv_r):
    """An ``(r, r)`` buffer for a face's node means with the root's (``face[0, 0] / r``) set."""
    r = face.shape[0]
    means = np.empty((r, r))
    means[0, 0] = face[0, 0] * inv_r
    return means


@numba.njit(cache=True, inline="always")
def _triple_level(fa, fb, fc, ma, mb, mc, h, inv_r, last, total):
    """``total`` plus the terms of the level-``h`` nodes in :func:`haar_triple`; unless ``last``, the
    node means ``ma, mb, mc`` move down to the children."""
    lev = float(h)
    for p in range(h - 1, -1, -1):
        for q in range(h - 1, -1, -1):
            a01, a10, a11 = _details(fa, p, q, h, inv_r)
            b01, b10, b11 = _details(fb, p, q, h, inv_r)
            c01, c10, c11 = _details(fc, p, q, h, inv_r)
            am = ma[p, q]
            bm = mb[p, q]
            cm = mc[p, q]
            pairs = (a01 * b01 + a10 * b10 + a11 * b11) * cm
            pairs += (a01 * c01 + a10 * c10 + a11 * c11) * bm
            pairs += (b01 * c01 + b10 * c10 + b11 * c11) * am
            distinct = (
                a01 * (b10 * c11 + b11 * c10)
                + a10 * (b01 * c11 + b11 * c01)
                + a11 * (b01 * c10 + b10 * c01)
            )
            total += pairs + lev * distinct
            if not last:
                _child_means(am, h, p, q, lev, a01, a10, a11, ma)
                _child_means(bm, h, p, q, lev, b01, b10, b11, mb)
                _child_means(cm, h, p, q, lev, c01, c10, c11, mc)
    return total


@numba.njit(cache=True, parallel=True)
def haar_triple(a, b, c, out):
    """Per-face ``int_[0,1]^2 f g h`` of three Haar-coded faces ``(F, r, r)`` into ``out (F,)``.

    Tripling-coefficient rules of Ng et al. 2004 in the continuous orthonormal
    basis of the unit face (coefficients ``alpha = a / r``), summed in one
    top-down pass over the quadtree that carries each function's mean on the
    current node (its projection on the scaling functions of that level, i.e.
    the sum over the node's ancestors):

        int f g h = a0 b0 c0
                  + sum_nodes sum_t (a_t b_t C + a_t c_t B + b_t c_t A)
                  + sum_nodes 2**l sum_{t1 != t2 != t3} a_t1 b_t2 c_t3

    with ``A, B, C`` the means of f, g, h on the node (level l).
    """
    r = a.shape[1]
    inv_r = 1.0 / r
    for f in numba.prange(a.shape[0]):
        fa, fb, fc = a[f], b[f], c[f]
        ma, mb, mc = _root_mean(fa, inv_r), _root_mean(fb, inv_r), _root_mean(fc, inv_r)
        total = ma[0, 0] * mb[0, 0] * mc[0, 0]
        h = 1
        while h < r:
            total = _triple_level(fa, fb, fc, ma, mb, mc, h, inv_r, 2 * h == r, total)
            h *= 2
        out[f] = total


@numba.njit(cache=True, parallel=True)
def haar_product(a, b, out):
    """Haar coefficients ``(F, r, r)`` of the product of two Haar-coded faces.

    For the wavelet of type t at node S (level l), with ``A, B`` the means of
    f, g on S and ``E(D)`` the sum of ``alpha_w beta_w`` over the wavelets w of
    the subtree rooted at D::

        (fg)_t = alpha_t B + beta_t A + 2**l (alpha_t1 beta_t2 + alpha_t2 beta_t1)
               + 2**l sum_quadrants s_t(quadrant) E(child)

    and ``(fg)_0 = alpha_0 beta_0 + E(root)`` (Parseval). A top-down pass
    writes the first three terms, a bottom-up pass adds the last one.
    """
    n_faces = a.shape[0]
    r = a.shape[1]
    inv_r = 1.0 / r
    for f in numba.prange(n_faces):
        fa = a[f]
        fb = b[f]
        dst = out[f]
        ma = np.empty((r, r))
        mb = np.empty((r, r))
        ma[0, 0] = fa[0, 0] * inv_r
        mb[0, 0] = fb[0, 0] * inv_r
        dst[0, 0] = ma[0, 0] * mb[0, 0]
        # top-down: the ancestor (mean) terms and the three-distinct-types terms
        h = 1
        while h < r:
            lev = float(h)
            last = 2 * h == r
            for p in range(h - 1, -1, -1):
                for q in range(h - 1, -1, -1):
                    a01, a10, a11 = _details(fa, p, q, h, inv_r)
                    b01, b10, b11 = _details(fb, p, q, h, inv_r)
                    am = ma[p, q]
                    bm = mb[p, q]
                    dst[p, h + q] = a01 * bm + b01 * am + lev * (a10 * b11 + a11 * b10)
                    dst[h + p, q] = a10 * bm + b10 * am + lev * (a01 * b11 + a11 * b01)
                    dst[h + p, h + q] = a11 * bm + b11 * am + lev * (a01 * b10 + a10 * b01)
                    if not last:
                        _child_means(am, h, p, q, lev, a01, a10, a11, ma)
                        _child_means(bm, h, p, q, lev, b01, b10, b11, mb)
            h *= 2
        # bottom-up: subtree sums E of alpha_w beta_w; ma is reused as E storage
        energy = ma
        h = r // 2
        while h >= 1:
            lev = float(h)
            leaf = 2 * h == r
            for p in range(h):
                for q in range(h):
                    own = (
                        fa[p, h + q] * fb[p, h + q]
                        + fa[h + p, q] * fb[h + p, q]
                        + fa[h + p, h + q] * fb[h + p, h + q]
                    ) * (inv_r * inv_r)
                    if leaf:
                        energy[p, q] = own
                        continue
                    e00 = energy[2 * p, 2 * q]
                    e01 = energy[2 * p, 2 * q + 1]
                    e10 = energy[2 * p + 1, 2 * q]
                    e11 = energy[2 * p + 1, 2 * q + 1]
                    dst[p, h + q] += lev * ((e00 - e01) + (e10 - e11))
                    dst[h + p, q] += lev * ((e00 + e01) - (e10 + e11))
                    dst[h + p, h + q] += lev * ((e00 - e01) - (e10 - e11))
                    # in place is safe: (p, q) is read by block (p//2, q//2), already done
                    energy[p, q] = own + ((e00 + e01) + (e10 + e11))
            h //= 2
        if r > 1:
            dst[0, 0] += energy[0, 0]
        for i in range(r):
            for j in range(r):
                dst[i, j] *= r


# --------------------------------------------------------------------------- sparse transfer


@numba.njit(cache=True, parallel=True)
def sparse_dot(indptr, indices, codes, scale, basis, sign_bit, light_pulse, light_haar, out):
    """Per-vertex dot product of the 8-bit sparse transfer with a light.

    ``indptr (V+1,)``, ``indices (E,)`` unsigned (the top bit ``sign_bit`` marks a
    negative code), ``codes (E,) uint8``, ``scale (V,) float32``, ``basis (V,) uint8``
    (0 pulse, 1 Haar), ``light_* (N, C)``, ``out (V, C)``::

        out[v] = scale[v] / 255 * sum_e (+-codes[e]) light_basis(v)[index(e)]
    """
    n_vertices = indptr.shape[0] - 1
    n_channels = out.shape[1]
    low = sign_bit - 1
    for v in numba.prange(n_vertices):
        light = light_haar if basis[v] == 1 else light_pulse
        for ch in range(n_channels):
            out[v, ch] = 0.0
        for e in range(indptr[v], indptr[v + 1]):
            raw = np.int64(indices[e])
            k = raw & low
            w = np.float64(codes[e])
            if raw >= sign_bit:
                w = -w
            for ch in range(n_channels):
                out[v, ch] += w * light[k, ch]
        s = np.float64(scale[v]) / 255.0
        for ch in range(n_channels):
            out[v, ch] *= s

"""The real Gaunt (triple product) tensor of prtlab's real SH basis.

``G_ijk = int_S2 Y_i(w) Y_j(w) Y_k(w) dw`` for the real orthonormal basis of
:mod:`prtlab.sh` (index ``i = l*l + l + m``, no Condon-Shortley phase,
polar axis z). Computed once per order by a product quadrature that is exact
for the integrands (they are polynomials of degree ``<= 3 (n - 1)`` restricted
to the sphere), stored sparsely and cached in memory.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from prtlab._validate import check_order

from ._eval import basis_reference
from ._project import quadrature

__all__ = ["GauntTensor", "gaunt_tensor"]

#: Entries whose quadrature value is below this are zero (they are exact zeros:
#: accidental zeros of the Wigner 3j symbols; quadrature noise is ~1e-17, the
#: smallest true non-zero real Gaunt coefficient up to order 16 is ~1e-4).
_ZERO = 1e-12


def _band_index(order: int) -> tuple[np.ndarray, np.ndarray]:
    """``l`` and ``m`` of every coefficient index ``i = l*l + l + m`` below ``order**2``."""
    l = np.repeat(np.arange(order), 2 * np.arange(order) + 1)
    m = np.arange(order * order) - l * l - l
    return l, m


def _selection_rules(l1, m1, l2, m2, l3, m3) -> np.ndarray:
    """True where the real Gaunt coefficient may be non-zero (broadcasting int arrays).

    ``l1 + l2 + l3`` even, triangle inequality on ``l``; on ``|m|`` one of them
    is the sum or difference of the other two (``|m1| = |m2| +- |m3|`` in some
    order), and an even number of the three are sine-type (``m < 0``).
    """
    a1, a2, a3 = np.abs(m1), np.abs(m2), np.abs(m3)
    l_ok = ((l1 + l2 + l3) % 2 == 0) & (l3 <= l1 + l2) & (l3 >= np.abs(l1 - l2))
    m_ok = (a1 == a2 + a3) | (a2 == a1 + a3) | (a3 == a1 + a2)
    parity_ok = ((m1 < 0).astype(int) + (m2 < 0) + (m3 < 0)) % 2 == 0
    return l_ok & m_ok & parity_ok


@dataclass(frozen=True, eq=False)
class GauntTensor:
    """Sparse real Gaunt tensor ``G_ijk = int Y_i Y_j Y_k dw`` of one order (COO format).

    Attributes
    ----------
    order : int
        Number of bands ``n``; indices run over ``0 .. n*n - 1``.
    i, j, k : (nnz,) int64
        Coefficient indices ``l*l + l + m`` of the three factors.
    value : (nnz,) float64
        ``G_ijk``.

    Notes
    -----
    The tensor is totally symmetric and **every** non-zero entry is listed,
    all permutations expanded: ``(i, j, k)``, ``(j, i, k)``, ... each appear
    once (a permutation that maps an entry to itself appears once, not twice).
    Entries are sorted by ``(k, i, j)``, so the entries that contribute to
    output coefficient ``k`` of a product ``c_k = sum_ij G_ijk a_i b_j`` are
    contiguous. Arrays are read-only (the tensor is cached and shared).
    """

    order: int
    i: np.ndarray
    j: np.ndarray
    k: np.ndarray
    value: np.ndarray

    @property
    def nnz(self) -> int:
        """Number of listed (non-zero) entries."""
        return int(self.value.shape[0])

    def dense(self) -> np.ndarray:
        """The dense tensor, shape ``(n*n, n*n, n*n)`` float64 (a fresh, writable array)."""
        n2 = self.order * self.order
        g = np.zeros((n2, n2, n2))
        g[self.i, self.j, self.k] = self.value
        return g

    def __repr__(self) -> str:
        return f"GauntTensor(order={self.order}, nnz={self.nnz})"


def gaunt_tensor(order: int) -> GauntTensor:
    """The sparse real Gaunt tensor of ``order`` (cached in memory).

    Parameters
    ----------
    order : int
        Number of bands ``n >= 1``: indices ``0 .. n*n - 1``. Orders up to
        about 16 are cheap (the cost grows as ``n**8``: order 8 takes
        milliseconds, order 16 a few seconds).

    Returns
    -------
    GauntTensor
        COO arrays ``i, j, k, value`` of every non-zero ``G_ijk``, all
        permutations expanded; see :class:`GauntTensor`.

    Notes
    -----
    .. math::

        G_{ijk} = \\int_{S^2} Y_i(\\omega) Y_j(\\omega) Y_k(\\omega)\\, d\\omega

    for the design's real orthonormal basis (``Y_00 = 1 / sqrt(4 pi)``, so
    ``G_{0jk} = delta_jk / sqrt(4 pi)``). The product of two band-limited
    functions is ``(fg)_k = sum_ij G_ijk f_i g_j``.

    The integrand is a polynomial of degree ``l1 + l2 + l3 <= 3 (n - 1)`` on
    the sphere, so a Gauss-Legendre (``3n/2`` nodes in ``z``) times uniform
    (``3n - 2`` angles in ``phi``) product rule integrates it exactly up to
    rounding. Non-zero entries obey the selection rules: ``l1 + l2 + l3``
    even, ``|l1 - l2| <= l3 <= l1 + l2``, ``|m|`` of one factor equal to the
    sum or difference of the other two, an even number of sine-type
    (``m < 0``) factors. Entries allowed by these rules but below ``1e-12``
    (accidental zeros of the Wigner 3j symbol) are dropped. Cross-checked
    against ``sympy.physics.wigner.real_gaunt`` in the tests.

    References
    ----------
    Ng, Ramamoorthi, Hanrahan 2004, "Triple product wavelet integrals for
    all-frequency relighting", Sec. 4 (SH triple products). Homeier and Steinborn 1996,
    "Some properties of the coupling coefficients of real spherical harmonics".

    Examples
    --------
    >>> g = gaunt_tensor(2)
    >>> g.nnz, round(float(g.value[0] * np.sqrt(4 * np.pi)), 12)
    (10, 1.0)
    """
    return _gaunt_cached(check_order(order))


@functools.lru_cache(maxsize=None)
def _gaunt_cached(order: int) -> GauntTensor:
    n2 = order * order
    dirs, weights = quadrature(1, degree=3 * (order - 1))
    y = basis_reference(dirs, order)  # (N, n2)
    yw = y * weights[:, None]
    l, m = _band_index(order)
    ii, jj, kk, vv = [], [], [], []
    chunk = max(1, (1 << 22) // (y.shape[0] * n2))  # output slices per GEMM (bounds memory)
    for k0 in range(0, n2, chunk):
        k1 = min(n2, k0 + chunk)
        # G[:, :, k0:k1] as one GEMM: rows (k, i), columns j
        lhs = (yw[:, None, :] * y[:, k0:k1, None]).reshape(y.shape[0], -1)
        g_k = (lhs.T @ y).reshape(k1 - k0, n2, n2)
        kidx = np.arange(k0, k1)[:, None, None]
        allowed = _selection_rules(l[None, :, None], m[None, :, None], l[None, None, :], m[None, None, :],
                                   l[kidx], m[kidx])
        k_idx, i_idx, j_idx = np.nonzero(allowed & (np.abs(g_k) > _ZERO))
        ii.append(i_idx)
        jj.append(j_idx)
        kk.append(k_idx + k0)
        vv.append(g_k[k_idx, i_idx, j_idx])
    arrays = [np.concatenate(a).astype(np.int64) for a in (ii, jj, kk)]
    value = np.concatenate(vv).astype(np.float64)
    # exact permutation symmetry: every entry takes the value computed for its sorted triple
    srt = np.sort(np.stack(arrays), axis=0)
    key = (srt[0] * n2 + srt[1]) * n2 + srt[2]
    own = (arrays[0] * n2 + arrays[1]) * n2 + arrays[2]
    canonical = own == key
    order_c = np.argsort(own[canonical])
    value = value[canonical][order_c][np.searchsorted(own[canonical][order_c], key)]
    for a in (*arrays, value):
        a.setflags(write=False)
    return GauntTensor(order, arrays[0], arrays[1], arrays[2], value)


@functools.lru_cache(maxsize=None)
def _gaunt_block(na: int, nb: int, nc: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Entries of ``G`` with ``i < na**2, j < nb**2, k < nc**2`` as int64/float64 arrays, sorted by k.

    These drive a product of an order-``na`` with an order-``nb`` function
    truncated to order ``nc``.
    """
    g = _gaunt_cached(max(na, nb, nc))
    keep = (g.i < na * na) & (g.j < nb * nb) & (g.k < nc * nc)
    out = tuple(np.ascontiguousarray(a[keep]) for a in (g.i, g.j, g.k, g.value))
    for a in out:
        a.setflags(write=False)
    return out

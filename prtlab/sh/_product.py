"""SH products: truncated and exact products, product matrices, triple integrals.

Two tiers of one algorithm, picked with ``method=``:

``"sparse"`` (default)
    numba kernel over the sparse Gaunt tensor (``_product_kernels.py``),
    parallel over the batch.
``"dense"``
    the float64 reference: ``einsum`` with the dense Gaunt tensor.

Coefficient layout (all functions here and in ``_explog.py``): an SH function
of order ``n`` is an array ``(..., n*n)``; a coloured one is ``(..., n*n, C)``
(channels last). With ``channels=None`` the layout is inferred (the rule of ``evaluate``): if the last
axis has a perfect-square length it is the coefficient axis, otherwise the
second-to-last is and the last holds channels. Pass ``channels=True`` /
``channels=False`` when the channel count is itself a perfect square
(1, 4, 9, ...). Leading axes are batch axes and broadcast between operands; a
coloured operand combines with an uncoloured one channel by channel.
"""

from __future__ import annotations

import math

import numpy as np

from prtlab._validate import check_order

from ._gaunt import _gaunt_block, _gaunt_cached
from ._product_kernels import _sparse_product, _sparse_product_matrix

__all__ = ["product", "product_exact", "product_matrix", "triple_integral"]

_PRODUCT_METHODS = ("sparse", "dense")


def _check_method(method, valid: tuple[str, ...]) -> str:
    if not isinstance(method, str) or method not in valid:
        raise ValueError(f"method must be one of {', '.join(repr(v) for v in valid)}; got {method!r}")
    return method


def _is_square(n: int) -> bool:
    r = math.isqrt(n)
    return n >= 1 and r * r == n


def _as_coeffs(x, name: str, channels=None) -> tuple[np.ndarray, int, bool]:
    """Validate an SH coefficient array; return (float64 array, order, coloured)."""
    x = np.asarray(x)
    if x.dtype.kind not in "fiu":
        raise TypeError(f"{name} must be a real numeric array of SH coefficients, got dtype {x.dtype}")
    x = x.astype(np.float64, copy=False)
    colour = channels
    if colour is None:
        if x.ndim >= 1 and _is_square(x.shape[-1]):
            colour = False
        elif x.ndim >= 2 and _is_square(x.shape[-2]):
            colour = True
        else:
            raise ValueError(
                f"{name} must have shape (..., n*n) or (..., n*n, C) (coefficient index l*l + l + m), "
                f"got shape {x.shape}; no axis with a perfect-square length in the last two positions"
            )
    elif not isinstance(colour, (bool, np.bool_)):
        raise TypeError(f"channels must be None, True or False, got {colour!r}")
    axis = -2 if colour else -1
    if x.ndim < (2 if colour else 1) or not _is_square(x.shape[axis]):
        want = "(..., n*n, C)" if colour else "(..., n*n)"
        raise ValueError(f"{name} must have shape {want} with n >= 1, got shape {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{name} contains NaN or inf; SH coefficients must be finite")
    return x, math.isqrt(x.shape[axis]), bool(colour)


def _to_bnc(x: np.ndarray, coloured: bool, batch: tuple, n_chan: int) -> np.ndarray:
    """Broadcast to ``batch + (n2, C)`` and reshape to a contiguous ``(B, n2, C)``."""
    if not coloured:
        x = x[..., None]
    x = np.broadcast_to(x, batch + x.shape[-2:-1] + (n_chan,))
    return _read_only(np.ascontiguousarray(x.reshape((-1,) + x.shape[-2:])))


def _read_only(x: np.ndarray) -> np.ndarray:
    """A read-only view: kernel inputs always have the same numba type (one compiled signature)."""
    x = x.view()
    x.setflags(write=False)
    return x


def _layout(arrays, coloured):
    """Common batch shape and channel count of several (array, coloured) operands."""
    batches = [x.shape[:-2] if c else x.shape[:-1] for x, c in zip(arrays, coloured)]
    try:
        batch = np.broadcast_shapes(*batches)
    except ValueError:
        raise ValueError(
            f"batch shapes {', '.join(str(b) for b in batches)} do not broadcast; "
            "leading axes of the operands must broadcast against each other"
        ) from None
    chans = {x.shape[-1] for x, c in zip(arrays, coloured) if c}
    if len(chans) > 1:
        raise ValueError(f"operands have different channel counts {sorted(chans)}; use the same C")
    n_chan = chans.pop() if chans else 1
    return batch, n_chan, any(coloured)


def _from_bnc(out: np.ndarray, batch: tuple, coloured: bool) -> np.ndarray:
    out = out.reshape(batch + out.shape[1:])
    return out if coloured else out[..., 0]


def _product_bnc(a: np.ndarray, b: np.ndarray, nc: int, method: str) -> np.ndarray:
    """Product of ``(B, na2, C)`` and ``(B, nb2, C)`` truncated to order nc -> ``(B, nc2, C)``."""
    na, nb = math.isqrt(a.shape[1]), math.isqrt(b.shape[1])
    if method == "dense":
        g = _gaunt_cached(max(na, nb, nc)).dense()[: na * na, : nb * nb, : nc * nc]
        return np.einsum("ijk,tic,tjc->tkc", g, a, b)
    gi, gj, gk, gv = _gaunt_block(na, nb, nc)
    out = np.empty((a.shape[0], nc * nc, a.shape[2]))
    _sparse_product(a, b, gi, gj, gk, gv, out)
    return out


def product(a, b, order=None, *, method="sparse", channels=None) -> np.ndarray:
    """SH product of two functions, truncated to ``order``.

    Parameters
    ----------
    a : (..., na*na) or (..., na*na, C) float
        First function.
    b : (..., nb*nb) or (..., nb*nb, C) float
        Second function (batch axes broadcast against ``a``'s).
    order : int, optional
        Order of the result; default ``na``.
    method : {"sparse", "dense"}
        ``"sparse"``: numba kernel over the sparse Gaunt tensor;
        ``"dense"``: float64 einsum with the dense tensor (reference tier).
    channels : bool, optional
        Whether the last axis holds channels; inferred when None (see module notes).

    Returns
    -------
    c : (..., order*order[, C]) float64
        Coloured if either operand is.

    Notes
    -----
    .. math:: c_k = \\sum_{ij} G_{ijk} a_i b_j, \\qquad k < \\text{order}^2,

    the projection onto bands ``l < order`` of the pointwise product of the
    reconstructed functions (``G`` from :func:`gaunt_tensor`). Exact for
    ``order >= na + nb - 1`` (see :func:`product_exact`).

    References
    ----------
    Ng, Ramamoorthi, Hanrahan 2004, triple product integrals (Eq. 2);
    Zhou et al. 2005, Eq. 4 (SH products of blocker visibilities).

    Examples
    --------
    >>> one = np.zeros(4); one[0] = np.sqrt(4 * np.pi)    # the constant 1
    >>> f = np.array([0.5, 0.1, -0.2, 0.3])
    >>> np.allclose(product(one, f), f)
    True
    """
    method = _check_method(method, _PRODUCT_METHODS)
    a, na, ca = _as_coeffs(a, "a", channels)
    b, nb, cb = _as_coeffs(b, "b", channels)
    nc = na if order is None else check_order(order)
    batch, n_chan, coloured = _layout((a, b), (ca, cb))
    out = _product_bnc(_to_bnc(a, ca, batch, n_chan), _to_bnc(b, cb, batch, n_chan), nc, method)
    return _from_bnc(out, batch, coloured)


def product_exact(a, b, *, method="sparse", channels=None) -> np.ndarray:
    """Exact SH product: the product truncated to order ``na + nb - 1``.

    Parameters
    ----------
    a : (..., na*na[, C]) float
    b : (..., nb*nb[, C]) float
    method : {"sparse", "dense"}
    channels : bool, optional

    Returns
    -------
    c : (..., (na+nb-1)**2[, C]) float64
        The coefficients of the pointwise product, which is band-limited to
        ``l <= (na - 1) + (nb - 1)``: no truncation error.
    """
    a_arr, na, _ = _as_coeffs(a, "a", channels)
    b_arr, nb, _ = _as_coeffs(b, "b", channels)
    return product(a_arr, b_arr, na + nb - 1, method=method, channels=channels)


def product_matrix(f, order=None, *, method="sparse") -> np.ndarray:
    """The matrix of multiplication by ``f``: ``product_matrix(f, n) @ g == product(f, g, n)``.

    Parameters
    ----------
    f : (..., nf*nf) float
        The multiplier. Uncoloured only: for a coloured ``f (..., nf*nf, C)``
        pass ``np.moveaxis(f, -1, -2)`` and get one matrix per channel,
        ``(..., C, n*n, n*n)``.
    order : int, optional
        Order ``n`` of both ``g`` and the result; default ``nf``.
    method : {"sparse", "dense"}

    Returns
    -------
    m : (..., n*n, n*n) float64
        ``m[..., k, j] = sum_i G_ijk f_i``; symmetric.

    Notes
    -----
    For ``g`` of order ``n``, ``m @ g`` is the product truncated to order
    ``n``. It is also the Jacobian of ``g -> product(f, g)`` and, with
    ``f = exp*(x)`` of order ``2n - 1``, of the SH exponential at ``x``.

    References
    ----------
    Sloan, Kautz, Snyder 2002, "Precomputed radiance transfer ...", Sec. 6
    (transfer matrices of products); Ng et al. 2004.
    """
    method = _check_method(method, _PRODUCT_METHODS)
    f, nf, _ = _as_coeffs(f, "f", False)
    n = nf if order is None else check_order(order)
    batch = f.shape[:-1]
    flat = _read_only(np.ascontiguousarray(f.reshape(-1, nf * nf)))
    if method == "dense":
        g = _gaunt_cached(max(nf, n)).dense()[: nf * nf, : n * n, : n * n]
        out = np.einsum("ijk,ti->tkj", g, flat)
    else:
        gi, gj, gk, gv = _gaunt_block(nf, n, n)
        out = np.empty((flat.shape[0], n * n, n * n))
        _sparse_product_matrix(flat, gi, gj, gk, gv, out)
    return out.reshape(batch + (n * n, n * n))


def triple_integral(a, b, c, *, method="sparse", channels=None) -> np.ndarray:
    """Integral over the sphere of the product of three SH functions.

    Parameters
    ----------
    a, b, c : (..., n*n[, C]) float
        Three functions; orders may differ, batch axes broadcast.
    method : {"sparse", "dense"}
    channels : bool, optional

    Returns
    -------
    s : (...[, C]) float64
        ``sum_ijk G_ijk a_i b_j c_k = int a(w) b(w) c(w) dw`` (exact: no truncation).

    References
    ----------
    Ng, Ramamoorthi, Hanrahan 2004, Eq. 2; Guerrero et al. 2008, Eq. 3.
    """
    method = _check_method(method, _PRODUCT_METHODS)
    a, na, ca = _as_coeffs(a, "a", channels)
    b, nb, cb = _as_coeffs(b, "b", channels)
    c, nc, cc = _as_coeffs(c, "c", channels)
    batch, n_chan, coloured = _layout((a, b, c), (ca, cb, cc))
    ab = _product_bnc(_to_bnc(a, ca, batch, n_chan), _to_bnc(b, cb, batch, n_chan), nc, method)
    s = np.einsum("tkc,tkc->tc", ab, _to_bnc(c, cc, batch, n_chan))
    s = s.reshape(batch + (n_chan,))
    return s if coloured else s[..., 0]

"""Evaluation of the real orthonormal spherical harmonics.

Convention (:mod:`prtlab.sh`): coefficient index ``i = l*l + l + m``,
no Condon-Shortley phase, polar axis = world z::

    Y_l0  = K_l0 P_l(z)
    Y_lm  = sqrt(2) K_lm P_l^m(z) cos(m phi)        m > 0
    Y_l-m = sqrt(2) K_lm P_l^m(z) sin(m phi)        m > 0
    K_lm  = sqrt((2l+1)/(4 pi) (l-m)!/(l+m)!)

so that ``Y_1,-1 = c y``, ``Y_1,0 = c z``, ``Y_1,1 = c x`` with
``c = sqrt(3 / (4 pi))``.

This module also owns the validators every SH function shares (order,
directions, coefficient arrays), so each rule and its message lives once.
"""

from __future__ import annotations

import math

import numpy as np

from prtlab._validate import as_directions, check_choice, check_order

from . import _kernels

__all__ = ["basis", "basis_reference", "evaluate", "index", "n_coeffs"]

_METHODS = ("numba", "reference")

# Directions per chunk when a (N, n*n) basis matrix would otherwise be large.
_CHUNK = 1 << 16


# --------------------------------------------------------------------------- validators


def _check_method(method, allowed=_METHODS) -> str:
    return check_choice(method, "method", allowed)


def _raise_bad_dirs(dirs: np.ndarray, name: str = "dirs") -> None:
    """Explain why a kernel flagged some directions (NaN/inf or zero length)."""
    if not np.all(np.isfinite(dirs)):
        raise ValueError(f"{name} contains NaN or inf; every direction must be a finite unit vector")
    raise ValueError(f"{name} contains a zero vector; every direction must be a unit vector")


def _isqrt_order(n: int) -> int:
    """Order whose square is ``n``, or -1 if ``n`` is not a positive perfect square."""
    if n < 1:
        return -1
    r = math.isqrt(n)
    return r if r * r == n else -1


def _as_coeffs(coeffs, name: str = "coeffs", channels: bool | None = None):
    """Coerce an SH coefficient array and find its coefficient axis.

    Rule (used by every function that takes ``(..., n*n)`` or ``(..., n*n, C)``):
    the last axis is the coefficient axis if its length is a perfect square and
    ``channels`` is not True; otherwise the second-to-last axis is, and the last
    axis is colour. ``channels=True``/``False`` forces either reading.

    Returns
    -------
    coeffs : float64 array
    order : int
    has_channels : bool
    """
    arr = np.asarray(coeffs)
    if arr.dtype.kind not in "fiu":
        raise TypeError(f"{name} must be a real array, got dtype {arr.dtype}")
    arr = arr.astype(np.float64, copy=False)
    if arr.ndim == 0:
        raise ValueError(f"{name} must have shape (..., n*n) or (..., n*n, C), got a scalar")
    if channels is None:
        if _isqrt_order(arr.shape[-1]) > 0:
            has_channels = False
        elif arr.ndim >= 2 and _isqrt_order(arr.shape[-2]) > 0:
            has_channels = True
        else:
            raise ValueError(
                f"{name} must have shape (..., n*n) or (..., n*n, C) with n*n a perfect square "
                f"(1, 4, 9, 16, ...), got shape {arr.shape}"
            )
    else:
        has_channels = bool(channels)
        if has_channels and arr.ndim < 2:
            raise ValueError(f"{name} must have shape (..., n*n, C) when channels=True, got shape {arr.shape}")
    axis_len = arr.shape[-2] if has_channels else arr.shape[-1]
    order = _isqrt_order(axis_len)
    if order < 1:
        raise ValueError(
            f"{name}: the coefficient axis has length {axis_len}, which is not a perfect square "
            f"n*n (1, 4, 9, 16, ...); pass a (..., n*n) or (..., n*n, C) array"
        )
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf; SH coefficients must be finite")
    return arr, order, has_channels


def _band_of_coeff(order: int) -> np.ndarray:
    """(n*n,) int: the band l of every coefficient index."""
    return np.repeat(np.arange(order), 2 * np.arange(order) + 1)


# --------------------------------------------------------------------------- helpers


def n_coeffs(order: int) -> int:
    """Number of coefficients ``n*n`` of an order-``n`` SH vector (bands ``0..n-1``)."""
    order = check_order(order)
    return order * order


def index(l, m):
    """Coefficient index ``i = l*l + l + m`` of ``Y_lm``.

    Parameters
    ----------
    l, m : int or int arrays (broadcast)
        Band ``l >= 0`` and ``-l <= m <= l``.

    Returns
    -------
    i : int or int64 array
    """
    l_arr, m_arr = np.asarray(l), np.asarray(m)
    if l_arr.dtype.kind not in "iu" or m_arr.dtype.kind not in "iu":
        raise TypeError(f"l and m must be integers, got dtypes {l_arr.dtype} and {m_arr.dtype}")
    if np.any(l_arr < 0) or np.any(np.abs(m_arr) > l_arr):
        raise ValueError("index needs l >= 0 and -l <= m <= l")
    i = l_arr * l_arr + l_arr + m_arr
    return int(i) if i.ndim == 0 else i.astype(np.int64)


# --------------------------------------------------------------------------- evaluation


def basis_reference(dirs, order: int) -> np.ndarray:
    """All real SH up to ``order`` at ``dirs``: the float64 reference tier.

    Associated Legendre functions are computed divided by ``sin(theta)^m``
    (``Q_l^m``), with the stable three-term recurrence in ``l``, and the
    azimuthal factor ``sin(theta)^m (cos m phi, sin m phi)`` as the real and
    imaginary parts of ``(x + i y)^m``; no trigonometry, no division by
    ``sin(theta)``, exact at the poles.

    Parameters
    ----------
    dirs : (..., 3) float
        Unit directions (normalised here, so near-unit input is fine).
    order : int
        Number of bands ``n``; the result has ``n*n`` coefficients.

    Returns
    -------
    y : (..., order**2) float64
    """
    order = check_order(order)
    dirs = as_directions(dirs, normalize=False)
    norm = np.linalg.norm(dirs, axis=-1, keepdims=True)
    if np.any(norm == 0.0):
        _raise_bad_dirs(dirs)
    d = dirs / norm
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    out = np.empty(d.shape[:-1] + (order * order,))

    # (x + i y)^m = sin^m(theta) e^{i m phi}
    cm = np.ones_like(x)
    sm = np.zeros_like(x)
    q_mm = np.ones_like(x)  # Q_m^m = (2m-1)!!
    for m in range(order):
        if m > 0:
            cm, sm = cm * x - sm * y, cm * y + sm * x
            q_mm = q_mm * (2 * m - 1)
        q_prev2, q_prev1 = None, q_mm
        for l in range(m, order):
            if l == m:
                q = q_mm
            elif l == m + 1:
                q = (2 * m + 1) * z * q_mm
            else:
                q = ((2 * l - 1) * z * q_prev1 - (l + m - 1) * q_prev2) / (l - m)
            if l > m:
                q_prev2, q_prev1 = q_prev1, q
            k = np.sqrt((2 * l + 1) / (4 * np.pi) * _factorial_ratio(l, m))
            if m == 0:
                out[..., l * l + l] = k * q
            else:
                out[..., l * l + l + m] = np.sqrt(2.0) * k * q * cm
                out[..., l * l + l - m] = np.sqrt(2.0) * k * q * sm
    return out


def _factorial_ratio(l: int, m: int) -> float:
    """(l - m)! / (l + m)! without overflow."""
    r = 1.0
    for k in range(l - m + 1, l + m + 1):
        r /= k
    return r


def basis(dirs, order: int, method: str = "numba") -> np.ndarray:
    """All real SH ``Y_i``, ``i = 0..order**2 - 1``, at each direction.

    Parameters
    ----------
    dirs : (..., 3) float
        Directions; normalised here (they must be finite and non-zero).
    order : int
        Number of bands ``n >= 1``; the result has ``n*n`` coefficients.
    method : {"numba", "reference"}
        ``"numba"``: the fast tier, a parallel kernel with hand-written
        polynomials for bands ``l <= 3`` and the normalised three-term
        Legendre recurrence above them. ``"reference"``: :func:`basis_reference`.

    Returns
    -------
    y : (..., order**2) float64
        ``y[..., l*l + l + m] = Y_lm(dirs)``.

    Notes
    -----
    The basis is real and orthonormal, ``int_S2 Y_i Y_j dw = delta_ij``, with
    no Condon-Shortley phase: ``Y_1,-1 = c y``, ``Y_1,0 = c z``, ``Y_1,1 = c x``,
    ``c = sqrt(3 / (4 pi))``. The fast tier writes the fully normalised
    associated Legendre functions ``p_lm = N_lm P_l^m / sin^m(theta)`` by
    ``p_lm = a_lm z p_(l-1)m - b_lm p_(l-2)m`` with
    ``a_lm = sqrt((4l^2 - 1) / (l^2 - m^2))`` and
    ``b_lm = sqrt((2l+1)(l+m-1)(l-m-1) / ((2l-3)(l-m)(l+m)))``, times the
    real and imaginary parts of ``(x + i y)^m``; no trigonometry, exact at the
    poles, stable to high order (tested to order 20 against the reference).

    Examples
    --------
    >>> import numpy as np
    >>> from prtlab.sh import basis
    >>> y = basis(np.array([[0.0, 0.0, 1.0]]), 2)
    >>> np.round(y / np.sqrt(3 / (4 * np.pi)), 6)
    array([[0.57735, 0.     , 1.     , 0.     ]])
    """
    return _basis(dirs, order, method, "dirs")


def _basis(dirs, order, method: str, name: str) -> np.ndarray:
    """:func:`basis` with the directions' parameter name used in error messages."""
    order = check_order(order)
    method = _check_method(method)
    if method == "reference":
        arr = as_directions(dirs, name, normalize=False)
        if np.any(np.all(arr == 0.0, axis=-1)):
            _raise_bad_dirs(arr, name)
        return basis_reference(arr, order)
    arr = np.asarray(dirs)
    if arr.dtype.kind not in "fiu" or arr.ndim == 0 or arr.shape[-1] != 3:
        as_directions(arr, name, normalize=False)  # raises the shared message; NaN is left to the kernel
    flat = _kernels.kernel_array(arr.reshape(-1, 3))
    out = np.empty((flat.shape[0], order * order))
    if flat.shape[0]:
        n_bad = _kernels.sh_basis(flat, order, out)
        if n_bad:
            _raise_bad_dirs(flat, name)
    return out.reshape(arr.shape[:-1] + (order * order,))


def evaluate(coeffs, dirs, method: str = "numba", channels: bool | None = None) -> np.ndarray:
    """Reconstruct ``f(w) = sum_i c_i Y_i(w)`` at directions.

    Parameters
    ----------
    coeffs : (..., n*n) or (..., n*n, C) float
        SH coefficients. The coefficient axis is the last axis when its
        length is a perfect square, otherwise the second-to-last one (and the
        last is colour); ``channels=True`` / ``False`` forces the reading
        (needed only when the colour count is itself a perfect square, e.g. C = 1 or 4).
    dirs : (..., 3) float
        Directions.
    method : {"numba", "reference"}
        Basis tier (see :func:`basis`).
    channels : bool, optional
        Whether ``coeffs`` has a trailing colour axis (default: inferred).

    Returns
    -------
    values : (...) or (..., C) float64
        The batch axes of ``coeffs`` (all axes before the coefficient axis)
        and of ``dirs`` (all axes before the last) broadcast against each
        other as numpy does: one vector ``(n*n,)`` at ``(N, 3)`` directions
        gives ``(N,)``; per-vertex coefficients ``(V, n*n)`` at per-vertex
        directions ``(V, 3)`` give ``(V,)``; for every function at every
        direction pass ``coeffs[:, None]`` and ``dirs[None]``.
    """
    coeffs, order, has_channels = _as_coeffs(coeffs, channels=channels)
    dirs_arr = np.asarray(dirs)
    if dirs_arr.ndim == 0 or dirs_arr.shape[-1] != 3:
        raise ValueError(f"dirs must be a (..., 3) array of unit directions, got shape {dirs_arr.shape}")
    c_batch = coeffs.shape[:-2] if has_channels else coeffs.shape[:-1]
    d_batch = dirs_arr.shape[:-1]
    try:
        out_batch = np.broadcast_shapes(c_batch, d_batch)
    except ValueError:
        raise ValueError(
            f"the batch axes of coeffs {c_batch} and of dirs {d_batch} do not broadcast; "
            "add size-1 axes (e.g. coeffs[:, None] and dirs[None]) to evaluate every function at every direction"
        ) from None
    tail = (coeffs.shape[-1],) if has_channels else ()
    if len(c_batch) == 0:
        # One function at many directions: chunked basis @ coeffs.
        flat_dirs = dirs_arr.reshape(-1, 3)
        out = np.empty((flat_dirs.shape[0],) + tail)
        for start in range(0, flat_dirs.shape[0], _CHUNK):
            y = basis(flat_dirs[start : start + _CHUNK], order, method=method)
            out[start : start + _CHUNK] = y @ coeffs
        return out.reshape(out_batch + tail)
    y = basis(dirs_arr, order, method=method)
    if has_channels:
        return np.einsum("...ic,...i->...c", coeffs, y).reshape(out_batch + tail)
    return np.einsum("...i,...i->...", coeffs, y).reshape(out_batch)

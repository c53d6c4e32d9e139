"""Zonal harmonics: rotation to an axis, Funk-Hecke convolution, irradiance.

A zonal function ``g(w) = g(w . z)`` is symmetric about the z axis; its SH
coefficients are non-zero only for ``m = 0`` and its ZH vector is
``z_l = int_S2 g(w . z) Y_l0(w) dw``, length n for order n.
"""

from __future__ import annotations

import functools
import math
from fractions import Fraction

import numpy as np

from prtlab._validate import check_int, check_order

from ._eval import _as_coeffs, _band_of_coeff, _basis, _check_method

__all__ = ["clamped_cosine_zh", "convolve", "irradiance", "zh_project", "zh_rotate"]


def _as_zh(zh, name: str) -> np.ndarray:
    arr = np.asarray(zh)
    if arr.dtype.kind not in "fiu":
        raise TypeError(f"{name} must be a real (..., n) array, got dtype {arr.dtype}")
    arr = arr.astype(np.float64, copy=False)
    if arr.ndim == 0 or arr.shape[-1] < 1:
        raise ValueError(f"{name} must be a (..., n) array of zonal coefficients with n >= 1, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf; ZH coefficients must be finite")
    return arr


def _zh_scale(order: int) -> np.ndarray:
    """(order,) ``sqrt(4 pi / (2l + 1))``."""
    return np.sqrt(4.0 * np.pi / (2.0 * np.arange(order) + 1.0))


def zh_rotate(zh, axes, method: str = "numba") -> np.ndarray:
    """Rotate zonal functions from the z axis to ``axes``.

    Parameters
    ----------
    zh : (..., n) float
        ZH coefficients about z (``z_l``, ``l = 0..n-1``).
    axes : (..., 3) float
        New symmetry axes (normalised here); batch axes broadcast with ``zh``'s.
    method : {"numba", "reference"}
        Basis tier.

    Returns
    -------
    coeffs : (B..., n*n) float64
        ``c_lm = sqrt(4 pi / (2l + 1)) z_l Y_lm(axis)``, B the broadcast batch.

    Notes
    -----
    By the addition theorem ``P_l(w . d) = 4 pi / (2l+1) sum_m Y_lm(w) Y_lm(d)``
    and ``Y_l0(w) = sqrt((2l+1)/(4 pi)) P_l(w_z)``, the function
    ``sum_l z_l Y_l0(R^T w)`` with ``R z = d`` has exactly these coefficients;
    it equals ``rotate`` of the zonal SH vector by any rotation taking z to d.

    References
    ----------
    P.-P. Sloan, B. Luna, J. Snyder, "Local, deformable precomputed radiance
    transfer", SIGGRAPH 2005, eq. (3).
    """
    zh = _as_zh(zh, "zh")
    order = zh.shape[-1]
    y = _basis(axes, order, _check_method(method), "axes")
    try:
        np.broadcast_shapes(zh.shape[:-1], y.shape[:-1])
    except ValueError:
        raise ValueError(
            f"the batch axes of zh {zh.shape[:-1]} and of axes {y.shape[:-1]} do not broadcast; "
            "pass matching batch shapes (or a single zh (n,) / axis (3,))"
        ) from None
    band = _band_of_coeff(order)
    return (zh * _zh_scale(order))[..., band] * y


def convolve(coeffs, zh_kernel, channels: bool | None = None) -> np.ndarray:
    """Convolve SH functions with a zonal kernel (Funk-Hecke).

    Parameters
    ----------
    coeffs : (..., n*n) or (..., n*n, C) float
        SH coefficients (see :func:`evaluate` for the coefficient axis rule).
    zh_kernel : (k,) or (..., k) float, k >= n
        ZH coefficients ``k_l`` of the kernel ``K(w . w')``; bands beyond n are
        ignored (they cannot reach an order-n function). Batch axes broadcast
        with those of ``coeffs``.
    channels : bool, optional
        Whether ``coeffs`` has a trailing colour axis (default: inferred).

    Returns
    -------
    out : same shape as ``coeffs`` (broadcast), float64
        ``out_lm = sqrt(4 pi / (2l + 1)) k_l c_lm``.

    Notes
    -----
    ``h(n) = int_S2 K(n . w) f(w) dw`` has coefficients
    ``h_lm = sqrt(4 pi / (2l + 1)) k_l f_lm`` (Funk-Hecke theorem).

    References
    ----------
    R. Ramamoorthi, P. Hanrahan, "An efficient representation for irradiance
    environment maps", SIGGRAPH 2001, eq. (6) and (7).
    """
    coeffs, order, has_channels = _as_coeffs(coeffs, channels=channels)
    kern = _as_zh(zh_kernel, "zh_kernel")
    if kern.shape[-1] < order:
        raise ValueError(
            f"zh_kernel has {kern.shape[-1]} bands but coeffs has order {order}; "
            f"pass a kernel with at least {order} ZH coefficients (or truncate coeffs)"
        )
    factors = (kern[..., :order] * _zh_scale(order))[..., _band_of_coeff(order)]
    if has_channels:
        factors = factors[..., None]
    try:
        return coeffs * factors
    except ValueError:
        raise ValueError(
            f"the batch axes of coeffs {coeffs.shape} and zh_kernel {kern.shape} do not broadcast"
        ) from None


def _half_moment(l: int) -> Fraction:
    """Exact ``int_0^1 t P_l(t) dt``."""
    if l == 0:
        return Fraction(1, 2)
    if l == 1:
        return Fraction(1, 3)
    if l % 2:
        return Fraction(0)
    k = l // 2
    sign = 1 if (k + 1) % 2 == 0 else -1
    return sign * Fraction(math.factorial(l - 2), 2**l * math.factorial(k - 1) * math.factorial(k + 1))


def clamped_cosine_zh(order: int) -> np.ndarray:
    """ZH coefficients of the clamped cosine ``max(0, cos theta)``.

    Parameters
    ----------
    order : int
        Number of bands n.

    Returns
    -------
    zh : (n,) float64
        ``z_l = 2 pi sqrt((2l+1)/(4 pi)) int_0^1 t P_l(t) dt``.

    Notes
    -----
    ``int_0^1 t P_l(t) dt`` is ``1/2`` (l = 0), ``1/3`` (l = 1), ``0`` (odd
    l > 1) and ``(-1)^(l/2 + 1) (l-2)! / (2^l (l/2 - 1)! (l/2 + 1)!)`` (even
    l >= 2), evaluated in exact rational arithmetic. The convolution factors
    ``sqrt(4 pi/(2l+1)) z_l`` are then ``pi, 2 pi/3, pi/4, 0, -pi/24, ...``.

    References
    ----------
    R. Ramamoorthi, P. Hanrahan, "An efficient representation for irradiance
    environment maps", SIGGRAPH 2001, eq. (8) and (9).
    """
    return _clamped_cosine_zh(check_order(order)).copy()


@functools.lru_cache(maxsize=None)
def _clamped_cosine_zh(order: int) -> np.ndarray:
    """:func:`clamped_cosine_zh`, made once per order (its exact rationals cost about 0.2 ms a call)."""
    out = np.array(
        [2.0 * math.pi * math.sqrt((2 * l + 1) / (4.0 * math.pi)) * float(_half_moment(l)) for l in range(order)]
    )
    out.setflags(write=False)
    return out


def irradiance(coeffs, channels: bool | None = None) -> np.ndarray:
    """SH coefficients of the irradiance of a radiance distribution.

    ``E(n) = int_S2 L(w) max(0, n . w) dw`` for unit normals n; then
    ``E(n) == evaluate(irradiance(L), n)`` exactly for band-limited L
    (constant radiance L gives ``pi L``).

    Parameters
    ----------
    coeffs : (..., n*n) or (..., n*n, C) float
        Radiance SH coefficients.

    Returns
    -------
    coeffs : same shape, float64
        ``convolve(coeffs, clamped_cosine_zh(n))``.
    """
    coeffs, order, has_channels = _as_coeffs(coeffs, channels=channels)
    return convolve(coeffs, clamped_cosine_zh(order), channels=has_channels)


def zh_project(g, order: int, n_nodes: int | None = None) -> np.ndarray:
    """ZH coefficients of a zonal function given as a function of ``cos theta``.

    Parameters
    ----------
    g : callable
        ``g(t (K,)) -> (K,) or (K, C)``, vectorised over ``t = cos theta`` in [-1, 1].
    order : int
        Number of bands n.
    n_nodes : int, optional
        Gauss-Legendre nodes in ``t``; exact when g is a polynomial of degree
        ``<= 2 n_nodes - n``. Default ``max(2 n, 64)``. Kinked functions
        (e.g. clamped cosines) converge slowly: raise it or use closed forms.

    Returns
    -------
    zh : (n,) or (n, C) float64
        ``z_l = 2 pi int_-1^1 g(t) sqrt((2l+1)/(4 pi)) P_l(t) dt``.
    """
    order = check_order(order)
    if not callable(g):
        raise TypeError(f"g must be a callable of cos(theta), got {type(g).__name__}")
    if n_nodes is None:
        n_nodes = max(2 * order, 64)
    check_int(n_nodes, "n_nodes", 1)
    t, w = np.polynomial.legendre.leggauss(int(n_nodes))
    values = np.asarray(g(t.copy()))
    if values.dtype.kind not in "fiu" or values.ndim not in (1, 2) or values.shape[0] != t.shape[0]:
        raise ValueError(
            f"g must return a real ({t.shape[0]},) or ({t.shape[0]}, C) array for ({t.shape[0]},) inputs, "
            f"got shape {values.shape} and dtype {values.dtype}"
        )
    values = values.astype(np.float64)
    if not np.all(np.isfinite(values)):
        raise ValueError("g returned NaN or inf; zonal functions must be finite")
    legendre = np.polynomial.legendre.legvander(t, order - 1)  # (K, n): P_l(t)
    y_l0 = legendre * np.sqrt((2.0 * np.arange(order) + 1.0) / (4.0 * np.pi))
    vals = values.reshape(t.shape[0], -1)
    out = 2.0 * np.pi * (y_l0 * w[:, None]).T @ vals
    return out[:, 0] if values.ndim == 1 else out

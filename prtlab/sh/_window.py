"""Windowing of SH expansions against ringing, and non-negativity checks.

Truncating an expansion to n bands rings (Gibbs): a non-negative function can
come back with negative lobes. Scaling band l by a factor ``h_l`` that decays
smoothly to zero trades sharpness for less ringing.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from prtlab._validate import as_real_array, check_int, check_order

from ._eval import _as_coeffs, _band_of_coeff, basis

__all__ = ["apply_window", "is_nonnegative", "min_value", "nonnegative_window", "window"]

WINDOW_KINDS = ("hanning", "lanczos", "sinc4")


def _sinc(x: np.ndarray) -> np.ndarray:
    return np.sinc(x)  # sin(pi x) / (pi x), 1 at 0


def window(order: int, kind: str = "hanning", width: float | None = None) -> np.ndarray:
    """Per-band window factors ``h_l``, ``l = 0..n-1``.

    Parameters
    ----------
    order : int
        Number of bands n.
    kind : {"hanning", "lanczos", "sinc4"}
        Window shape, with ``x = l / width``:
        ``"hanning"``: ``(1 + cos(pi x)) / 2``; ``"lanczos"``: ``sinc(x)``;
        ``"sinc4"``: ``sinc(x)^4`` (``sinc(x) = sin(pi x) / (pi x)``);
        each is 0 for ``l >= width``.
    width : float, optional
        The band at which the window reaches zero (default ``n``: every band
        kept, the last one attenuated). Smaller means smoother. ``inf`` gives
        no windowing (all ones).

    Returns
    -------
    factors : (n,) float64, ``factors[0] == 1``

    References
    ----------
    P.-P. Sloan, "Stupid spherical harmonics (SH) tricks", GDC 2008,
    section "Windowing" (Hanning and Lanczos windows, sigma factors).
    """
    order = check_order(order)
    if kind not in WINDOW_KINDS:
        raise ValueError(f"kind must be one of {', '.join(repr(k) for k in WINDOW_KINDS)}, got {kind!r}")
    if width is None:
        width = float(order)
    width = float(width)
    if not width > 0.0:  # also catches NaN
        raise ValueError(f"width must be > 0 (the band where the window reaches zero), got {width}")
    l = np.arange(order, dtype=np.float64)
    x = l / width
    if kind == "hanning":
        h = 0.5 * (1.0 + np.cos(np.pi * x))
    elif kind == "lanczos":
        h = _sinc(x)
    else:
        h = _sinc(x) ** 4
    return np.where(l < width, h, 0.0)


def apply_window(coeffs, factors, channels: bool | None = None) -> np.ndarray:
    """Scale band l of ``coeffs`` by ``factors[l]``.

    Parameters
    ----------
    coeffs : (..., n*n) or (..., n*n, C) float
    factors : (n,) float
        From :func:`window` or :func:`nonnegative_window`.

    Returns
    -------
    windowed : same shape as ``coeffs``, float64
    """
    coeffs, order, has_channels = _as_coeffs(coeffs, channels=channels)
    f = as_real_array(factors, "factors")
    if f.shape != (order,):
        raise ValueError(f"factors must have shape ({order},) to match coeffs of order {order}, got shape {f.shape}")
    scale = f[_band_of_coeff(order)]
    return coeffs * (scale[:, None] if has_channels else scale)


@lru_cache(maxsize=8)
def _fibonacci_basis(n_dirs: int, order: int) -> np.ndarray:
    k = np.arange(n_dirs, dtype=np.float64)
    z = 1.0 - (2.0 * k + 1.0) / n_dirs
    phi = k * np.pi * (3.0 - np.sqrt(5.0))  # golden angle
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    dirs = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)
    y = basis(dirs, order)
    y.setflags(write=False)
    return y


def _default_n_dirs(order: int) -> int:
    return max(4096, 64 * order * order)


def _min_core(coeffs: np.ndarray, order: int, has_channels: bool, n_dirs: int) -> np.ndarray:
    y = _fibonacci_basis(n_dirs, order)
    c = np.moveaxis(coeffs, -2, -1) if has_channels else coeffs
    batch = c.shape[:-1]
    flat = c.reshape(-1, order * order).T  # (n*n, K)
    out = np.full(flat.shape[1], np.inf)
    step = max(1, (1 << 22) // max(1, flat.shape[1]))
    for start in range(0, n_dirs, step):
        vals = y[start : start + step] @ flat
        if vals.size:
            out = np.minimum(out, vals.min(axis=0))
    return out.reshape(batch)


def _check_n_dirs(n_dirs, order: int) -> int:
    if n_dirs is None:
        return _default_n_dirs(order)
    return check_int(n_dirs, "n_dirs", 1, meaning="number of sample directions")


def min_value(coeffs, n_dirs: int | None = None, channels: bool | None = None) -> np.ndarray:
    """Minimum of each SH function over a dense set of directions.

    Parameters
    ----------
    coeffs : (..., n*n) or (..., n*n, C) float
    n_dirs : int, optional
        Number of sample directions, a spherical Fibonacci lattice
        (``z_k = 1 - (2k+1)/N``, ``phi_k = k pi (3 - sqrt 5)``). Default
        ``max(4096, 64 n^2)``: mean spacing ``sqrt(4 pi / N) ~ 0.44 / n`` rad,
        about 14 samples per wavelength ``2 pi / n`` of the highest band.

    Returns
    -------
    minimum : (...) or (..., C) float64
        The smallest sampled value (an upper bound of the true minimum; it
        misses narrow dips between samples by ``O(|f''| spacing^2)``).
    """
    coeffs, order, has_channels = _as_coeffs(coeffs, channels=channels)
    n_dirs = _check_n_dirs(n_dirs, order)
    return _min_core(coeffs, order, has_channels, n_dirs)


def is_nonnegative(coeffs, n_dirs: int | None = None, tol: float = 0.0, channels: bool | None = None):
    """Whether ``min_value(coeffs, n_dirs) >= -tol`` for each function (see :func:`min_value`).

    Returns
    -------
    ok : (...) or (..., C) bool array (0-d for one scalar function)
    """
    tol = float(tol)
    if not tol >= 0.0:
        raise ValueError(f"tol must be >= 0, got {tol}")
    return min_value(coeffs, n_dirs=n_dirs, channels=channels) >= -tol


def nonnegative_window(
    coeffs,
    kind: str = "sinc4",
    n_dirs: int | None = None,
    channels: bool | None = None,
    return_width: bool = False,
):
    """The widest window of ``kind`` that makes every function non-negative.

    Parameters
    ----------
    coeffs : (..., n*n) or (..., n*n, C) float
        Functions to window; one window is found for all of them together.
    kind : {"sinc4", "hanning", "lanczos"}
        Window shape (see :func:`window`).
    n_dirs : int, optional
        Sampling of the non-negativity check (see :func:`min_value`).
    return_width : bool
        Also return the chosen width.

    Returns
    -------
    factors : (n,) float64
        All ones if the functions are already non-negative at the samples.
    width : float, only if ``return_width``
        ``inf`` when no windowing is needed.

    Notes
    -----
    Search: the width ``w`` runs over 64 log-spaced values in ``[1, 16 n]``
    (``w <= 1`` keeps only band 0, non-negative whenever every mean
    ``c_00 >= 0``); the largest passing grid value and the failing one above
    it are refined by 40 bisection steps, keeping the passing end. The
    criterion is ``min_value(apply_window(coeffs, window(n, kind, w))) >= 0``
    at the sample directions.

    Raises
    ------
    ValueError
        If some function has a negative mean (``c_00 < 0``): no window can
        make it non-negative.
    """
    coeffs, order, has_channels = _as_coeffs(coeffs, channels=channels)
    if kind not in WINDOW_KINDS:
        raise ValueError(f"kind must be one of {', '.join(repr(k) for k in WINDOW_KINDS)}, got {kind!r}")
    n_dirs = _check_n_dirs(n_dirs, order)
    mean = coeffs[..., 0, :] if has_channels else coeffs[..., 0]
    if np.any(mean < 0.0):
        raise ValueError(
            "coeffs has a function with negative mean (c_00 < 0); no window can make it non-negative"
        )

    def passes(width: float) -> bool:
        windowed = apply_window(coeffs, window(order, kind, width), channels=has_channels)
        return coeffs.size == 0 or bool(np.all(_min_core(windowed, order, has_channels, n_dirs) >= 0.0))

    def result(width: float):
        factors = window(order, kind, width)
        return (factors, width) if return_width else factors

    if passes(np.inf):
        return result(np.inf)
    grid = np.geomspace(1.0, 16.0 * order, 64)
    ok = [passes(w) for w in grid]
    if not ok[-1]:
        good_idx = max(i for i, flag in enumerate(ok) if flag)  # ok[0] holds: w = 1 keeps band 0 only
        lo, hi = grid[good_idx], grid[good_idx + 1]
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            if passes(mid):
                lo = mid
            else:
                hi = mid
        return result(float(lo))
    return result(float(grid[-1]))

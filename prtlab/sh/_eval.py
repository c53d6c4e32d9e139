"""Evaluation of the real orthonormal spherical harmonics.

Convention (``../shared/DESIGN.md``): coefficient index ``i = l*l + l + m``,
no Condon-Shortley phase, polar axis = world z::

    Y_l0  = K_l0 P_l(z)
    Y_lm  = sqrt(2) K_lm P_l^m(z) cos(m phi)        m > 0
    Y_l-m = sqrt(2) K_lm P_l^m(z) sin(m phi)        m > 0
    K_lm  = sqrt((2l+1)/(4 pi) (l-m)!/(l+m)!)

so that ``Y_1,-1 = c y``, ``Y_1,0 = c z``, ``Y_1,1 = c x`` with
``c = sqrt(3 / (4 pi))``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["basis_reference"]


def _check_order(order) -> int:
    if isinstance(order, bool) or not isinstance(order, (int, np.integer)):
        raise TypeError(f"order must be an int (number of bands), got {type(order).__name__}")
    order = int(order)
    if order < 1:
        raise ValueError(f"order must be >= 1 (order n means bands l = 0..n-1), got {order}")
    return order


def _as_unit_dirs(dirs) -> np.ndarray:
    dirs = np.asarray(dirs)
    if dirs.dtype.kind not in "fiu":
        raise TypeError(f"dirs must be a real array, got dtype {dirs.dtype}")
    dirs = dirs.astype(np.float64, copy=False)
    if dirs.ndim == 0 or dirs.shape[-1] != 3:
        raise ValueError(f"dirs must be a (..., 3) array of unit directions, got shape {dirs.shape}")
    if not np.all(np.isfinite(dirs)):
        raise ValueError("dirs contains NaN or inf; every direction must be a finite unit vector")
    return dirs


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
    order = _check_order(order)
    dirs = _as_unit_dirs(dirs)
    norm = np.linalg.norm(dirs, axis=-1, keepdims=True)
    if np.any(norm == 0.0):
        raise ValueError("dirs contains a zero vector; every direction must be a unit vector")
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

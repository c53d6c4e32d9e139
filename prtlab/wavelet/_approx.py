"""Non-linear approximation: keep the k largest Haar coefficients of each cubemap.

Ng et al. 2003 approximate the lighting by its k largest wavelet coefficients,
chosen per cubemap (all six faces together), optionally after weighting each
coefficient by the area of its support ("area-weighted selection", which
favours broad features). Energy means the plain sum of squares of the
coefficients, equal by Parseval to the sum of squared texel values.
"""

from __future__ import annotations

import numpy as np

from prtlab._validate import check_int
from ._haar import _as_cubemaps, _as_real, _check_finite

__all__ = ["keep_largest", "energy_kept"]


def _as_count(k, name: str = "k") -> int:
    return check_int(k, name, 0, meaning="number of coefficients to keep")


def _order(coeffs, weights):
    """Flatten to ``(B, N)`` and return the per-cubemap descending order of ``|c| * w``."""
    arr = _as_cubemaps(coeffs, "coeffs")
    flat = arr.reshape(-1, arr.shape[-3] * arr.shape[-2] * arr.shape[-1])
    key = np.abs(flat)
    if weights is not None:
        w = _as_real(weights, "weights")
        _check_finite(w, "weights")
        try:
            w = np.broadcast_to(w, arr.shape)
        except ValueError:
            raise ValueError(
                f"weights must broadcast to coeffs' shape {arr.shape} (e.g. (6, r, r) from "
                f"support_solid_angles(r)), got shape {w.shape}"
            ) from None
        if np.any(w < 0):
            raise ValueError("weights must be non-negative (e.g. support_solid_angles(r))")
        key = key * w.reshape(flat.shape)
    # stable sort of -key: ties keep the lower flat index (layout order) first
    order = np.argsort(-key, axis=-1, kind="stable")
    return arr, flat, order


def keep_largest(coeffs, k: int, weights=None):
    """Keep the k largest-magnitude coefficients of every cubemap, zero the rest.

    Parameters
    ----------
    coeffs : (..., 6, r, r) float
        Haar coefficients (:func:`haar2d`), or any per-cubemap coefficients.
    k : int
        Coefficients kept per cubemap (over all ``6 r**2``; ``k >= 6 r**2`` keeps all).
    weights : (6, r, r) or broadcastable float, optional
        Non-negative selection weights: the k largest ``|c| * w`` are kept
        (pass ``support_solid_angles(r)`` for area-weighted selection).

    Returns
    -------
    approx : (..., 6, r, r) float64
        ``coeffs`` with all but the selected coefficients set to zero.
    fraction : (...) float64
        Energy kept, ``sum approx**2 / sum coeffs**2`` (1 for an all-zero cubemap).

    Notes
    -----
    Ties are broken by the flattened ``(face, i, j)`` index, lowest first, so
    the result is deterministic. Without weights the selection is the best
    k-term approximation in L2 of an orthonormal basis.

    References
    ----------
    R. Ng, R. Ramamoorthi, P. Hanrahan, "All-frequency shadows using
    non-linear wavelet lighting approximation", SIGGRAPH 2003, Section 5
    (non-linear approximation, area-weighted selection).

    Examples
    --------
    >>> import numpy as np
    >>> from prtlab.wavelet import haar2d, keep_largest
    >>> light = np.zeros((6, 8, 8))
    >>> light[2, :4, :4] = 1.0  # a bright quarter of the +Y face
    >>> approx, fraction = keep_largest(haar2d(light), 4)
    >>> int((approx != 0).sum()), float(fraction)
    (4, 1.0)
    """
    k = _as_count(k)
    arr, flat, order = _order(coeffs, weights)
    keep = order[:, : min(k, flat.shape[-1])]
    approx = np.zeros_like(flat)
    np.put_along_axis(approx, keep, np.take_along_axis(flat, keep, axis=-1), axis=-1)
    total = np.einsum("bn,bn->b", flat, flat)
    kept = np.einsum("bn,bn->b", approx, approx)
    fraction = np.divide(kept, total, out=np.ones_like(total), where=total > 0)
    batch = arr.shape[:-3]
    return approx.reshape(arr.shape), fraction.reshape(batch)


def energy_kept(coeffs, k, weights=None) -> np.ndarray:
    """Fraction of energy kept by :func:`keep_largest` for one or many k.

    Parameters
    ----------
    coeffs : (..., 6, r, r) float
    k : int or (K,) int
        Numbers of coefficients kept.
    weights : optional
        As in :func:`keep_largest`.

    Returns
    -------
    fraction : (...) or (..., K) float64
        Non-decreasing in k, 1 at ``k = 6 r**2`` (and for all-zero cubemaps).
    """
    scalar = np.ndim(k) == 0
    ks = [_as_count(x) for x in np.atleast_1d(np.asarray(k, dtype=object)).ravel()]
    arr, flat, order = _order(coeffs, weights)
    sorted_energy = np.take_along_axis(flat, order, axis=-1) ** 2
    cumulative = np.concatenate([np.zeros((flat.shape[0], 1)), np.cumsum(sorted_energy, axis=-1)], axis=-1)
    total = cumulative[:, -1:]
    idx = np.minimum(np.array(ks, dtype=np.int64), flat.shape[-1])
    picked = cumulative[:, idx]
    fraction = np.divide(picked, total, out=np.ones_like(picked), where=total > 0)
    fraction = fraction.reshape(arr.shape[:-3] + (len(ks),))
    return fraction[..., 0] if scalar else fraction

"""Orthonormal non-standard 2D Haar transform of cubemap faces.

Each face of a cubemap ``(..., 6, r, r)`` (``r`` a power of two; face order and
orientation from :mod:`prtlab.geometry._spheremaps`) is transformed on its own,
as in all-frequency relighting (Ng, Ramamoorthi, Hanrahan 2003): one level of
the 1D Haar step along rows and one along columns, then recurse on the scaling
quadrant. This module also owns the validators every wavelet function shares.

Coefficient layout (the standard in-place quadtree layout, identical to
``pywt.coeffs_to_array(pywt.wavedec2(face, "haar", mode="periodization"))``)::

    [0, 0]              scaling coefficient of the face
    [p, h + q]          wavelet "01" of node (p, q) at level l, h = 2**l
    [h + p, q]          wavelet "10"
    [h + p, h + q]      wavelet "11"

for ``l = 0 .. log2(r) - 1`` and ``0 <= p, q < h``. The node ``(p, q)`` of
level ``l`` covers texel rows ``p m .. (p+1) m - 1`` and columns
``q m .. (q+1) m - 1`` with ``m = r / h``.
"""

from __future__ import annotations

import numpy as np

from ..geometry._spheremaps import cubemap_solid_angles
from . import _kernels

__all__ = [
    "haar2d",
    "ihaar2d",
    "solid_angle_weight",
    "support_solid_angles",
    "coefficient_levels",
]

_METHODS = ("numba", "reference")


# --------------------------------------------------------------------------- validators


def _check_method(method, allowed=_METHODS) -> str:
    if method not in allowed:
        raise ValueError(f"method must be one of {', '.join(repr(m) for m in allowed)}, got {method!r}")
    return method


def _check_resolution(res, name: str = "res") -> int:
    if isinstance(res, bool) or not isinstance(res, (int, np.integer)):
        raise TypeError(f"{name} must be an int (face resolution), got {type(res).__name__}")
    res = int(res)
    if res < 1 or res & (res - 1):
        raise ValueError(
            f"{name} must be a power of two (the Haar quadtree halves each face down to one texel), "
            f"got {res}; resample the cubemap to a power-of-two resolution"
        )
    return res


def _as_real(values, name: str) -> np.ndarray:
    arr = np.asarray(values)
    if arr.dtype.kind not in "fiub":
        raise TypeError(f"{name} must be a real array, got dtype {arr.dtype}")
    return arr.astype(np.float64, copy=False)


def _check_finite(arr: np.ndarray, name: str) -> None:
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf; wavelet transforms need finite values")


def _as_cubemaps(
    values, name: str, channels: bool = False, faces_axis: bool = True, hint: str = "", check_finite: bool = True
) -> np.ndarray:
    """Coerce ``(..., 6, r, r)`` (or ``(..., 6, r, r, C)`` with ``channels``) float64 cubemaps.

    With ``faces_axis=False`` the trailing axes are one face ``(..., r, r)``.
    Returns the array with the colour axis (if any) still trailing.
    """
    arr = _as_real(values, name)
    core = (3 if faces_axis else 2) + (1 if channels else 0)
    want = ("(..., 6, r, r" if faces_axis else "(..., r, r") + (", C)" if channels else ")")
    if arr.ndim < core:
        raise ValueError(f"{name} must have shape {want} with r a power of two, got shape {arr.shape}{hint}")
    shape = arr.shape[:-1] if channels else arr.shape
    if faces_axis and shape[-3] != 6:
        raise ValueError(
            f"{name} must have shape {want} (six faces +X, -X, +Y, -Y, +Z, -Z), got {shape[-3]} faces "
            f"in shape {arr.shape}{hint}"
        )
    if shape[-1] != shape[-2]:
        raise ValueError(f"{name} faces must be square {want}, got shape {arr.shape}")
    r = shape[-1]
    if r < 1 or r & (r - 1):
        raise ValueError(
            f"{name} must have shape {want} with r a power of two, got r = {r}; "
            "resample the cubemap to a power-of-two resolution"
        )
    if check_finite:
        _check_finite(arr, name)
    return arr


def _flat_faces(arr: np.ndarray, channels: bool) -> tuple[np.ndarray, tuple]:
    """``(..., r, r[, C])`` -> contiguous ``(F, r, r)`` and the shape to restore."""
    if channels:
        arr = np.moveaxis(arr, -1, -4)
    shape = arr.shape
    r = shape[-1]
    return _kernel_array(arr.reshape(-1, r, r)), shape


def _kernel_array(arr: np.ndarray) -> np.ndarray:
    """C-contiguous and writeable (one numba signature per kernel; read-only views are copied)."""
    return np.require(arr, dtype=np.float64, requirements=["C", "W"])


def _restore(flat: np.ndarray, shape: tuple, channels: bool) -> np.ndarray:
    out = flat.reshape(shape)
    if channels:
        out = np.moveaxis(out, -4, -1)
    return out


# --------------------------------------------------------------------------- reference tier


def _forward_reference(faces: np.ndarray) -> np.ndarray:
    """Obvious float64 tier: one Haar step on rows then columns per level, numpy over faces."""
    out = np.empty_like(faces)
    scaling = faces
    n = faces.shape[-1]
    while n > 1:
        h = n // 2
        # 1D orthonormal Haar step along the columns index j (rows of the image) ...
        lo_j = (scaling[..., :, 0::2] + scaling[..., :, 1::2]) / np.sqrt(2.0)
        hi_j = (scaling[..., :, 0::2] - scaling[..., :, 1::2]) / np.sqrt(2.0)
        # ... then along the row index i
        out[..., :h, h:n] = (hi_j[..., 0::2, :] + hi_j[..., 1::2, :]) / np.sqrt(2.0)  # "01"
        out[..., h:n, :h] = (lo_j[..., 0::2, :] - lo_j[..., 1::2, :]) / np.sqrt(2.0)  # "10"
        out[..., h:n, h:n] = (hi_j[..., 0::2, :] - hi_j[..., 1::2, :]) / np.sqrt(2.0)  # "11"
        scaling = (lo_j[..., 0::2, :] + lo_j[..., 1::2, :]) / np.sqrt(2.0)
        n = h
    out[..., 0, 0] = scaling[..., 0, 0]
    return out


def _inverse_reference(coeffs: np.ndarray) -> np.ndarray:
    """Obvious float64 tier of the inverse: undo the column step, then the row step, per level."""
    r = coeffs.shape[-1]
    scaling = coeffs[..., :1, :1].copy()
    h = 1
    while h < r:
        d01 = coeffs[..., :h, h : 2 * h]
        d10 = coeffs[..., h : 2 * h, :h]
        d11 = coeffs[..., h : 2 * h, h : 2 * h]
        lo_j = np.empty(coeffs.shape[:-2] + (2 * h, h))
        hi_j = np.empty_like(lo_j)
        lo_j[..., 0::2, :] = (scaling + d10) / np.sqrt(2.0)
        lo_j[..., 1::2, :] = (scaling - d10) / np.sqrt(2.0)
        hi_j[..., 0::2, :] = (d01 + d11) / np.sqrt(2.0)
        hi_j[..., 1::2, :] = (d01 - d11) / np.sqrt(2.0)
        scaling = np.empty(coeffs.shape[:-2] + (2 * h, 2 * h))
        scaling[..., :, 0::2] = (lo_j + hi_j) / np.sqrt(2.0)
        scaling[..., :, 1::2] = (lo_j - hi_j) / np.sqrt(2.0)
        h *= 2
    return scaling


# --------------------------------------------------------------------------- public


def _transform(values, name, method, channels, forward):
    method = _check_method(method)
    # The fast forward transform checks its output instead of its input: every texel
    # enters the face's scaling coefficient, so NaN or inf anywhere makes it non-finite.
    post_check = forward and method == "numba"
    arr = _as_cubemaps(values, name, channels=bool(channels), check_finite=not post_check)
    flat, shape = _flat_faces(arr, bool(channels))
    if method == "reference":
        out = _forward_reference(flat) if forward else _inverse_reference(flat)
    else:
        out = np.empty_like(flat)
        if flat.shape[0]:
            (_kernels.haar_forward if forward else _kernels.haar_inverse)(flat, out)
        if post_check and not np.all(np.isfinite(out[:, 0, 0])):
            _check_finite(flat, name)
            raise ValueError(f"{name} is too large: its Haar sums overflow float64; rescale it")
    return _restore(out, shape, bool(channels))


def haar2d(faces, method: str = "numba", channels: bool = False) -> np.ndarray:
    """Orthonormal non-standard 2D Haar transform of every cubemap face.

    Parameters
    ----------
    faces : (..., 6, r, r) float, or (..., 6, r, r, C) with ``channels=True``
        Texel values; ``r`` a power of two. Leading axes are batch axes.
    method : {"numba", "reference"}
        ``"numba"``: a parallel kernel over faces. ``"reference"``: the
        obvious numpy version (one 1D step on rows, one on columns, per level).
    channels : bool
        Whether the last axis is colour.

    Returns
    -------
    coeffs : same shape as ``faces``, float64
        Per face, in the in-place quadtree layout of the module docstring.

    Notes
    -----
    Per level, a 2x2 block ``[[a, b], [c, d]]`` (``a = x[2p, 2q]``,
    ``b = x[2p, 2q+1]``, ``c = x[2p+1, 2q]``, ``d = x[2p+1, 2q+1]``) becomes::

        scaling       (a + b + c + d) / 2   -> next level
        "01" [p, h+q]   (a - b + c - d) / 2
        "10" [h+p, q]   (a + b - c - d) / 2
        "11" [h+p, h+q] (a - b - c + d) / 2

    The transform ``W`` is orthogonal on texel space: ``sum x y = sum W(x) W(y)``
    (Parseval) and ``ihaar2d = W^T``. The coefficients live in *texel space*:
    ``[0, 0] = sum(x) / r``, and they are ``r`` times the L2 coefficients of
    the piecewise-constant face function on the unit square ``[0, 1]^2``. For
    an integral over the sphere ``int L V dw ~ sum L V omega`` weight one
    factor with :func:`solid_angle_weight` first.

    References
    ----------
    R. Ng, R. Ramamoorthi, P. Hanrahan, "All-frequency shadows using
    non-linear wavelet lighting approximation", SIGGRAPH 2003, Section 4
    (non-standard 2D Haar on cubemap faces). E. Stollnitz, T. DeRose,
    D. Salesin, "Wavelets for computer graphics: a primer, part 1", IEEE CG&A
    1995 (non-standard decomposition).

    Examples
    --------
    >>> import numpy as np
    >>> from prtlab.wavelet import haar2d, ihaar2d
    >>> x = np.random.default_rng(0).random((6, 8, 8))
    >>> np.allclose(ihaar2d(haar2d(x)), x)
    True
    >>> np.allclose(haar2d(np.ones((6, 4, 4)))[:, 0, 0], 4.0)  # sum / r
    True
    """
    return _transform(faces, "faces", method, channels, forward=True)


def ihaar2d(coeffs, method: str = "numba", channels: bool = False) -> np.ndarray:
    """Inverse of :func:`haar2d`: texel values from Haar coefficients.

    Parameters
    ----------
    coeffs : (..., 6, r, r) float, or (..., 6, r, r, C) with ``channels=True``
        Coefficients in the layout of :func:`haar2d`.
    method : {"numba", "reference"}
    channels : bool

    Returns
    -------
    faces : same shape as ``coeffs``, float64

    Notes
    -----
    ``ihaar2d = haar2d^T = haar2d^-1``, so ``<haar2d(x), y> = <x, ihaar2d(y)>``.
    """
    return _transform(coeffs, "coeffs", method, channels, forward=False)


def solid_angle_weight(faces, channels: bool = False) -> np.ndarray:
    """Multiply every texel by its solid angle, for relighting dot products.

    Parameters
    ----------
    faces : (..., 6, r, r) float, or (..., 6, r, r, C) with ``channels=True``

    Returns
    -------
    weighted : same shape, float64
        ``faces * omega`` with ``omega = cubemap_solid_angles(r)`` (steradians).

    Notes
    -----
    With ``L`` and ``V`` two cubemaps, by Parseval
    ``sum(haar2d(solid_angle_weight(L)) * haar2d(V)) = sum_texels L V omega``,
    the quadrature of ``int_S2 L(w) V(w) dw``: pre-multiply one factor (the
    transfer, once, at precomputation) and per frame only a dot product of
    coefficients remains.
    """
    arr = _as_cubemaps(faces, "faces", channels=bool(channels))
    omega = cubemap_solid_angles(arr.shape[-2] if channels else arr.shape[-1])
    return arr * (omega[..., None] if channels else omega)


def coefficient_levels(res: int) -> np.ndarray:
    """Level of every coefficient of a face in the :func:`haar2d` layout.

    Returns
    -------
    level : (res, res) int64
        ``-1`` for the scaling coefficient ``[0, 0]``, ``l`` (0 = coarsest,
        the whole face) for the wavelets of level ``l``.
    """
    res = _check_resolution(res)
    idx = np.arange(res)
    lev = np.zeros(res, dtype=np.int64)
    lev[1:] = np.floor(np.log2(idx[1:])).astype(np.int64)
    level = np.maximum(lev[:, None], lev[None, :])
    level[0, 0] = -1
    return level


def support_solid_angles(res: int) -> np.ndarray:
    """Solid angle of the support of every Haar basis function of a cubemap.

    Parameters
    ----------
    res : int
        Face resolution (a power of two).

    Returns
    -------
    area : (6, res, res) float64
        For the scaling coefficient the face's solid angle (``4 pi / 6``); for
        a wavelet of node ``(p, q)`` at level ``l`` the solid angle of its
        square of ``m = res / 2**l`` texels on a side. Use as ``weights`` in
        :func:`keep_largest` for Ng et al.'s area-weighted selection.
    """
    res = _check_resolution(res)
    omega = cubemap_solid_angles(res)[0]
    area = np.empty((res, res))
    area[0, 0] = omega.sum()
    h = 1
    while h < res:
        m = res // h
        block = omega.reshape(h, m, h, m).sum(axis=(1, 3))
        area[:h, h : 2 * h] = block
        area[h : 2 * h, :h] = block
        area[h : 2 * h, h : 2 * h] = block
        h *= 2
    return np.broadcast_to(area, (6, res, res)).copy()

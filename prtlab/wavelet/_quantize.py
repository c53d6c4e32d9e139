"""Pulse basis, 8-bit quantisation and sparse per-vertex transfer (Yue et al. 2009).

The direct light of the portals pipeline is, per vertex, a transfer cubemap
``T (6, r, r)`` (the contribution of each direction cell, solid angle and BRDF
folded in) dotted with the light cubemap ``L`` every frame:
``L_v = sum_texels T L`` (Yue et al. 2009, Appendix eq. 7). Yue et al. store
``T`` either in the pulse basis (one box function per cell: the texels
themselves) or in the Haar basis, each quantised to 8 bits with the
per-vertex maximum as scale, and keep whichever needs fewer non-zero bytes
(Section 4.1.2). Both bases are orthonormal in texel space, so the dot product
is the same in either: ``sum T L = sum haar2d(T) haar2d(L)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from . import _kernels
from ._haar import (
    _as_cubemaps,
    _as_real,
    _check_finite,
    _check_method,
    _check_resolution,
    _kernel_array,
    haar2d,
    ihaar2d,
)

__all__ = ["Quantized8", "quantize8", "dequantize8", "SparseTransfer", "encode_transfer"]

_LEVELS = 255
_BASES = ("auto", "pulse", "haar")
_CHUNK = 2048  # vertices per encoding chunk (bounds the float64 scratch)


class Quantized8(NamedTuple):
    """8-bit codes of a set of groups of values, one scale per group.

    ``codes`` (uint8) quantise ``|value|``; ``negative`` (bool) holds the sign;
    ``scale`` (float32) is the group's maximum ``|value|`` rounded up to float32.
    """

    codes: np.ndarray
    scale: np.ndarray
    negative: np.ndarray


def _group_axes(ndim: int, group_ndim) -> tuple[int, ...]:
    if isinstance(group_ndim, bool) or not isinstance(group_ndim, (int, np.integer)):
        raise TypeError(f"group_ndim must be an int (trailing axes sharing one scale), got {type(group_ndim).__name__}")
    group_ndim = int(group_ndim)
    if not 0 <= group_ndim <= ndim:
        raise ValueError(
            f"group_ndim must be between 0 and values.ndim = {ndim} (e.g. 3 for one (6, r, r) cubemap "
            f"per vertex), got {group_ndim}"
        )
    return tuple(range(ndim - group_ndim, ndim))


def _scale_of(magnitude: np.ndarray, axes: tuple[int, ...]) -> np.ndarray:
    """Per-group maximum rounded *up* to float32, so every ``|v| <= scale`` holds exactly."""
    peak = magnitude.max(axis=axes) if magnitude.size else np.zeros(magnitude.shape[: magnitude.ndim - len(axes)])
    if np.any(peak > np.finfo(np.float32).max):
        raise ValueError("values exceed the float32 range of the quantisation scale (|v| > 3.4e38); rescale them")
    scale = np.asarray(peak, dtype=np.float32)
    return np.where(scale.astype(np.float64) < peak, np.nextafter(scale, np.float32(np.inf)), scale)


def _quantize(arr: np.ndarray, axes: tuple[int, ...]) -> Quantized8:
    magnitude = np.abs(arr)
    scale = _scale_of(magnitude, axes)
    s = scale.astype(np.float64).reshape(scale.shape + (1,) * len(axes))
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(s > 0, magnitude / s, 0.0)
    codes = np.minimum(np.floor(ratio * _LEVELS + 0.5), _LEVELS).astype(np.uint8)
    return Quantized8(codes, scale, (arr < 0) & (codes > 0))


def quantize8(values, group_ndim: int = 3) -> Quantized8:
    """Quantise values to 8 bits with one scale (the group maximum) per group.

    Parameters
    ----------
    values : (..., *group) float
        E.g. ``(V, 6, r, r)`` transfer cubemaps (pulse basis) or their Haar
        coefficients; signed values are allowed.
    group_ndim : int
        Number of trailing axes that share one scale (3: one cubemap per vertex).

    Returns
    -------
    Quantized8
        ``codes`` (values.shape) uint8, ``scale`` (values.shape[:-group_ndim])
        float32, ``negative`` (values.shape) bool.

    Notes
    -----
    ``scale = max |v|`` over the group, rounded up to the next float32, and
    ``code = floor(255 |v| / scale + 1/2)`` (round to nearest, halves up), so
    ``|dequantize8(q) - v| <= scale / 510`` for every value. An all-zero group
    has ``scale = 0`` and all codes 0.

    References
    ----------
    Y. Yue, K. Iwasaki, B.-Y. Chen, Y. Dobashi, T. Nishita, "Interactive
    rendering of interior scenes with dynamic environment illumination",
    CGF 28(7) 2009, Section 4.1.2 (steps 4-6: quantise to 8 bits with the
    per-vertex maximum contribution).

    Examples
    --------
    >>> import numpy as np
    >>> from prtlab.wavelet import quantize8, dequantize8
    >>> q = quantize8(np.array([[2.0, 1.0, -0.5, 0.0]]), group_ndim=1)
    >>> q.codes.tolist(), q.scale.tolist(), dequantize8(q).round(3).tolist()
    ([[255, 128, 64, 0]], [2.0], [[2.0, 1.004, -0.502, 0.0]])
    """
    arr = _as_real(values, "values")
    _check_finite(arr, "values")
    return _quantize(arr, _group_axes(arr.ndim, group_ndim))


def dequantize8(quantized: Quantized8) -> np.ndarray:
    """Values from 8-bit codes: ``(-1)**negative * code * scale / 255``, float64."""
    codes, scale, negative = quantized
    codes = np.asarray(codes)
    scale = np.asarray(scale, dtype=np.float64)
    if codes.dtype != np.uint8:
        raise TypeError(f"codes must be uint8 (from quantize8), got dtype {codes.dtype}")
    if scale.ndim > codes.ndim or codes.shape[: scale.ndim] != scale.shape:
        raise ValueError(
            f"scale must have the leading shape of codes (codes {codes.shape}, scale {scale.shape}); "
            "pass the Quantized8 returned by quantize8"
        )
    s = scale.reshape(scale.shape + (1,) * (codes.ndim - scale.ndim))
    values = codes.astype(np.float64) * (s / _LEVELS)
    return np.where(np.asarray(negative, dtype=bool), -values, values)


# --------------------------------------------------------------------------- sparse transfer


@dataclass(frozen=True, eq=False)
class SparseTransfer:
    """8-bit sparse transfer cubemaps, one basis (pulse or Haar) per vertex.

    A CSR layout over vertices: the entries of vertex ``v`` are
    ``indptr[v]:indptr[v+1]``.

    Attributes
    ----------
    indptr : (V + 1,) int64
    indices : (E,) uint16 (if ``6 r**2 <= 2**15``) or uint32
        Low bits: the coefficient's index into the flattened ``(6, r, r)``
        cubemap (texel in the pulse basis, :func:`haar2d` layout in the Haar
        basis). Top bit (``sign_bit``): set when the coefficient is negative.
    codes : (E,) uint8
        Non-zero magnitude codes, ``|value| ~ code * scale / 255``.
    scale : (V,) float32
        Per-vertex maximum ``|value|`` in the chosen basis (see :func:`quantize8`).
    basis : (V,) uint8
        0 pulse, 1 Haar.
    res : int
        Face resolution r.
    """

    indptr: np.ndarray
    indices: np.ndarray
    codes: np.ndarray
    scale: np.ndarray
    basis: np.ndarray
    res: int

    PULSE = 0
    HAAR = 1

    def __post_init__(self):
        res = _check_resolution(self.res)
        fields = {}
        for name, dtypes in (("indptr", (np.int64,)), ("indices", (np.uint16, np.uint32)), ("codes", (np.uint8,)),
                             ("scale", (np.float32,)), ("basis", (np.uint8,))):
            arr = np.asarray(getattr(self, name))
            if arr.ndim != 1 or arr.dtype not in dtypes:
                raise TypeError(
                    f"SparseTransfer.{name} must be a 1D {' or '.join(np.dtype(d).name for d in dtypes)} array, "
                    f"got {arr.dtype} with shape {arr.shape}; build the container with encode_transfer"
                )
            fields[name] = np.require(arr, requirements=["C", "W"])
        n_vertices = fields["indptr"].shape[0] - 1
        n_entries = fields["codes"].shape[0]
        if (
            n_vertices < 0
            or fields["indptr"][0] != 0
            or fields["indptr"][-1] != n_entries
            or np.any(np.diff(fields["indptr"]) < 0)
            or fields["indices"].shape[0] != n_entries
            or fields["scale"].shape[0] != n_vertices
            or fields["basis"].shape[0] != n_vertices
            or np.any(fields["basis"] > 1)
        ):
            raise ValueError(
                "SparseTransfer arrays are inconsistent: need indptr (V+1,) non-decreasing from 0 to E, "
                "indices and codes (E,), scale and basis (V,) with basis in {0, 1}; build it with encode_transfer"
            )
        sign_bit = 1 << (8 * fields["indices"].dtype.itemsize - 1)
        if n_entries and int((fields["indices"].astype(np.int64) & (sign_bit - 1)).max()) >= 6 * res * res:
            raise ValueError(f"SparseTransfer.indices point beyond the 6 * {res}**2 coefficients of a cubemap")
        for name, arr in fields.items():
            object.__setattr__(self, name, arr)
        object.__setattr__(self, "res", res)

    @property
    def n_vertices(self) -> int:
        return int(self.indptr.shape[0] - 1)

    @property
    def sign_bit(self) -> int:
        return 1 << (8 * self.indices.dtype.itemsize - 1)

    @property
    def nbytes(self) -> int:
        """Memory of the stored arrays in bytes (indptr, indices, codes, scale, basis)."""
        return int(sum(x.nbytes for x in (self.indptr, self.indices, self.codes, self.scale, self.basis)))

    def coefficients(self) -> np.ndarray:
        """Dequantised coefficients, each vertex in its own basis: (V, 6, r, r) float64."""
        n = 6 * self.res * self.res
        out = np.zeros((self.n_vertices, n))
        raw = self.indices.astype(np.int64)
        k = raw & (self.sign_bit - 1)
        sign = np.where(raw >= self.sign_bit, -1.0, 1.0)
        rows = np.repeat(np.arange(self.n_vertices), np.diff(self.indptr))
        out[rows, k] = sign * self.codes * (self.scale.astype(np.float64)[rows] / _LEVELS)
        return out.reshape(self.n_vertices, 6, self.res, self.res)

    def to_dense(self) -> np.ndarray:
        """Dequantised transfer cubemaps in the texel (pulse) domain: (V, 6, r, r) float64."""
        dense = self.coefficients()
        haar = self.basis == self.HAAR
        if np.any(haar):
            dense[haar] = ihaar2d(dense[haar])
        return dense

    def dot(self, light_pulse, light_haar=None, method: str = "numba") -> np.ndarray:
        """Per-vertex dot product with a light cubemap: ``sum_texels T_v L``.

        Parameters
        ----------
        light_pulse : (6, r, r) or (6, r, r, C) float
            The light cubemap texels (pulse coefficients).
        light_haar : same shape, optional
            Its Haar coefficients; default ``haar2d(light_pulse)``.
        method : {"numba", "reference"}
            ``"numba"``: a ``prange`` over vertices reading only the stored
            entries (the per-frame direct-light pass of the portals pipeline).
            ``"reference"``: dense coefficients times the light, per basis.

        Returns
        -------
        radiance : (V,) or (V, C) float64
        """
        method = _check_method(method)
        channels = np.ndim(light_pulse) == 4
        lp = _as_cubemaps(light_pulse, "light_pulse", channels=channels)
        r = lp.shape[-2] if channels else lp.shape[-1]
        want = (6, self.res, self.res) + (lp.shape[-1:] if channels else ())
        if lp.shape != want:
            raise ValueError(
                f"light_pulse must have shape {want} to match the transfer (r = {self.res}), got {lp.shape}"
            )
        if light_haar is None:
            lh = haar2d(lp, channels=channels)
        else:
            lh = _as_real(light_haar, "light_haar")
            if lh.shape != lp.shape:
                raise ValueError(f"light_haar must have the shape of light_pulse {lp.shape}, got {lh.shape}")
            _check_finite(lh, "light_haar")
        n = 6 * r * r
        lp2 = _kernel_array(lp.reshape(n, -1))
        lh2 = _kernel_array(lh.reshape(n, -1))
        if method == "reference":
            coeffs = self.coefficients().reshape(self.n_vertices, n)
            out = np.where((self.basis == self.HAAR)[:, None], coeffs @ lh2, coeffs @ lp2)
        else:
            out = np.empty((self.n_vertices, lp2.shape[1]))
            if self.n_vertices:
                _kernels.sparse_dot(
                    self.indptr, self.indices, self.codes, self.scale, self.basis,
                    np.int64(self.sign_bit), lp2, lh2, out,
                )
        return out if channels else out[:, 0]


def _check_basis(basis) -> str:
    if basis not in _BASES:
        raise ValueError(f"basis must be one of {', '.join(repr(b) for b in _BASES)}, got {basis!r}")
    return basis


def _concatenate(parts, dtype) -> np.ndarray:
    return np.concatenate(parts).astype(dtype, copy=False) if parts else np.zeros(0, dtype)


def _choose_basis(chunk, basis: str) -> tuple[Quantized8, np.ndarray]:
    """The 8-bit codes of each cubemap of ``chunk (v, 6, r, r)`` in its basis, and whether that is Haar (v,)."""
    n = chunk[0].size
    pulse = _quantize(chunk.reshape(-1, n), (1,)) if basis != "haar" else None
    haar = _quantize(haar2d(chunk).reshape(-1, n), (1,)) if basis != "pulse" else None
    if basis != "auto":
        return (haar if basis == "haar" else pulse), np.full(chunk.shape[0], basis == "haar")
    use_haar = np.count_nonzero(haar.codes, axis=1) < np.count_nonzero(pulse.codes, axis=1)
    per_entry = use_haar[:, None]
    chosen = Quantized8(
        np.where(per_entry, haar.codes, pulse.codes),
        np.where(use_haar, haar.scale, pulse.scale),
        np.where(per_entry, haar.negative, pulse.negative),
    )
    return chosen, use_haar


def encode_transfer(transfer, basis: str = "auto") -> SparseTransfer:
    """Encode per-vertex transfer cubemaps as 8-bit sparse pulse or Haar coefficients.

    Parameters
    ----------
    transfer : (V, 6, r, r) float
        One cubemap per vertex (texel values: the pulse coefficients).
    basis : {"auto", "pulse", "haar"}
        ``"auto"`` (Yue et al.): per vertex, quantise both the texels and their
        Haar coefficients (:func:`quantize8`, one scale per vertex and basis)
        and keep the one with fewer non-zero codes (ties: pulse, which needs no
        transform). ``"pulse"`` / ``"haar"`` force one basis.

    Returns
    -------
    SparseTransfer
        Only non-zero codes are stored; ``to_dense()`` reconstructs the
        dequantised cubemaps, ``dot(light)`` relights.

    Notes
    -----
    Every stored entry costs the same (an index and a code), so fewer non-zero
    codes is fewer bytes. The pulse basis wins when only a few cells see the
    portal; the Haar basis when a vertex sees a large portal (Yue et al.
    report 3-4x more storage for Haar far from small portals and ~40% of the
    pulse storage near large ones).

    References
    ----------
    Y. Yue et al., "Interactive rendering of interior scenes with dynamic
    environment illumination", CGF 28(7) 2009, Section 3.4 and 4.1.2.

    Examples
    --------
    >>> import numpy as np
    >>> from prtlab.wavelet import encode_transfer
    >>> transfer = np.zeros((2, 6, 8, 8))
    >>> transfer[0, 4, 3, 5] = 0.2  # sees the portal through one cell: pulse
    >>> transfer[1, 2] = 0.1  # sees a whole face: one Haar coefficient
    >>> sparse = encode_transfer(transfer)
    >>> sparse.basis.tolist(), sparse.indptr.tolist()
    ([0, 1], [0, 1, 2])
    >>> sparse.dot(np.ones((6, 8, 8))).round(6).tolist()  # sum of T * L per vertex
    [0.2, 6.4]
    """
    basis = _check_basis(basis)
    arr = _as_cubemaps(transfer, "transfer")
    if arr.ndim != 4:
        raise ValueError(
            f"transfer must have shape (V, 6, r, r), one cubemap per vertex, got shape {arr.shape}; "
            "reshape it to (-1, 6, r, r)"
        )
    n_vertices, r = arr.shape[0], arr.shape[-1]
    n = 6 * r * r
    index_dtype = np.uint16 if n <= (1 << 15) else np.uint32
    sign_bit = 1 << (8 * np.dtype(index_dtype).itemsize - 1)
    counts, indices, codes, scales, bases = [], [], [], [], []
    for start in range(0, n_vertices, _CHUNK):
        chunk = arr[start : start + _CHUNK]
        chosen, use_haar = _choose_basis(chunk, basis)
        rows, cols = np.nonzero(chosen.codes)
        counts.append(np.bincount(rows, minlength=chunk.shape[0]))
        indices.append((cols | np.where(chosen.negative[rows, cols], sign_bit, 0)).astype(index_dtype))
        codes.append(chosen.codes[rows, cols])
        scales.append(chosen.scale)
        bases.append(use_haar.astype(np.uint8))
    indptr = np.zeros(n_vertices + 1, dtype=np.int64)
    if n_vertices:
        np.cumsum(np.concatenate(counts), out=indptr[1:])
    return SparseTransfer(
        indptr=indptr,
        indices=_concatenate(indices, index_dtype),
        codes=_concatenate(codes, np.uint8),
        scale=_concatenate(scales, np.float32),
        basis=_concatenate(bases, np.uint8),
        res=int(r),
    )

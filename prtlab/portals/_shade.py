"""The per-frame shader passes of the portals pipeline (Yue et al. 2009, Section 5, Appendix)."""

from __future__ import annotations

import numpy as np

from prtlab.wavelet import SparseTransfer, haar2d

from . import _kernels

__all__ = ["direct_pass", "indirect_pass"]

_METHODS = ("numba", "reference")


def _check_method(method):
    if method not in _METHODS:
        raise ValueError(f"method must be 'numba' or 'reference', got {method!r}")


def direct_pass(direct: SparseTransfer, albedo, shell_cube, method: str = "numba") -> np.ndarray:
    """Direct radiance ``L_d(v) = rho_v sum_k T_k(v) L_s,k`` (Appendix Eq. 7, Section 4.1.2).

    Parameters
    ----------
    direct : SparseTransfer
        8-bit per-vertex transfer, pulse or Haar per vertex (``V`` vertices).
    albedo : (V, 3) float
    shell_cube : (6, r, r, 3) float
        Texel averages of the shell light (:func:`prtlab.portals.shell_light`).
    method : {"numba", "reference"}
        ``"numba"``: one fused kernel (``prange`` over vertices) reading only the
        stored 8-bit entries, the albedo folded in; ``"reference"``: dense float64
        coefficients (:meth:`prtlab.wavelet.SparseTransfer.dot`).

    Returns
    -------
    (V, 3) float64

    Notes
    -----
    Both bases are orthonormal in texel space, so the dot product in the
    vertex's stored basis equals the texel-space one:
    ``sum_k T_k L_k = sum_j haar(T)_j haar(L)_j``.
    """
    _check_method(method)
    albedo = np.asarray(albedo, dtype=np.float64)
    if albedo.shape != (direct.n_vertices, 3):
        raise ValueError(f"albedo must have shape ({direct.n_vertices}, 3), got {albedo.shape}")
    cube = np.asarray(shell_cube, dtype=np.float64)
    want = (6, direct.res, direct.res, 3)
    if cube.shape != want:
        raise ValueError(f"shell_cube must have shape {want} to match the transfer (r = {direct.res}), got "
                         f"{cube.shape}; build it with shell_light(source, {direct.res})")
    if not np.all(np.isfinite(cube)):
        raise ValueError("shell_cube has NaN or infinite values")
    if method == "reference":
        return direct.dot(cube, method="reference") * albedo
    n = 6 * direct.res * direct.res
    light = np.zeros((2 * n, 3))
    light[:n] = cube.reshape(n, 3)
    if np.any(direct.basis == direct.HAAR):  # the Haar coefficients only when some vertex stores Haar
        light[n:] = haar2d(cube, channels=True).reshape(n, 3)
    out = np.empty((direct.n_vertices, 3))
    if direct.n_vertices:
        _kernels.direct_pass_kernel(direct.indptr, direct.indices, direct.codes, direct.scale, direct.basis,
                                    np.int64(direct.sign_bit), light, np.ascontiguousarray(albedo), out)
    return out


def indirect_pass(transfer, light_sh, method: str = "numba") -> np.ndarray:
    """Indirect radiance of diffuse vertices ``L_i(v) = sum_lm t_lm(v) c_lm`` (Appendix Eq. 6).

    Parameters
    ----------
    transfer : (V, n*n, 3) float
        Per-vertex transfer vectors per colour channel (albedo folded in).
    light_sh : (n*n, 3) float
        SH coefficients of the shell light (:func:`prtlab.portals.shell_sh`).
    method : {"numba", "reference"}

    Returns
    -------
    (V, 3) float64
    """
    _check_method(method)
    transfer = np.asarray(transfer)
    light_sh = np.asarray(light_sh, dtype=np.float64)
    if transfer.ndim != 3 or transfer.shape[2] != 3:
        raise ValueError(f"transfer must have shape (V, n*n, 3), got {transfer.shape}")
    if light_sh.shape != transfer.shape[1:]:
        raise ValueError(f"light_sh must have shape {transfer.shape[1:]} to match the transfer, got {light_sh.shape}")
    if not np.all(np.isfinite(light_sh)):
        raise ValueError("light_sh has NaN or infinite values")
    if method == "reference":
        return np.einsum("vic,ic->vc", transfer.astype(np.float64), light_sh)
    out = np.zeros((transfer.shape[0], 3))
    if transfer.shape[0]:
        _kernels.indirect_pass_kernel(np.ascontiguousarray(transfer, dtype=np.float32),
                                      np.ascontiguousarray(light_sh), out)
    return out

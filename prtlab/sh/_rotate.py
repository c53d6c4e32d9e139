"""Rotation of real SH coefficient vectors.

``rotate(coeffs, R)`` returns the coefficients of ``g(w) = f(R^T w)``: the
function f turned by R. Band l of g is ``M_l(R) @ (band l of f)`` with the
orthogonal ``(2l+1, 2l+1)`` block

    M_l(R)[m, m'] = int_S2 Y_lm(w) Y_lm'(R^T w) dw.

In the design's basis band 1 is ``c (y, z, x)``, so ``M_1(R) = P R P^T`` with
``P`` the permutation taking ``(x, y, z)`` to ``(y, z, x)``; the higher blocks
follow by the Ivanic-Ruedenberg recurrence. ``M_l(A B) = M_l(A) M_l(B)``.
"""

from __future__ import annotations

import numpy as np

from prtlab._validate import check_order

from . import _kernels
from ._eval import _as_coeffs, _check_method, basis_reference

__all__ = ["rotate", "rotation_matrices", "rotation_matrix"]

_ROT_TOL = 1e-6


def _as_rotations(R, name: str = "R") -> np.ndarray:
    """Coerce ``(..., 3, 3)`` proper rotations (orthonormal and det +1 within 1e-6)."""
    arr = np.asarray(R)
    if arr.dtype.kind not in "fiu":
        raise TypeError(f"{name} must be a real (3, 3) or (..., 3, 3) array, got dtype {arr.dtype}")
    arr = arr.astype(np.float64, copy=False)
    if arr.ndim < 2 or arr.shape[-2:] != (3, 3):
        raise ValueError(f"{name} must be a (3, 3) or (..., 3, 3) rotation matrix, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf; pass finite rotation matrices")
    if arr.size:
        eye_err = np.abs(np.einsum("...ij,...kj->...ik", arr, arr) - np.eye(3)).max()
        if eye_err > _ROT_TOL:
            raise ValueError(
                f"{name} is not orthonormal (max |R R^T - I| = {eye_err:.3g} > {_ROT_TOL:g}); "
                "pass a proper rotation matrix (re-orthonormalise it, e.g. by SVD or QR)"
            )
        det = np.linalg.det(arr)
        if np.any(np.abs(det - 1.0) > _ROT_TOL):
            raise ValueError(
                f"{name} is a reflection, not a proper rotation (det = {det.ravel()[np.argmax(np.abs(det.ravel() - 1))]:.6g}); "
                "pass a rotation with det +1"
            )
    return arr


def _packed_blocks(rot_flat: np.ndarray, order: int) -> np.ndarray:
    """(B, sum_l (2l+1)^2) packed blocks of ``rot_flat (B, 3, 3)`` by Ivanic-Ruedenberg."""
    offsets = _kernels.block_offsets(order)
    blocks = np.zeros((rot_flat.shape[0], int(offsets[-1])))
    if rot_flat.shape[0]:
        _kernels.ivanic_ruedenberg(_kernels.kernel_array(rot_flat), order, offsets, blocks)
    return blocks


def _quadrature_blocks(rot_flat: np.ndarray, order: int) -> np.ndarray:
    """Reference tier: ``M_l[m, m'] = sum_k w_k Y_lm(d_k) Y_lm'(R^T d_k)``, exact for degree 2l."""
    from ._project import quadrature

    dirs, weights = quadrature(order)
    y = basis_reference(dirs, order)
    offsets = _kernels.block_offsets(order)
    blocks = np.zeros((rot_flat.shape[0], int(offsets[-1])))
    for r, rot in enumerate(rot_flat):
        y_rot = basis_reference(dirs @ rot, order)  # rows: Y(R^T d_k)
        for l in range(order):
            sl = slice(l * l, (l + 1) * (l + 1))
            blk = (y[:, sl] * weights[:, None]).T @ y_rot[:, sl]
            blocks[r, offsets[l] : offsets[l + 1]] = blk.ravel()
    return blocks


#: The blocks of the last single rotations asked for (``_blocks``): (its float64 bytes, order, method) -> the
#: packed blocks, never handed out to be written (``rotate`` reads them, ``rotation_matrices`` copies them).
#: Callers that rotate by the same few poses again and again (an object's pose in every frame) skip the checks
#: and the recurrence; the blocks are the values the computation gives.
_KEPT_BLOCKS: dict = {}
_KEPT_MAX = 256


def _blocks(R, order: int, method: str):
    order = check_order(order)
    method = _check_method(method)
    arr = np.asarray(R)
    key = None
    if arr.shape == (3, 3) and arr.dtype == np.float64:
        key = (arr.tobytes(), order, method)
        kept = _KEPT_BLOCKS.get(key)
        if kept is not None:
            return (), kept, order
    rot = _as_rotations(R)
    flat = rot.reshape(-1, 3, 3)
    blocks = _packed_blocks(flat, order) if method == "numba" else _quadrature_blocks(flat, order)
    if key is not None:
        if len(_KEPT_BLOCKS) >= _KEPT_MAX:
            _KEPT_BLOCKS.clear()
        _KEPT_BLOCKS[key] = blocks
    return rot.shape[:-2], blocks, order


def rotation_matrices(R, order: int, method: str = "numba") -> list[np.ndarray]:
    """Per-band SH rotation blocks of R.

    Parameters
    ----------
    R : (3, 3) or (..., 3, 3) float
        Proper rotations (orthonormal, det +1, within 1e-6).
    order : int
        Number of bands n.
    method : {"numba", "reference"}
        ``"numba"``: Ivanic-Ruedenberg recurrence in a parallel kernel.
        ``"reference"``: each block by exact product quadrature,
        ``M_l[m, m'] = int Y_lm(w) Y_lm'(R^T w) dw`` (slow, obvious).

    Returns
    -------
    blocks : list of n arrays, ``blocks[l]`` of shape (..., 2l+1, 2l+1)
        Band l of ``rotate(f, R)`` is ``blocks[l] @ f[l*l:(l+1)**2]``.

    Notes
    -----
    ``M_0 = 1``, ``M_1 = P R P^T`` where ``P`` reorders ``(x, y, z)`` to the
    band-1 order ``(y, z, x)``; ``M_l(A B) = M_l(A) M_l(B)`` and every block
    is orthogonal.

    References
    ----------
    J. Ivanic, K. Ruedenberg, "Rotation matrices for real spherical harmonics.
    Direct determination by recursion", J. Phys. Chem. 100 (1996) 6342-6347,
    Tables 1 and 2 (eq. 8.1); erratum J. Phys. Chem. A 102 (1998) 9099-9100.
    """
    batch, blocks, order = _blocks(R, order, method)
    offsets = _kernels.block_offsets(order)
    out = []
    for l in range(order):
        d = 2 * l + 1
        out.append(blocks[:, offsets[l] : offsets[l + 1]].reshape(batch + (d, d)).copy())
    return out


def rotation_matrix(R, order: int, method: str = "numba") -> np.ndarray:
    """Dense block-diagonal ``(..., n*n, n*n)`` SH rotation matrix of R.

    ``rotate(f, R) == rotation_matrix(R, n) @ f``; see :func:`rotation_matrices`
    for the blocks, the convention and the reference.
    """
    blocks = rotation_matrices(R, order, method=method)
    order = len(blocks)
    batch = blocks[0].shape[:-2]
    dense = np.zeros(batch + (order * order, order * order))
    for l, blk in enumerate(blocks):
        sl = slice(l * l, (l + 1) * (l + 1))
        dense[..., sl, sl] = blk
    return dense


def rotate(coeffs, R, method: str = "numba", channels: bool | None = None) -> np.ndarray:
    """Rotate SH functions: coefficients of ``w -> f(R^T w)``.

    Parameters
    ----------
    coeffs : (..., n*n) or (..., n*n, C) float
        SH coefficients (colour as a trailing axis; see :func:`evaluate` for
        how the coefficient axis is found and ``channels``).
    R : (3, 3) or (..., 3, 3) float
        Proper rotation(s); their batch axes broadcast with those of ``coeffs``.
    method : {"numba", "reference"}
        Block computation tier (see :func:`rotation_matrices`); the blocks are
        always applied by a parallel numba kernel.
    channels : bool, optional
        Whether ``coeffs`` has a trailing colour axis (default: inferred).

    Returns
    -------
    rotated : (B..., n*n) or (B..., n*n, C) float64
        ``B`` is the broadcast of the batch axes of ``coeffs`` and ``R``.

    Notes
    -----
    If ``f = sum_i c_i Y_i`` then ``rotate(c, R)`` are the coefficients of
    ``g(w) = f(R^T w)``, so ``evaluate(rotate(c, R), R @ w) == evaluate(c, w)``.
    Band energies ``sum_m c_lm^2`` are invariant, and
    ``rotate(rotate(c, B), A) == rotate(c, A @ B)``.

    Examples
    --------
    >>> import numpy as np
    >>> from prtlab.sh import rotate, basis
    >>> Rz = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # +90 deg about z
    >>> c = basis(np.array([1.0, 0.0, 0.0]), 2)  # a lobe towards +x
    >>> np.allclose(rotate(c, Rz), basis(np.array([0.0, 1.0, 0.0]), 2))  # now towards +y
    True
    """
    coeffs, order, has_channels = _as_coeffs(coeffs, channels=channels)
    r_batch, blocks, order = _blocks(R, order, method)
    c_batch = coeffs.shape[:-2] if has_channels else coeffs.shape[:-1]
    try:
        out_batch = np.broadcast_shapes(c_batch, r_batch)
    except ValueError:
        raise ValueError(
            f"the batch axes of coeffs {c_batch} and of R {r_batch} do not broadcast; "
            "pass one R (3, 3) or rotations whose batch axes match the coefficients'"
        ) from None
    n_channels = coeffs.shape[-1] if has_channels else 1
    shaped = coeffs if has_channels else coeffs[..., None]
    if shaped.shape[:-2] != out_batch:
        shaped = np.broadcast_to(shaped, out_batch + (order * order, n_channels))
    flat = _kernels.kernel_array(shaped.reshape(-1, order * order, n_channels))
    n_rot = blocks.shape[0]
    rot_index = np.broadcast_to(np.arange(n_rot, dtype=np.int64).reshape(r_batch), out_batch).ravel()
    rot_index = _kernels.kernel_array(rot_index, dtype=np.int64)
    out = np.empty_like(flat)
    if flat.shape[0]:
        _kernels.apply_blocks(blocks, _kernels.block_offsets(order), rot_index, flat, out)
    if has_channels:
        return out.reshape(out_batch + (order * order, n_channels))
    return out.reshape(out_batch + (order * order,))

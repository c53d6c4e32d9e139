"""The per-frame passes of Iwasaki et al. 2007 (Sec. 5): basis irradiance, weights, bounces, radiance.

Notation (per receiver vertex ``x_j``, receiver BRDF terms ``k'``, source terms
``k``, basis functions ``i``, colour ``c``; ``m = k N + i`` flattens ``(k, i)``):

* transfer ``T_jk' = P_n(V_j G_jk')``: the visibility of the vertex toward the
  source (self-visibility times the occlusion fields of the objects other than
  source and receiver) times the SH of ``g_k' cos``, truncated to order n.
* basis irradiance (Eq. 13) ``Phi_(k',m)(x_j) = int S_m(x_j, w) V_j(w) g_k'(w) (n . w) dw
  = < S_m(x_j), T_jk' >`` (exact for order-n functions, as in
  :func:`prtlab.shadowfields.direct_pass`).
* reflected light of a bounce ``L_k'(x_j) = sum_s sum_m Phi^s_(k',m)(x_j) w^s_(m, c)`` (Eq. 12 without
  ``h_k'``), and the radiance ``B(x_j, w_o) = sum_k' h_k'(w_o) colour_k' L_k'(x_j)``.
* weights (Eq. 14): ``w^s_(k,.), c = A^{-1} Psi (colour_k,c L_k,c)`` per term ``k``: the least-squares
  fit of the source's outgoing-radiance factors by its basis (colour folded into the weights).

References
----------
K. Iwasaki et al., EGSR 2007, Eq. (9), (12)-(14), Sec. 5.1-5.3.
"""

from __future__ import annotations

import numpy as np

from prtlab import sh
from prtlab.shadowfields import SphereGrid, interpolate_field

from ._fields import StoredBasisRadiance
from ._kernels import bounce_kernel, eq13_kernel, outgoing_kernel

__all__ = ["basis_irradiance", "reflected_light", "fit_weights", "outgoing_radiance"]

_METHODS = ("numba", "reference")
#: Fields larger than this (bytes) are read with the receiver vertices sorted by cell (the kernel's
#: ``in_cell_order``): for larger fields, 8 rows gathered per vertex in the callers' order cost more than gathering
#: the vertices' own data in blocks; for smaller, less (the crossover measured between 6 and 12.5 MB: see
#: docs/notes/interreflection.md).
_CELL_ORDER_BYTES = 8 << 20
_NOT_FINITE = "points or transfer contain NaN or inf"


def _check_method(method):
    if method not in _METHODS:
        raise ValueError(f"method must be 'numba' or 'reference', got {method!r}")
    return method


def basis_irradiance(field, grid: SphereGrid, points, transfer, source_transform=None,
                     method: str = "numba") -> np.ndarray:
    """Basis irradiance ``Phi_(k',k,i)`` of one source at receiver vertices (Eq. 13).

    Parameters
    ----------
    field : (n_r, 6, res, res, K, N, n*n) float, or StoredBasisRadiance
        The source's basis radiance field (object space), dense or as stored (read in its format,
        accumulated in float64).
    grid : SphereGrid
        Its sample spheres.
    points : (V, 3) float
        Receiver vertices, world space.
    transfer : (V, K', n*n) float
        ``P_n(V_j G_jk')`` in the world frame.
    source_transform : prtlab.scene.Transform, optional
        The source's pose (default identity).
    method : {"numba", "reference"}

    Returns
    -------
    phi : (V, K', K, N) float64
        Beyond the outermost sphere the field of the outermost sphere in the
        vertex's direction is scaled by ``(r_max / r)^2`` (the solid angle of a
        distant source falls off as ``1 / r^2``; its radiance does not change).
    """
    _check_method(method)
    stored = field if isinstance(field, StoredBasisRadiance) else None
    if stored is None:
        field = np.asarray(field, dtype=np.float64)
    shape = stored.shape if stored is not None else field.shape
    if len(shape) != 7 or tuple(shape[:4]) != grid.shape:
        raise ValueError(f"field must be {grid.shape} + (K, N, n*n), got shape {tuple(shape)}")
    n_k, n_b, n2 = shape[4:]
    points = np.asarray(points, dtype=np.float64)
    transfer = np.asarray(transfer, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (V, 3), got shape {points.shape}")
    if transfer.ndim != 3 or transfer.shape[0] != len(points) or transfer.shape[2] != n2:
        raise ValueError(f"transfer must be (V, K', n*n) = ({len(points)}, K', {n2}), got shape {transfer.shape}")
    n_kp = transfer.shape[1]
    if len(points) == 0:
        return np.zeros((0, n_kp, n_k, n_b))
    if method == "reference":
        if not (np.all(np.isfinite(points)) and np.all(np.isfinite(transfer))):
            raise ValueError(_NOT_FINITE)
        local = points
        if source_transform is not None:
            R = np.asarray(source_transform.rotation, dtype=np.float64)
            local = ((points - source_transform.translate) @ R) / float(source_transform.scale)
            transfer = sh.rotate(transfer, R.T, channels=False)  # <S_world, T> = <S_obj, R^T T>
        r = np.linalg.norm(local - grid.center, axis=1)
        scale = (grid.radii[-1] / np.maximum(r, grid.radii[-1])) ** 2  # 1 inside the outermost sphere
        field = stored.dense() if stored is not None else field
        s_at, _ = interpolate_field(grid, field.reshape(grid.shape + (n_k * n_b, n2)), local, method="reference")
        phi = np.einsum("vmi,vki->vkm", s_at, transfer) * scale[:, None, None]
        return phi.reshape(len(points), n_kp, n_k, n_b)
    if source_transform is None:
        translate, rotation, size, turn = np.zeros(3), np.eye(3), 1.0, np.empty((0, 0))
    else:
        translate = np.asarray(source_transform.translate, dtype=np.float64)
        rotation = np.asarray(source_transform.rotation, dtype=np.float64)
        size = float(source_transform.scale)
        turn = sh.rotation_matrix(rotation.T, int(round(np.sqrt(n2))))  # <S_world, T> = <S_obj, R^T T>
    n_s = int(np.prod(grid.shape))
    if stored is not None:
        rows, values, column_scale, scaled = stored.rows.reshape(-1), stored.values, stored.scale, \
            stored.storage == "int16"
    else:
        rows, values = np.arange(n_s, dtype=np.int32), np.ascontiguousarray(field.reshape(n_s, n_k * n_b, n2))
        column_scale, scaled = np.empty((0, n_k * n_b), np.float32), False
    out = np.empty((len(points), n_kp, n_k * n_b))
    if not eq13_kernel(rows, values, column_scale, scaled, points, translate, np.ascontiguousarray(rotation), size,
                       np.asarray(grid.center, np.float64), np.asarray(grid.radii, np.float64), grid.shape[2], turn,
                       np.ascontiguousarray(transfer), values.nbytes > _CELL_ORDER_BYTES, out):
        raise ValueError(_NOT_FINITE)
    return out.reshape(len(points), n_kp, n_k, n_b)


def reflected_light(irradiance, weights, method: str = "numba") -> np.ndarray:
    """Light reflected by the sources into each receiver BRDF term: ``L_k' = sum_s Phi^s w^s`` (Eq. 12).

    Parameters
    ----------
    irradiance : sequence of (V, K', K_s, N_s) float
        Basis irradiance from each source.
    weights : sequence of (K_s, N_s, C) float
        Each source's weights.
    method : {"numba", "reference"}

    Returns
    -------
    light : (V, K', C) float64
    """
    _check_method(method)
    irradiance, weights = list(irradiance), list(weights)
    if len(irradiance) != len(weights):
        raise ValueError(
            f"got {len(irradiance)} irradiance arrays for {len(weights)} weight arrays; give one per source"
        )
    if not irradiance:
        raise ValueError("reflected_light needs at least one source")
    n_v, n_kp = np.shape(irradiance[0])[:2]
    n_c = np.shape(weights[0])[-1]
    flat_phi, flat_w = [], []
    for phi, w in zip(irradiance, weights):
        phi = np.asarray(phi, dtype=np.float64)
        w = np.asarray(w, dtype=np.float64)
        if phi.ndim != 4 or phi.shape[:2] != (n_v, n_kp) or w.shape != phi.shape[2:] + (n_c,):
            raise ValueError(f"irradiance (V, K', K, N) {phi.shape} and weights (K, N, C) {w.shape} do not match")
        flat_phi.append(phi.reshape(n_v, n_kp, -1))
        flat_w.append(w.reshape(-1, n_c))
    all_phi = np.concatenate(flat_phi, axis=2)  # every source's (k, i) side by side: one pass
    all_w = np.concatenate(flat_w, axis=0)
    if method == "reference":
        return np.einsum("vkm,mc->vkc", all_phi, all_w)
    out = np.zeros((n_v, n_kp, n_c))
    if n_v:
        bounce_kernel(all_phi, np.ascontiguousarray(all_w), out)
    return out


def fit_weights(pca_basis, light, colour, method: str = "fast") -> np.ndarray:
    """Weights of a source's outgoing-radiance factors ``colour_k L_k`` in its basis (Eq. 14).

    Parameters
    ----------
    pca_basis : prtlab.pca.PCABasis
    light : (V, K, C) float
        ``L_k,c(x_j)`` at every vertex of the source.
    colour : (K, C) float
        The source's separable-BRDF colours.
    method : {"fast", "reference"}
        Tier of :meth:`prtlab.pca.PCABasis.weights` (precomputed projector or ``A^{-1} b``).

    Returns
    -------
    weights : (K, N, C) float64
    """
    light = np.asarray(light, dtype=np.float64)
    colour = np.asarray(colour, dtype=np.float64)
    if light.ndim != 3 or light.shape[1:] != colour.shape:
        raise ValueError(f"light must be (V, K, C) with (K, C) = {colour.shape}, got shape {light.shape}")
    values = np.moveaxis(light * colour[None], 0, 1)  # (K, V, C)
    return pca_basis.weights(values, colour=True, method=method)


def outgoing_radiance(light, h, colour, method: str = "numba") -> np.ndarray:
    """``B(x_j, w_o) = sum_k h_k(w_o) colour_k L_k(x_j)``: (V, K, C), (V, K), (K, C) -> (V, C); ``method``
    ``"reference"``: numpy's einsum (its sum in another order, to rounding)."""
    _check_method(method)
    light, h, colour = (np.ascontiguousarray(a, dtype=np.float64) for a in (light, h, colour))
    if method == "reference":
        return np.einsum("vk,kc,vkc->vc", h, colour, light)
    if light.ndim != 3 or h.shape != light.shape[:2] or colour.shape != light.shape[1:]:
        raise ValueError(f"light (V, K, C) {light.shape}, h (V, K) {h.shape} and colour (K, C) {colour.shape} "
                         "do not match")
    out = np.empty((light.shape[0], light.shape[2]))
    outgoing_kernel(light, h, colour, out)
    return out

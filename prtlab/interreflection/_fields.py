"""Basis radiance fields ``S_(k,i)`` of a source object on its sample spheres (Iwasaki et al. 2007, Sec. 4.3).

A source object whose outgoing radiance is written with its PCA basis
functions ``Psi_i`` and the view factors ``h_k`` of its separable BRDF
(Eq. 9)::

    B(x, w_o) = sum_k sum_i w_(k,i) h_k(w_o) Psi_i(x)

sends toward a point ``p`` in direction ``-w_in`` the radiance
``sum_(k,i) w_(k,i) S_(k,i)(p, w_in)`` with the *basis radiance*

    S_(k,i)(p, w_in) = h_k(-w_in) Psi_i(x~(p, w_in))

where ``x~`` is the first hit of the ray ``p + t w_in`` on the source (0 if
the ray misses it). ``Psi_i`` at the hit is the barycentric interpolation of
its vertex values; ``h_k`` is evaluated in the local frame of the
interpolated shading normal (:func:`prtlab.brdf.local_frame`). A hit on the
back of the surface (``n . w_in > 0``: the ray meets the side the vertex
normals do not point to) carries 0, following the vertex shading side of
``docs/DECISIONS.md``. ``S_(k,i)(p, .)`` is projected to SH by the product
quadrature of :func:`prtlab.sh.quadrature` at every point of the sample
spheres (:func:`prtlab.shadowfields.sphere_grid`), in object space.

References
----------
K. Iwasaki, Y. Dobashi, F. Yoshimoto, T. Nishita, "Precomputed radiance transfer
for dynamic scenes taking into account light interreflection", EGSR 2007,
Sec. 3.1 (Eq. 2), Sec. 4.3.
"""

from __future__ import annotations

import numpy as np

from prtlab import brdf, sh
from prtlab.geometry import RayCaster
from prtlab.shadowfields import DEFAULT_DEGREE, SphereGrid

__all__ = ["basis_radiance_field", "basis_radiance_at"]

_RAYS_PER_BATCH = 1 << 19


def basis_radiance_at(mesh, basis, sep, points, order: int, degree: int | None = None) -> np.ndarray:
    """SH of the basis radiance ``S_(k,i)(p, .)`` of a source object at points (object space).

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The source object in object space (its ``vertex_normals`` give the shading side).
    basis : (N, n_vertices) float
        Basis functions ``Psi_i`` at the vertices (e.g. ``PCABasis.basis``).
    sep : prtlab.brdf.SeparableBRDF
        The source's separable BRDF (K terms, ``"plain"``).
    points : (..., 3) float
    order : int
    degree : int, optional
        Quadrature degree (default :data:`prtlab.shadowfields.DEFAULT_DEGREE`).

    Returns
    -------
    S : (..., K, N, n*n) float64
    """
    basis = np.asarray(basis, dtype=np.float64)
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if basis.ndim != 2 or basis.shape[1] != len(vertices):
        raise ValueError(f"basis must be (N, n_vertices) = (N, {len(vertices)}), got shape {basis.shape}")
    if isinstance(order, bool) or not isinstance(order, (int, np.integer)) or order < 1:
        raise ValueError(f"order must be an int >= 1, got {order!r}")
    degree = max(DEFAULT_DEGREE, 2 * order - 2) if degree is None else int(degree)
    points = np.asarray(points, dtype=np.float64)
    if points.ndim == 0 or points.shape[-1] != 3:
        raise ValueError(f"points must be a (..., 3) array, got shape {points.shape}")
    batch = points.shape[:-1]
    flat = points.reshape(-1, 3)
    normals = np.asarray(mesh.vertex_normals, dtype=np.float64)
    caster = RayCaster([(vertices, faces)])
    dirs, weights = sh.quadrature(order, degree)
    y = sh.basis(dirs, order)  # (D, n2)
    n_b, n_k, n2 = basis.shape[0], sep.K, order * order
    wy = weights[:, None] * y  # (D, n2)
    out = np.zeros((len(flat), n_k * n_b, n2))
    step = max(1, _RAYS_PER_BATCH // (len(dirs) * max(1, n_k * n_b // 4)))
    for a in range(0, len(flat), step):
        b = min(len(flat), a + step)
        hits = caster.closest_hit(flat[a:b, None, :], dirs[None])
        sel = np.nonzero(hits.hit)
        if not len(sel[0]):
            continue
        tri = faces[hits.triangle[sel]]  # (H, 3)
        uv = hits.barycentric[sel]
        bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)  # (H, 3)
        shading_n = np.einsum("hc,hcx->hx", bary, normals[tri])
        shading_n /= np.maximum(np.linalg.norm(shading_n, axis=1, keepdims=True), 1e-300)
        w_in = dirs[sel[1]]
        front = np.sum(shading_n * w_in, axis=1) < 0.0
        psi = np.zeros((b - a, len(dirs), n_b))
        psi[sel] = np.einsum("hc,nhc->hn", bary, basis[:, tri]) * front[:, None]
        h = np.zeros((b - a, len(dirs), n_k))
        h[sel] = brdf.project_h(sep, -w_in, shading_n)
        value = (h[:, :, :, None] * psi[:, :, None, :]).reshape(b - a, len(dirs), n_k * n_b)
        out[a:b] = np.matmul(value.transpose(0, 2, 1), wy)
    return out.reshape(batch + (n_k, n_b, n2))


def basis_radiance_field(mesh, basis, sep, grid: SphereGrid, order: int, degree: int | None = None) -> np.ndarray:
    """The basis radiance field of a source object on its sample spheres (Sec. 4.3).

    Returns
    -------
    S : (n_r, 6, res, res, K, N, n*n) float64
        :func:`basis_radiance_at` at ``grid.points()``.
    """
    return basis_radiance_at(mesh, basis, sep, grid.points(), order, degree)

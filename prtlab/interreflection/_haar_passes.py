"""All-frequency basis irradiance (Iwasaki et al. 2007, Eq. 13 with Haar cubemaps).

For a receiver vertex ``x`` with normal ``n``, receiver BRDF terms ``g_k'`` and a
source with basis radiance ``S_m`` (``m = (k, i)``, :mod:`._haar_fields`)::

    Phi_(k',m)(x) = int S_m(x, w) V(x, w) g_k'(w) max(0, n . w) dw

Eq. 13 writes it as the product of the coefficient vectors of ``S``, ``V`` and
``g cos``. Here all three live on one cubemap of ``r x r`` texels per face:

1. **transfer** (:func:`haar_transfer`, world frame): ``W_k'(t) = V(t) G_k'(t)`` per texel,
   ``V`` the texel-wise product of the receiver's Haar self-visibility and the
   occluders' Haar occlusion fields (the machinery of
   :func:`prtlab.shadowfields.haar_visibility_pass`: exact in the pulse basis, no
   re-truncation), ``G_k'(t) = g_k'(m_t / |m_t|) max(0, n . m_t)`` with the exact texel
   moment ``m_t = int_t w dw`` (:func:`prtlab.shadowfields.texel_moments`: exact for a
   Lambertian term on texels above the horizon; a midpoint rule in ``g`` for glossy terms);
2. **basis irradiance** (:func:`haar_basis_irradiance`): ``W`` is turned into the source's
   object frame (``W_obj(t) = W(texel containing R d_t)``,
   :func:`prtlab.shadowfields.rotation_texel_map` of ``R^T``), Haar-transformed once per
   ``k'`` (orthonormal on texels), and ``Phi_(k',m) = sum_c S^_m[c] W^_k'[c]`` — the
   double product of the sparse ``S`` coefficients (trilinear blend of the 8 nearest
   sample points, as the SH path, :func:`basis_irradiance`) with the dense transformed
   transfer. By Parseval this is ``sum_t S_m(t) V(t) G_k'(t)``: the texel-wise triple
   product, at ``O(6 r^2 log r)`` per vertex and ``k'`` plus ``8 keep`` per ``m``.

Beyond the outermost sphere the outermost samples are used, scaled by ``(r_max / r)^2``
(as the SH path).

Error (what the cubemap and the truncation cost): against the exact integral,
``S V`` is point-sampled at texel centres and ``g cos`` integrated exactly over the
texel, so the error is the midpoint rule's: on texels where ``S V`` is smooth second
order in the texel size; on *edge* texels (a silhouette of the source or an occluder
crosses them: hit/miss or blocked/visible differs from a 4-neighbour) at most
``max |S V|`` over the texel times ``|G_t|`` (:func:`haar_irradiance_bound` bounds these
by the largest sampled ``|S V|`` among the texel and its neighbours, which is exact when
``S`` is bounded by its samples near the edge); on horizon texels ``n . m_t`` is the signed
cosine integral (error at most ``int_t |min(0, n . w)| dw``). The Haar truncation of
``S`` adds at most ``sqrt(energy_lost) ||W||`` (Cauchy-Schwarz, texel space).

Interpolation between sample points blends 8 sharp cubemaps (a soft, doubled
silhouette); near a large source the sampling of the spheres dominates, and the
pipeline's near field casts ``S`` at the receiver instead (:func:`near_basis_irradiance`, the sum of
:func:`texel_basis_irradiance` over :func:`haar_basis_radiance_cubemaps` gathered hit by hit).

Kernels live in this module (``@numba.njit(cache=True)``); the ``"reference"`` tiers
are the float64 numpy specifications.

Measured figures (how they were found): ``docs/notes/interreflection.md``.

References
----------
K. Iwasaki et al., EGSR 2007, Sec. 5.1-5.2, Eq. (13).
R. Ng, R. Ramamoorthi, P. Hanrahan, "Triple product wavelet integrals for all-frequency
relighting", SIGGRAPH 2004.
"""

from __future__ import annotations

import numba
import numpy as np

from prtlab._validate import as_points, check_choice
from prtlab import brdf
from prtlab.shadowfields import (
    SparseCubemaps,
    haar_visibility_pass,
    rotation_texel_map,
    texel_moments,
)
from prtlab.shadowfields._haar_direct import check_receivers, visibility_factors
from prtlab.shadowfields._haar_kernels import blends_nothing

from ._haar_fields import HaarBasisRadianceField, _check_resolution

__all__ = ["haar_transfer", "haar_basis_irradiance", "texel_basis_irradiance", "near_basis_irradiance",
           "haar_irradiance_bound"]

_METHODS = ("numba", "reference")
#: Transfer texels (vertex x k' x texel) per chunk of vertices.
_TEXELS_PER_CHUNK = 1 << 21


# --------------------------------------------------------------------------- kernels


@numba.njit(cache=True)
def _haar_analysis(tex, res, out, work):
    """Forward orthonormal Haar transform of one flat cubemap ``tex`` (6 r^2) into ``out`` (``haar2d`` layout).

    Per level a 2x2 block ``a, b / c, d`` gives ``(a + b + c + d) / 2`` (scaling, next level),
    ``(a - b + c - d) / 2`` at ``[p, h + q]``, ``(a + b - c - d) / 2`` at ``[h + p, q]`` and
    ``(a - b - c + d) / 2`` at ``[h + p, h + q]``. ``work`` is scratch of ``r^2``.
    """
    rr = res * res
    for f in range(6):
        base = f * rr
        for a in range(rr):
            work[a] = tex[base + a]
        h = res // 2
        while h >= 1:
            for p in range(h):
                for q in range(h):
                    a = work[2 * p * res + 2 * q]
                    b = work[2 * p * res + 2 * q + 1]
                    c = work[(2 * p + 1) * res + 2 * q]
                    d = work[(2 * p + 1) * res + 2 * q + 1]
                    out[base + p * res + h + q] = 0.5 * (a - b + c - d)
                    out[base + (h + p) * res + q] = 0.5 * (a + b - c - d)
                    out[base + (h + p) * res + h + q] = 0.5 * (a - b - c + d)
                    work[p * res + q] = 0.5 * (a + b + c + d)  # p, q <= 2p, 2q: read before written
            h //= 2
        out[base] = work[0]


@numba.njit(cache=True, inline="always")
def _sparse_dot(tab_idx, tab_val, p, m, coef):
    """``sum_k tab_val[p, m, k] coef[tab_idx[p, m, k]]`` over the stored entries (they end at the first zero)."""
    acc = 0.0
    for k in range(tab_idx.shape[2]):
        val = tab_val[p, m, k]
        if val == 0.0:
            break
        acc += np.float64(val) * coef[np.int64(tab_idx[p, m, k])]
    return acc


@numba.njit(cache=True, parallel=True)
def haar_basis_irradiance_kernel(tab_idx, tab_val, corners, weights, transfer, texel_map, res, out):
    """Eq. 13 per receiver vertex: transform its transfer once per ``k'``, dot with the blended sparse ``S``.

    tab_idx, tab_val : (P, M, keep) uint16/int32, float32 -- sparse Haar ``S_m`` of the P sample points,
        largest first (a cubemap's loop stops at its first zero)
    corners, weights : (V, 8) int64, float64 -- samples blended at each vertex (weights include the
        ``(r_max / r)^2`` factor)
    transfer : (V, K', 6 r^2) float64 -- ``V G_k'`` per world texel
    texel_map : (6 r^2,) int64 -- source-frame texel -> world texel
    out : (V, K', M)
    """
    n_v, n_kp, n = transfer.shape  # n = 6 r^2 texels
    n_m = tab_idx.shape[1]
    for v in numba.prange(n_v):
        tex = np.empty(n)
        coef = np.empty(n)
        work = np.empty(res * res)
        for kp in range(n_kp):
            for m in range(n_m):
                out[v, kp, m] = 0.0
        if blends_nothing(weights, v):
            continue
        for kp in range(n_kp):
            for t in range(n):
                tex[t] = transfer[v, kp, texel_map[t]]
            _haar_analysis(tex, res, coef, work)
            for c in range(8):
                w = weights[v, c]
                if w == 0.0:
                    continue
                for m in range(n_m):
                    out[v, kp, m] += w * _sparse_dot(tab_idx, tab_val, corners[v, c], m, coef)


@numba.njit(cache=True, parallel=True)
def near_gather_kernel(rows, starts, hit_texel, w_obj, h, psi, out):
    """``out[rows[u], q, k, i] += sum_hits w_obj[rows[u], q, t] h[hit, k] psi[hit, i]`` over the hits of each
    receiver ``rows[u]`` (``starts[u]:starts[u + 1]``, hits sorted by receiver; ``hit_texel`` their texels)."""
    n_kp = w_obj.shape[1]
    n_k = h.shape[1]
    n_b = psi.shape[1]
    for u in numba.prange(rows.shape[0]):
        v = rows[u]
        for e in range(starts[u], starts[u + 1]):
            t = hit_texel[e]
            for q in range(n_kp):
                w = w_obj[v, q, t]
                if w == 0.0:
                    continue
                for k in range(n_k):
                    wh = w * h[e, k]
                    for i in range(n_b):
                        out[v, q, k, i] += wh * psi[e, i]


# --------------------------------------------------------------------------- transfer


def _corners(grid, local):
    """The 8 samples of the trilinear blend (as :func:`prtlab.shadowfields.interpolate_field`) and weights
    times ``(r_max / r)^2`` beyond the outermost sphere: (Q, 8) int64, (Q, 8) float64."""
    corners, weights, _ = grid.trilinear_corners(local)
    r = np.linalg.norm(local - grid.center, axis=1)
    scale = np.where(r > grid.radii[-1], (grid.radii[-1] / np.maximum(r, 1e-300)) ** 2, 1.0)
    return corners, weights * scale[:, None]


def _texel_g_cos(sep, normals, res) -> np.ndarray:
    """``G_k'(t) = g_k'(m_t / |m_t|) max(0, n . m_t)`` (V, K', 6 r^2) per world texel."""
    moments = texel_moments(res)  # (n, 3)
    cos = np.maximum(normals @ moments.T, 0.0)  # (V, n): int_t cos (above the horizon)
    g_radial = np.asarray(sep.g_radial)
    if sep.K == 1 and int(sep.freq[0]) == 0 and np.ptp(g_radial) <= 1e-12 * np.abs(g_radial).max():
        return (float(np.mean(g_radial)) * cos)[:, None, :]
    unit = moments / np.linalg.norm(moments, axis=1, keepdims=True)
    R = brdf.local_frame(normals)  # world = R local
    local = np.einsum("vji,tj->vti", R, unit)
    return np.moveaxis(sep.g(local), 2, 1) * cos[:, None, :]


def haar_transfer(points, normals, sep, resolution: int = 32, *, self_visibility: SparseCubemaps | None = None,
                  self_transform=None, occluders=(), method: str = "numba") -> np.ndarray:
    """Per-texel transfer ``W_k'(t) = V(x, t) int_t g_k'(w) max(0, n . w) dw`` of receiver vertices (world frame).

    Parameters
    ----------
    points, normals : (V, 3) float
        World positions and unit normals of the receiver vertices.
    sep : prtlab.brdf.SeparableBRDF
        The receiver's separable BRDF (``g_k'``, :func:`prtlab.brdf.local_frame` frame).
    resolution : int
        Cubemap texels per face edge (that of the visibility data).
    self_visibility : SparseCubemaps (V,), optional
        :func:`prtlab.shadowfields.haar_self_visibility` of the receiver (object frame).
    self_transform : prtlab.scene.Transform, optional
        The receiver's pose (turns the self-visibility).
    occluders : sequence of (HaarOcclusionField, Transform or None)
        The objects between receiver and source, with their poses (any order: the product is exact).
    method : {"numba", "reference"}
        Tier of :func:`prtlab.shadowfields.haar_visibility_pass`.

    Returns
    -------
    transfer : (V, K', 6, r, r) float64
    """
    method = check_choice(method, "method", _METHODS)
    points, normals = check_receivers(sep, points, normals)
    res = _check_resolution(resolution)
    n = 6 * res * res
    nv = len(points)
    out = np.empty((nv, sep.K, n))
    factors = visibility_factors(points, self_visibility, self_transform, list(occluders), "trilinear", res)
    step = max(1, _TEXELS_PER_CHUNK // (n * max(sep.K, 1)))
    for a in range(0, nv, step):
        b = min(nv, a + step)
        g = _texel_g_cos(sep, normals[a:b], res)
        if factors:
            chunk = [(t, c[a:b], w[a:b], m) for t, c, w, m in factors]
            query = np.ascontiguousarray(np.broadcast_to(np.arange(n), (b - a, n)))
            g = g * haar_visibility_pass(query, chunk, res, method=method)[:, None, :]
        out[a:b] = g
    return out.reshape(nv, sep.K, 6, res, res)


# --------------------------------------------------------------------------- basis irradiance


def _check_transfer(transfer, nv, res) -> np.ndarray:
    transfer = np.asarray(transfer, dtype=np.float64)
    if transfer.ndim != 5 or transfer.shape[0] != nv or transfer.shape[2:] != (6, res, res):
        raise ValueError(f"transfer must be (V, K', 6, r, r) = ({nv}, K', 6, {res}, {res}) (haar_transfer), "
                         f"got shape {transfer.shape}")
    if not np.all(np.isfinite(transfer)):
        raise ValueError("transfer contains NaN or inf")
    return transfer


def haar_basis_irradiance(field: HaarBasisRadianceField, points, transfer, source_transform=None,
                          method: str = "numba") -> np.ndarray:
    """All-frequency basis irradiance ``Phi_(k',k,i)`` of one source at receiver vertices (Eq. 13).

    Parameters
    ----------
    field : HaarBasisRadianceField
        The source's sparse Haar basis radiance field (object space).
    points : (V, 3) float
        Receiver vertices, world space.
    transfer : (V, K', 6, r, r) float
        :func:`haar_transfer` of the receivers toward this source (world frame).
    source_transform : prtlab.scene.Transform, optional
        The source's pose (default identity).
    method : {"numba", "reference"}
        Parallel kernel, or dense numpy synthesis of the blended ``S`` and
        :func:`prtlab.wavelet.haar2d` of the transfer (float64 specification).

    Returns
    -------
    phi : (V, K', K, N) float64
        ``sum_t S_(k,i)(x, t) W_k'(t)``, ``S`` blended trilinearly between the sample points
        (scaled by ``(r_max / r)^2`` beyond the outermost sphere).

    Notes
    -----
    A turned source reads the world transfer at the texel containing ``R d_t`` for each of its
    texels ``t`` (nearest texel; exact for the 24 rotations that permute the texels).
    """
    method = check_choice(method, "method", _METHODS)
    if not isinstance(field, HaarBasisRadianceField):
        raise TypeError(f"field must be a HaarBasisRadianceField (haar_basis_radiance_field), got "
                        f"{type(field).__name__}")
    res = field.resolution
    points = as_points(points, "points", flat=True)
    nv = len(points)
    transfer = _check_transfer(transfer, nv, res)
    n_k, n_b = field.n_terms
    n_kp = transfer.shape[1]
    if nv == 0:
        return np.zeros((0, n_kp, n_k, n_b))
    local = points
    R = np.eye(3)
    if source_transform is not None:
        R = np.asarray(source_transform.rotation, dtype=np.float64)
        local = ((points - source_transform.translate) @ R) / float(source_transform.scale)
    corners, weights = _corners(field.grid, local)
    texel_map = rotation_texel_map(R.T, res)  # source texel t -> world texel containing R d_t
    n = 6 * res * res
    keep = field.keep
    idx = field.indices.reshape(-1, n_k * n_b, keep)
    val = field.values.reshape(-1, n_k * n_b, keep)
    flat = transfer.reshape(nv, n_kp, n)
    if method == "reference":
        from prtlab.wavelet import haar2d

        coeffs = np.zeros((nv, n_k * n_b, n))
        rows = np.arange(nv)[:, None, None]
        terms = np.arange(n_k * n_b)[None, :, None]
        for c in range(8):
            p = corners[:, c]
            np.add.at(coeffs, (rows, terms, idx[p].astype(np.int64)),
                      weights[:, c, None, None] * val[p].astype(np.float64))
        w_hat = haar2d(flat[:, :, texel_map].reshape(nv, n_kp, 6, res, res), method="reference").reshape(nv, n_kp, n)
        return np.einsum("vmt,vkt->vkm", coeffs, w_hat).reshape(nv, n_kp, n_k, n_b)
    out = np.empty((nv, n_kp, n_k * n_b))
    haar_basis_irradiance_kernel(np.ascontiguousarray(idx), np.ascontiguousarray(val), corners,
                                 np.ascontiguousarray(weights), np.ascontiguousarray(flat), texel_map, res, out)
    return out.reshape(nv, n_kp, n_k, n_b)


def texel_basis_irradiance(radiance_cubemaps, transfer, source_transform=None) -> np.ndarray:
    """``Phi_(k',k,i) = sum_t S_(k,i)(t) W_k'(t)`` from dense basis radiance cubemaps (the near field).

    Parameters
    ----------
    radiance_cubemaps : (V, K, N, 6, r, r) float
        :func:`haar_basis_radiance_cubemaps` at the receivers (source object frame).
    transfer : (V, K', 6, r, r) float
        :func:`haar_transfer` (world frame).
    source_transform : prtlab.scene.Transform, optional

    Returns
    -------
    phi : (V, K', K, N) float64
    """
    s = np.asarray(radiance_cubemaps, dtype=np.float64)
    if s.ndim != 6 or s.shape[3] != 6 or s.shape[4] != s.shape[5]:
        raise ValueError(f"radiance_cubemaps must be (V, K, N, 6, r, r), got shape {s.shape}")
    nv, res = s.shape[0], s.shape[-1]
    transfer = _check_transfer(transfer, nv, res)
    R = np.eye(3) if source_transform is None else np.asarray(source_transform.rotation, dtype=np.float64)
    n = 6 * res * res
    w_obj = transfer.reshape(nv, -1, n)[:, :, rotation_texel_map(R.T, res)]
    return np.einsum("vknt,vqt->vqkn", s.reshape(nv, s.shape[1], s.shape[2], n), w_obj)


def near_basis_irradiance(mesh, basis, sep, points, transfer, source_transform=None, caster=None,
                          method: str = "numba") -> np.ndarray:
    """``Phi_(k',k,i) = sum_t S_(k,i)(x, t) W_k'(t)`` with ``S`` cast at the receivers themselves (the near field).

    (Long for its documentation; the code is 63 lines: select the live texels, cast, gather.)

    The same sum as :func:`texel_basis_irradiance` of :func:`haar_basis_radiance_cubemaps` (the same
    texel-centre rays), gathered hit by hit without the dense cubemaps, and casting only the texels
    where the transfer is non-zero (above the receiver's horizon, not blocked) and whose centre
    direction lies in the cone of the source's bounding sphere.

    Parameters
    ----------
    mesh, basis, sep : trimesh.Trimesh, (N, n_vertices) float, prtlab.brdf.SeparableBRDF
        The source in object space, its radiance basis and its separable BRDF (``h_k``).
    points : (V, 3) float
        Receiver points in the source's object space.
    transfer : (V, K', 6, r, r) float
        :func:`haar_transfer` of the receivers (world frame).
    source_transform : prtlab.scene.Transform, optional
        The source's pose (its rotation turns the transfer into the object frame).
    caster : prtlab.geometry.RayCaster, optional
        A caster of ``mesh`` to reuse (default: built here).
    method : {"numba", "reference"}
        The gather of the hits: a parallel kernel over receivers, or numpy ``einsum`` and ``reduceat``.

    Returns
    -------
    phi : (V, K', K, N) float64
    """
    from prtlab.geometry import RayCaster, cubemap_directions
    from prtlab.shadowfields import bounding_sphere

    method = check_choice(method, "method", _METHODS)
    basis = np.asarray(basis, dtype=np.float64)
    points = as_points(points, "points", flat=True)
    nv = len(points)
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    if basis.ndim != 2 or basis.shape[1] != len(vertices):
        raise ValueError(f"basis must be (N, n_vertices) = (N, {len(vertices)}), got shape {basis.shape}")
    transfer = np.asarray(transfer, dtype=np.float64)
    res = transfer.shape[-1] if transfer.ndim == 5 else 0
    transfer = _check_transfer(transfer, nv, res)
    n_kp, n_k, n_b = transfer.shape[1], sep.K, basis.shape[0]
    out = np.zeros((nv, n_kp, n_k, n_b))
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if nv == 0 or len(faces) == 0:
        return out
    R = np.eye(3) if source_transform is None else np.asarray(source_transform.rotation, dtype=np.float64)
    n = 6 * res * res
    w_obj = np.ascontiguousarray(transfer.reshape(nv, n_kp, n)[:, :, rotation_texel_map(R.T, res)])  # source frame
    dirs = cubemap_directions(res).reshape(-1, 3)
    normals = np.asarray(mesh.vertex_normals, dtype=np.float64)
    caster = RayCaster([(vertices, faces)]) if caster is None else caster
    # a texel can see the source only inside the cone of its bounding sphere (outside it: no hit, skip the ray)
    center, radius = bounding_sphere(vertices)
    to_c = center - points
    dist = np.linalg.norm(to_c, axis=1)
    cos_cone = np.where(dist > radius, np.sqrt(np.maximum(1.0 - (radius / np.maximum(dist, 1e-300)) ** 2, 0.0)),
                        -2.0)
    inside = (dirs @ to_c.T).T >= (cos_cone * dist)[:, None] - 1e-9 * np.maximum(dist, 1.0)[:, None]  # (V, n)
    rv, rt = np.nonzero(np.any(w_obj != 0.0, axis=1) & inside)  # row-major: sorted by receiver
    h_radial = np.asarray(sep.h_radial)
    h_const = None  # a Lambertian source: h = const on its front side (psi is 0 on the back)
    if sep.K == 1 and int(sep.freq[0]) == 0 and np.ptp(h_radial) <= 1e-12 * np.abs(h_radial).max():
        h_const = float(np.mean(h_radial))
    step = 1 << 18
    for a in range(0, len(rv), step):
        v, t = rv[a:a + step], rt[a:a + step]
        hits = caster.closest_hit(points[v], dirs[t])
        sel = np.flatnonzero(hits.hit)
        if not len(sel):
            continue
        tri = faces[hits.triangle[sel]]
        uv = hits.barycentric[sel]
        bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
        shading_n = np.einsum("hc,hcx->hx", bary, normals[tri])
        shading_n /= np.maximum(np.linalg.norm(shading_n, axis=1, keepdims=True), 1e-300)
        w_in = dirs[t[sel]]
        front = np.sum(shading_n * w_in, axis=1) < 0.0
        psi = np.einsum("hc,nhc->hn", bary, basis[:, tri]) * front[:, None]  # (H, N)
        h = np.full((len(sel), 1), h_const) if h_const is not None else brdf.project_h(sep, -w_in, shading_n)
        rows, starts = np.unique(v[sel], return_index=True)  # hits sorted by receiver
        if method == "numba":
            near_gather_kernel(rows, np.append(starts, len(sel)), np.ascontiguousarray(t[sel]), w_obj,
                               np.ascontiguousarray(h), np.ascontiguousarray(psi), out)
            continue
        w = w_obj[v[sel], :, t[sel]]  # (H, K')
        contrib = np.einsum("hq,hk,hn->hqkn", w, h, psi).reshape(len(sel), -1)
        out[rows] += np.add.reduceat(contrib, starts, axis=0).reshape(len(rows), n_kp, n_k, n_b)
    return out


def haar_irradiance_bound(radiance_cubemaps, transfer, g_abs=None) -> np.ndarray:
    """The resolution bound of the texel-wise Eq. 13: ``sum over edge texels of max|S V| |G_t|``.

    Parameters
    ----------
    radiance_cubemaps : (V, K, N, 6, r, r) float
        Sampled ``S_(k,i)`` at the receivers (source frame = world frame here).
    transfer : (V, K', 6, r, r) float
        ``V G`` per texel (:func:`haar_transfer`).
    g_abs : (V, K', 6, r, r) float, optional
        ``|G_k'(t)|`` per texel (visibility 1); default ``|transfer|`` (then blocked texels count 0).

    Returns
    -------
    bound : (V, K', K, N) float64
        An edge texel is one where ``S`` or ``V`` (transfer > 0) differs between it and a
        4-neighbour on its face in being zero; it contributes the largest ``|S|`` of itself and its
        neighbours times its ``|G|``.
    """
    s = np.abs(np.asarray(radiance_cubemaps, dtype=np.float64))
    w = np.asarray(transfer, dtype=np.float64)
    g = np.abs(w) if g_abs is None else np.abs(np.asarray(g_abs, dtype=np.float64))
    nv, n_k, n_b, _, res, _ = s.shape
    n_kp = w.shape[1]

    def edges(on):  # (..., 6, r, r) bool: differs from a 4-neighbour
        e = np.zeros(on.shape, bool)
        di = on[..., 1:, :] != on[..., :-1, :]
        dj = on[..., :, 1:] != on[..., :, :-1]
        e[..., 1:, :] |= di
        e[..., :-1, :] |= di
        e[..., :, 1:] |= dj
        e[..., :, :-1] |= dj
        return e

    def neighbourhood_max(x):
        m = x.copy()
        m[..., 1:, :] = np.maximum(m[..., 1:, :], x[..., :-1, :])
        m[..., :-1, :] = np.maximum(m[..., :-1, :], x[..., 1:, :])
        m[..., :, 1:] = np.maximum(m[..., :, 1:], x[..., :, :-1])
        m[..., :, :-1] = np.maximum(m[..., :, :-1], x[..., :, 1:])
        return m

    s_edge = edges(s > 0)  # (V, K, N, 6, r, r)
    v_edge = edges(w > 0)  # (V, K', 6, r, r)
    s_max = neighbourhood_max(s)
    out = np.zeros((nv, n_kp, n_k, n_b))
    for q in range(n_kp):
        edge = s_edge | v_edge[:, q, None, None]
        out[:, q] = np.einsum("vknfij,vfij->vkn", np.where(edge, s_max, 0.0), g[:, q])
    return out

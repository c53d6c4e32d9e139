"""Sun-accurate indirect light: bounces driven by the per-frame direct radiance of the interior (issue 17).

The paper (Yue et al. 2009, Section 4.1.1) projects the shell light on a few SH bands and precomputes the
indirect response to each band. A sun through a window is far sharper than order-4 SH: the projection spreads its
light over directions it never comes from, and that light bounces (on the sunlit room the floor's indirect light
was 25% too bright). Here instead the first bounce starts from where the light really lands: the direct radiance
``L_d(u)`` that the direct pass computes exactly per vertex each frame (8-bit cubemaps at ``cube_resolution``).

Precomputed, independent of the light (``indirect="surface"``):

- ``F (V, C)``: the final gather of each vertex ``v`` over the *source patches* ``c``: ``F_vc = 1/M sum_rays
  sum_corners w_corner [patch(corner) = c]`` for ``M`` stratified cosine-weighted rays; a ray reaching the front of
  a triangle reads the patch of each of its corners by its barycentric weight. Patches are the vertices themselves
  when the interior has at most ``clusters`` vertices (the gather is then exact up to its noise); otherwise
  k-means clusters of the vertices (position and normal), the light of a cluster being its area-weighted mean.
- ``H (C, C, 3) = Pbar diag(rho) F``: one bounce between patches (``Pbar`` the area-weighted mean over a patch).
- ``S_B = sum_{b=0}^{B-1} H^b`` (binary doubling: ``2 log2 B`` products).

Per frame: ``s = Pbar L_d`` (the patches' mean direct radiance of the hat-averaged source transfer), ``L_ind = rho
* F (S_B s)``: light that bounced ``1..B`` times, ``V C + C^2`` multiply-adds per colour channel. ``s`` is read
straight from the shell light through ``G = Pbar diag(rho) T_src`` (:class:`SourceOperator`, built once when
shading starts: ``C`` rows instead of the source pass over ``V`` vertices); :meth:`SurfaceTransfer.frame` keeps a
float64 reference tier.

Limits: diffuse interiors only (a glossy vertex's radiance depends on the direction; use ``indirect="paper"``).
Errors: the gather noise (``M`` rays, stratified); the linear interpolation of ``L_d`` between vertices across
the sun patch's edge; with clusters, the sun's patch averaged over a cluster for the first bounce.
"""

from __future__ import annotations

import itertools
import threading
import weakref
from concurrent.futures import wait as futures_wait

import numba
import numpy as np

from prtlab import _tasks
from prtlab.geometry import RayCaster, stratified_hemisphere
from prtlab.wavelet import SparseTransfer, haar2d

from . import _kernels
from ._indirect import front_hit_corners

__all__ = ["vertex_areas", "cluster_vertices", "patch_gather", "patch_operator", "power_sum", "SurfaceTransfer",
           "SourceOperator", "limited_projection", "shade_surface"]


def vertex_areas(caster: RayCaster) -> np.ndarray:
    """Area per vertex of every caster object, concatenated (a third of each adjacent triangle), ``(N,)``."""
    out = []
    for i in range(caster.n_objects):
        v, f = caster.world_vertices(i), caster.faces(i)
        a = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
        out.append(np.bincount(f.ravel(), weights=np.repeat(a / 3.0, 3), minlength=len(v)))
    return np.concatenate(out) if out else np.zeros(0)


def cluster_vertices(points, normals, objects, n_clusters: int, seed: int = 0) -> np.ndarray:
    """Patch of each vertex, ``(V,) int64`` in ``0 .. C-1``: the identity when ``V <= n_clusters``, else k-means
    (10 iterations, k-means++ start) on position and normal (the normal scaled by the interior's diagonal, so a
    patch does not fold round a corner) and object (one cluster never spans two objects' vertices when they are
    far apart in that feature); empty clusters are dropped and the labels renumbered."""
    from scipy.cluster.vq import kmeans2

    points = np.asarray(points, dtype=np.float64)
    n = len(points)
    if n <= n_clusters:
        return np.arange(n, dtype=np.int64)
    diag = float(np.linalg.norm(points.max(0) - points.min(0))) or 1.0
    feats = np.column_stack([points, 0.5 * diag * np.asarray(normals, dtype=np.float64),
                             2.0 * diag * np.asarray(objects, dtype=np.float64)[:, None]])
    _, labels = kmeans2(feats, _kmeans_pp(feats, int(n_clusters), int(seed)), iter=10, minit="matrix")
    _, labels = np.unique(labels, return_inverse=True)
    return labels.astype(np.int64)


def _kmeans_pp(data, k: int, seed: int) -> np.ndarray:
    """k-means++ seeding, ``(k, D)``: the centres of scipy's ``kmeans2(minit="++", seed=seed)`` (its stream and
    steps), with each point's distance to its nearest centre kept from one pick to the next (``O(N k)`` distances;
    scipy recomputes them to every centre at each pick, ``O(N k^2)``: 70 s of the 44k-vertex box's 1,024 clusters)."""
    from scipy.spatial.distance import cdist

    rs = np.random.RandomState(seed)
    init = np.empty((k, data.shape[1]))
    nearest = None
    for i in range(k):
        if i == 0:
            pick = rs.randint(0, len(data))
        else:
            new = cdist(init[i - 1 : i], data, metric="sqeuclidean")[0]
            nearest = new if nearest is None else np.minimum(nearest, new)
            pick = int(np.searchsorted((nearest / nearest.sum()).cumsum(), rs.uniform()))
        init[i] = data[pick]
    return init


#: a corner of a near hit's triangle within this fraction of the triangle's longest edge from the gatherer's
#: tangent plane lies on the edge the two surfaces share (shading points sit a few mm inside their faces)
_EDGE_TOLERANCE = 0.05


def patch_gather(caster: RayCaster, points, normals, vertex_offset, vertex_normals, patch, n_patches: int,
                 n_rays: int, rng: np.random.Generator, chunk: int = 256, near: float = 0.0):
    """``F (V, C)`` float32: the final gather of each point over the source patches (module docstring).

    ``vertex_offset`` (``n_objects + 1``) and ``vertex_normals (N, 3)`` as in :func:`final_gather`; ``patch (N,)``
    the patch of every caster vertex. Rays are jittered-stratified cosine-weighted (pdf ``cos / pi``), so a row
    sums to the part of the hemisphere (cosine-weighted) that sees the front of the interior.

    With ``near > 0`` returns ``(F, near_patch, near_point)``: of the rays that land closer than ``near`` times
    their triangle's longest edge on a triangle with a corner on the gatherer's tangent plane (a concave edge),
    ``near_patch (V, C)`` is their part of ``F`` and ``near_point (V, N)`` the weights of their point reads
    (:func:`_near_point_weights`), both ``scipy.sparse.csr_matrix`` float64 per ray count as ``F``.
    """
    from scipy.sparse import coo_matrix

    points = np.asarray(points, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    patch = np.asarray(patch, dtype=np.int64)
    out = np.zeros((len(points), int(n_patches)), dtype=np.float32)
    faces_all = [caster.faces(i) for i in range(caster.n_objects)]
    if near > 0:
        verts = np.concatenate([caster.world_vertices(i) for i in range(caster.n_objects)])
        longest = [_longest_edges(caster.world_vertices(i), f) for i, f in enumerate(faces_all)]
        near_rows, near_patch, near_weight, point_rows, point_vid, point_weight = [], [], [], [], [], []
    chunk = max(1, min(chunk, (1 << 22) // max(n_rays, 1)))
    for start in range(0, len(points), chunk):
        x, nv = points[start : start + chunk], normals[start : start + chunk]
        nc = len(x)
        dirs, _ = stratified_hemisphere(n_rays, rng, nv, cosine=True)
        org = np.broadcast_to(x[:, None, :], dirs.shape).reshape(-1, 3)
        hits = caster.closest_hit(org, dirs.reshape(-1, 3), normals=np.broadcast_to(nv[:, None, :],
                                                                                     dirs.shape).reshape(-1, 3))
        sel, vid, bw = front_hit_corners(hits, dirs.reshape(-1, 3), faces_all, vertex_offset, vertex_normals)
        flat = (sel // n_rays)[:, None] * n_patches + patch[vid]
        out[start : start + nc] = (np.bincount(flat.ravel(), weights=bw.ravel(), minlength=nc * n_patches)
                                   .reshape(nc, n_patches) / n_rays)
        if near > 0:
            edge = np.empty(len(sel))
            for i in np.unique(hits.object[sel]):
                m = hits.object[sel] == i
                edge[m] = longest[i][hits.triangle[sel][m]]
            m = np.nonzero(hits.distance[sel] < near * edge)[0]
            rows = start + sel[m] // n_rays
            weights = _near_point_weights(bw[m], verts[vid[m]], points[rows], normals[rows], _EDGE_TOLERANCE * edge[m])
            m, rows, weights = m[weights.any(1)], rows[weights.any(1)], weights[weights.any(1)]
            near_rows.append(np.repeat(rows, 3))
            near_patch.append(patch[vid[m]].ravel())
            near_weight.append(bw[m].ravel())
            point_rows.append(np.repeat(rows, 3))
            point_vid.append(vid[m].ravel())
            point_weight.append(weights.ravel())
    if near <= 0:
        return out
    shape = (len(points), int(n_patches)), (len(points), len(patch))
    near_patch = coo_matrix((np.concatenate(near_weight) / n_rays, (np.concatenate(near_rows),
                                                                  np.concatenate(near_patch))), shape=shape[0])
    near_point = coo_matrix((np.concatenate(point_weight) / n_rays, (np.concatenate(point_rows),
                                                                   np.concatenate(point_vid))), shape=shape[1])
    near_patch, near_point = near_patch.tocsr(), near_point.tocsr()
    near_patch.eliminate_zeros()
    near_point.eliminate_zeros()
    return out, near_patch, near_point


def _longest_edges(vertices, faces) -> np.ndarray:
    """The longest edge of each triangle, ``(F,)``."""
    v = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
    return np.linalg.norm(v - np.roll(v, 1, axis=1), axis=2).max(axis=1)


def _near_point_weights(bw, corners, gatherer, normal, tolerance) -> np.ndarray:
    """Weights ``(R, 3)`` of a near hit's point read: over the hit triangle's corners (``corners (R, 3, 3)``) that
    lie in the gatherer's tangent plane (point ``gatherer (R, 3)``, unit ``normal (R, 3)``; within ``tolerance
    (R,)``), i.e. on the edge where the hit surface meets the gatherer's, its barycentrics ``bw (R, 3)``
    renormalised (equal weights if the hit's own are all zero there). A row with no such corner, or a back-face
    hit (``bw`` zero), is zero: that ray keeps its coefficient read."""
    offset = np.abs(np.einsum("rkc,rc->rk", corners - gatherer[:, None, :], normal))
    on_edge = (offset <= np.asarray(tolerance)[:, None]) & (np.sum(bw, axis=1) > 0)[:, None]
    out = np.where(on_edge, np.asarray(bw, dtype=np.float64), 0.0)
    total = out.sum(axis=1, keepdims=True)
    out = np.where(total > 0, out / np.where(total > 0, total, 1.0), on_edge / np.maximum(on_edge.sum(1), 1)[:, None])
    return out


def _patch_mean(patch, areas, n_patches):
    """Weights ``a_v / A_patch(v)`` of the area-weighted mean over each patch."""
    total = np.bincount(patch, weights=areas, minlength=n_patches)
    return areas / np.where(total > 0, total, 1.0)[patch]


def hat_projection(caster: RayCaster, patch) -> np.ndarray | None:
    """``M^{-1} diag(a)`` (dense, ``(V, V)``) when the patches are the vertices (else None): hat averages
    ``y_hat`` to the coefficients ``c`` of the linear interpolant with the same hat integrals, ``M c = a y_hat``
    (:func:`mass_matrix`, ``a`` the vertex areas). Interpolating the hat averages themselves puts an edge vertex's
    value where its one-sided hat's centroid is: the sunlit room's edge vertices came out 5% and corners 16% too
    bright; nodal point values lose power (2.5% low): this projection gave 1.7% and 5% (``docs/notes/portals.md``).
    """
    patch = np.asarray(patch)
    if len(patch) != int(patch.max(initial=-1)) + 1:
        return None
    mass = mass_matrix(caster).toarray()
    return np.linalg.solve(mass, np.diag(mass.sum(axis=1)))


def limited_projection(hat_values, mass, areas=None, consistent=None) -> np.ndarray:
    """Hat averages ``hat_values (V, k)`` to non-negative interpolant coefficients with the same total power: the
    consistent projection ``M^-1 diag(a) y`` (:func:`hat_projection`) limited by flux correction (Zalesak's limiter,
    bounds ``[0, inf)``), float64.

    The lumped coefficients ``y`` (non-negative, same power) are corrected by the antidiffusive fluxes ``f_uv = m_uv
    (c_u - c_v)`` (``c`` the consistent coefficients, ``m_uv`` the off-diagonal mass-matrix entries), each scaled
    by ``alpha_uv = alpha_vu`` in ``[0, 1]`` so that no coefficient goes below 0: ``c_u = y_u + sum_v alpha_uv f_uv
    / a_u``. The fluxes are antisymmetric, so ``sum_u a_u c_u = sum_u a_u y_u`` whatever ``alpha``; where no bound
    is hit, ``alpha = 1`` and ``c`` is the consistent projection. Contract: ``y >= 0`` gives ``c >= 0``.

    Why: next to a sharp sun patch the consistent projection rings below zero (on the sunlit room at a 60-degree
    sun the floor's row along the window wall came out at -1.1 against a hat average of +0.06), and a vertex on an
    edge, half of whose hemisphere sees the adjacent surface at a millimetre, reads those coefficients
    (``docs/notes/portals.md``).

    ``mass``: the consistent mass matrix (:func:`mass_matrix`, sparse ``(V, V)``); ``areas``: its row sums (the
    vertex areas; computed when not given); ``consistent``: ``M^-1 diag(a) y`` if known (solved when not given).
    """
    from scipy.sparse import coo_matrix

    y = np.asarray(hat_values, dtype=np.float64)
    squeeze = y.ndim == 1
    y = y[:, None] if squeeze else y
    m = coo_matrix(mass)
    if m.shape != (len(y), len(y)):
        raise ValueError(f"mass must be ({len(y)}, {len(y)}) to match hat_values, got {m.shape}")
    a = np.asarray(m.sum(axis=1)).ravel() if areas is None else np.asarray(areas, dtype=np.float64)
    off = m.row != m.col
    i, j, w = m.row[off], m.col[off], m.data[off]
    if consistent is None:
        consistent = np.linalg.solve(m.toarray(), a[:, None] * y) if len(y) else y.copy()
    consistent = np.asarray(consistent, dtype=np.float64).reshape(y.shape)
    out = np.empty_like(y)
    n = len(y)
    for k in range(y.shape[1]):
        low, high = y[:, k], consistent[:, k]
        flux = w * (high[i] - high[j])  # into u = i from its neighbour j
        lack = np.bincount(i, weights=np.minimum(flux, 0.0), minlength=n)  # <= 0
        room = -a * np.maximum(low, 0.0)  # the most a vertex may lose and stay >= 0
        r_minus = np.where(lack < 0, np.minimum(1.0, room / np.where(lack < 0, lack, -1.0)), 1.0)
        alpha = np.where(flux < 0, r_minus[i], r_minus[j])  # the upper bound is infinite: R+ = 1
        out[:, k] = low + np.bincount(i, weights=alpha * flux, minlength=n) / np.where(a > 0, a, 1.0)
    return out[:, 0] if squeeze else out


def patch_operator(hat_gather, albedo, patch, areas, n_patches: int, project=None) -> np.ndarray:
    """``K (C, C, 3)``: one bounce between the patches' light (float64).

    With ``project`` (patches = vertices): ``K = M^{-1} diag(a rho) F_hat`` on the interpolant's coefficients,
    ``F_hat`` the gather averaged over each vertex's hat (:func:`hat_points`). Otherwise (clusters) the
    area-weighted mean over each patch, ``K_cd = sum_{v in c} a_v rho_v F_hat,vd / A_c``.
    """
    from scipy.sparse import csr_matrix

    patch = np.asarray(patch, dtype=np.int64)
    hat_gather = np.asarray(hat_gather, dtype=np.float64)
    albedo = np.asarray(albedo, dtype=np.float64)
    out = np.zeros((n_patches, n_patches, 3))
    if project is not None:
        for ch in range(3):
            out[:, :, ch] = project @ (albedo[:, ch][:, None] * hat_gather)
        return out
    w = _patch_mean(patch, np.asarray(areas, dtype=np.float64), n_patches)
    for ch in range(3):
        mean = csr_matrix((w * albedo[:, ch], (patch, np.arange(len(patch)))), shape=(n_patches, len(patch)))
        out[:, :, ch] = mean @ hat_gather
    return out


def power_sum(h, b: int, project=None) -> np.ndarray:
    """``S_b = sum_{j=0}^{b-1} H^j`` per colour channel (``h (C, C, 3)``) by binary doubling (``S_{m + 2^i} = S_m
    + H^m S_{2^i}``, ``S_{2^(i+1)} = S_{2^i} + H^{2^i} S_{2^i}``), times ``project`` on the right if given;
    ``b = 0`` gives zeros."""
    h = np.asarray(h, dtype=np.float64)
    c = h.shape[0]
    out = np.zeros_like(h)
    if b <= 0:
        return out
    bits = bin(int(b))[:1:-1]  # least significant first
    for ch in range(h.shape[2]):
        total, power = np.zeros((c, c)), np.eye(c)  # S_m, H^m for the bits done
        s_block, p_block = np.eye(c), h[:, :, ch].copy()  # S_{2^i}, H^{2^i}
        for i, bit in enumerate(bits):
            if bit == "1":
                total = total + power @ s_block
                power = power @ p_block
            if i + 1 < len(bits):
                s_block = s_block + p_block @ s_block
                p_block = p_block @ p_block
        out[:, :, ch] = total if project is None else total @ project
    return out


class SurfaceTransfer:
    """The stored interior-to-interior transfer and its per-frame product (module docstring).

    ``gather (V, C)`` (or its ``(codes, scale)``), ``patch (V,)``, ``areas (V,)``, ``albedo (V, 3)``, ``operator
    (C, C, 3)`` (``K``), ``sums``
    a dict ``b -> S_b (C, C, 3)``, ``project`` (``M^-1 diag(a)`` or None). The gather is kept as 16-bit codes
    with a scale per row (:func:`quantize_rows`): the per-frame product reads ``2 V C`` bytes.

    ``mass`` (patches = vertices; the consistent mass matrix, :func:`mass_matrix`): the direct light's term of the
    bounce sum (``b = 0``, the source of the first bounce) is projected by :func:`limited_projection` instead of
    ``project`` (``limit=False``: the unlimited consistent projection, kept for measurement), per frame.
    """

    def __init__(self, gather, patch, areas, albedo, operator, sums: dict, project=None, mass=None,
                 limit: bool = True, near=None):
        self.codes, self.scale = gather if isinstance(gather, tuple) else quantize_rows(gather)
        self.patch = np.asarray(patch, dtype=np.int64)
        self.n_patches = self.codes.shape[1]
        self.mean_weight = _patch_mean(self.patch, np.asarray(areas, dtype=np.float64), self.n_patches)
        self.identity = self.n_patches == len(self.patch) and np.array_equal(self.patch, np.arange(len(self.patch)))
        self.albedo = np.asarray(albedo, dtype=np.float64)
        self.operator = np.asarray(operator)
        self.sums = {int(b): _channel_major(s) for b, s in sums.items()}  # (3, C, C) float32
        self.project = None if project is None else np.asarray(project, dtype=np.float64)
        self.mass = mass if (limit and mass is not None and self.project is not None) else None
        self.areas = np.asarray(areas, dtype=np.float64)
        self._all_rows = np.arange(len(self.codes), dtype=np.int64)
        self.near = None if near is None else tuple(near)
        self.task_cuts = {}  # shade_surface's row chunks of the gather and the near partners among them
        if self.near is not None:  # the vertices whose point values near hits read
            self.partners = np.unique(self.near[1].indices).astype(np.int64)
            self.partner_albedo = np.ascontiguousarray(self.albedo[self.partners])
            self.partner_slot = np.full(len(self.patch), -1, dtype=np.int64)  # v -> its row in partners, or -1
            self.partner_slot[self.partners] = np.arange(len(self.partners))

    def bounce_sum(self, b: int) -> np.ndarray:
        """``S_b``, ``(C, C, 3)`` float32 (a view of the channel-major ``(3, C, C)`` copy the frame reads; computed
        from ``H`` and kept when not stored)."""
        return self._bounce_sum_t(b).transpose(1, 2, 0)

    def _bounce_sum_t(self, b: int) -> np.ndarray:
        if b not in self.sums:
            self.sums[b] = _channel_major(power_sum(self.operator, b, self.project))
        return self.sums[b]

    def patch_source(self, direct) -> np.ndarray:
        """``s = Pbar L_d``, ``(C, 3)`` float64: the patches' area-weighted mean of the per-vertex ``direct (V, 3)``."""
        direct = np.asarray(direct, dtype=np.float64)
        if self.identity:
            return direct.copy()
        s = np.zeros((self.n_patches, 3))
        for ch in range(3):
            s[:, ch] = np.bincount(self.patch, weights=self.mean_weight * direct[:, ch], minlength=self.n_patches)
        return s

    def indirect(self, direct, bounces: int, method: str = "numba") -> np.ndarray:
        """``L_ind = rho * F (S_B Pbar L_d)``, ``(V, 3)`` float64, from the direct radiance ``direct (V, 3)``."""
        return self.frame(self.patch_source(direct), bounces, method)

    def frame(self, source, bounces: int, method: str = "numba", direct=None) -> np.ndarray:
        """``L_ind = rho * F (S_B s)``, ``(V, 3)`` float64, from the patches' source light ``source (C, 3)``
        (:meth:`patch_source`, or :meth:`SourceOperator.apply` straight from the shell light).

        With ``near`` data and the vertices' direct radiance ``direct (V, 3)`` (point values), the gather's near
        hits read point values instead (:meth:`near_correction`).

        ``method="numba"``: ``S_B s`` and the product with the 16-bit gather in float32 sums (forward error at most
        ``(C + 2) eps_32`` times the same sums of absolute values, each); ``"reference"``: the stored (float32, 16-bit)
        data decoded to float64, float64 throughout.
        """
        source = np.asarray(source, dtype=np.float64)
        n = len(self.patch)
        if bounces <= 0:
            return np.zeros((n, 3))
        if method not in ("numba", "reference"):
            raise ValueError(f"method must be 'numba' or 'reference', got {method!r}")
        light = self._light(source, int(bounces), method)
        out = self._gather(light, self._all_rows, method)
        if self.near is not None and direct is not None:
            out += self.near_correction(source, int(bounces), light, direct, method)
        return out

    def _gather(self, light, rows, method: str) -> np.ndarray:
        """``rho F light`` at the vertices ``rows``, ``(len(rows), 3)`` float64: the 16-bit gather product in float32
        sums (``"numba"``) or decoded to float64 (``"reference"``)."""
        if method == "reference":
            codes = self.codes if len(rows) == len(self.codes) else self.codes[rows]
            scale = self.scale[rows].astype(np.float64)
            return self.albedo[rows] * ((codes.astype(np.float64) * scale[:, None]) @ light)
        from ._shade import _threads_for

        out = np.empty((len(rows), 3))
        albedo = self.albedo if len(rows) == len(self.codes) else np.ascontiguousarray(self.albedo[rows])
        with _threads_for(len(rows) * self.n_patches * 3):
            _kernels.gather_product_kernel(self.codes, self.scale, np.ascontiguousarray(light.T), albedo, out, rows)
        return out

    def _light(self, source, bounces: int, method: str) -> np.ndarray:
        """``S_B s`` with the ``b = 0`` term limited, ``(C, 3)``: float64 (``"reference"``) or float32 sums."""
        correction = self.source_correction(source)
        if method == "reference":
            light = np.einsum("cdk,dk->ck", self.bounce_sum(bounces).astype(np.float64), source)
            return light if correction is None else light + correction
        from ._shade import _threads_for

        sums_t = self._bounce_sum_t(bounces)
        light_t = np.empty((3, self.n_patches), dtype=np.float32)
        with _threads_for(sums_t.size):
            _kernels.bounce_light_kernel(sums_t, np.ascontiguousarray(source), light_t)
        if correction is not None:
            light_t += correction.T.astype(np.float32)
        return light_t.T

    def near_correction(self, source, bounces: int, light, direct, method: str = "numba") -> np.ndarray:
        """What the near hits' point reads change in ``L_ind``, ``(V, 3)`` float64.

        A gather ray that lands within a fraction of its triangle's size (a vertex on a concave edge sees the
        adjacent surface from millimetres) reads the linear interpolant of the light's coefficients there, whose
        ramp across the cell a sharp sun patch's edge does not follow (the sunlit room's window wall, bottom row,
        at a 60-degree sun: 35% too bright). Such rays instead read the hit surface's point values at the hit
        triangle's corners on the edge the two surfaces share: ``L_d + L_ind^(B-1)`` there (the light that left them
        after ``0 .. B-1`` bounces; ``L_ind^(B-1)`` from the gather itself, without this correction). So ``L_ind += rho
        (N_point (L_d + L_ind^(B-1)) - N_patch S_B s)``, ``N_*`` the near rays' parts of the gather
        (:func:`patch_gather` with ``near``). ``light``: ``S_B s`` as :meth:`frame` computed it.
        """
        near_patch, near_point = self.near
        point = np.array(direct, dtype=np.float64)
        if bounces > 1:
            point[self.partners] += self._gather(self._light(source, bounces - 1, method), self.partners, method)
        return self.albedo * (near_point @ point - near_patch @ np.asarray(light, dtype=np.float64))

    def source_correction(self, source):
        """With ``mass``: ``limited_projection(s) - project s`` (``(C, 3)`` float64), what turns the bounce sum's
        ``b = 0`` term from the consistent projection into the limited one; else None."""
        if self.mass is None:
            return None
        source = np.asarray(source, dtype=np.float64)
        consistent = self.project @ source
        return limited_projection(source, self.mass, self.areas, consistent) - consistent

    def sent_direct(self, source):
        """The direct light the vertices send, as interpolant coefficients ``(V, 3)`` float64 with the hat averages'
        power: the limited projection of the patches' source ``s (C, 3)`` (the ``b = 0`` term of :meth:`frame`'s
        bounce sum); None when the patches are clusters (no per-vertex hat averages)."""
        if self.project is None:
            return None
        source = np.asarray(source, dtype=np.float64)
        consistent = self.project @ source
        return consistent if self.mass is None else limited_projection(source, self.mass, self.areas, consistent)

    def patch_light(self, direct, bounces: int) -> np.ndarray:
        """``S_B Pbar L_d``, ``(C, 3)`` float64 from the stored float32 ``S_B``: the light the patches send after
        ``0 .. B-1`` bounces (the ``b = 0`` term limited as in :meth:`frame`)."""
        if bounces <= 0:
            return np.zeros((self.n_patches, 3))
        return self._light(self.patch_source(direct), int(bounces), "reference")

    def source_operator(self, source) -> "SourceOperator":
        """The per-frame-invariant product ``Pbar diag(rho) T_src`` of a hat-averaged source transfer ``source``
        (:class:`prtlab.wavelet.SparseTransfer`, ``V`` rows): :class:`SourceOperator`."""
        return SourceOperator(source, self.patch, self.mean_weight, self.albedo, self.n_patches)


class SourceOperator:
    """``G = Pbar diag(rho) T_src`` as a CSR matrix ``(C, 2 T)`` with one float64 value per colour channel.

    The patches' source light ``s = Pbar (rho * T_src L)`` is then ``G [L_pulse; L_haar]`` per frame: ``C`` rows,
    each the union of its vertices' entries, instead of a pass over all ``V`` vertices; the same sums reassociated
    (float64 roundoff). ``T = 6 r^2``; a vertex stored in Haar has its entries in columns ``T..2T-1``.

    Parameters
    ----------
    source : SparseTransfer
        The 8-bit hat-averaged source transfer, ``V`` rows.
    patch : (V,) int
    mean_weight : (V,) float
        ``a_v / A_patch(v)``.
    albedo : (V, 3) float
    n_patches : int
    """

    def __init__(self, source, patch, mean_weight, albedo, n_patches: int):
        n_texels = 6 * source.res * source.res
        counts = np.diff(source.indptr)
        rows = np.repeat(np.arange(source.n_vertices), counts)
        raw = source.indices.astype(np.int64)
        columns = (raw & (source.sign_bit - 1)) + n_texels * source.basis.astype(np.int64)[rows]
        code = np.where(raw >= source.sign_bit, -1.0, 1.0) * source.codes
        weight = np.asarray(mean_weight, dtype=np.float64) * source.scale.astype(np.float64) / 255.0
        key = np.asarray(patch, dtype=np.int64)[rows] * (2 * n_texels) + columns
        keys, where = np.unique(key, return_inverse=True)
        albedo = np.asarray(albedo, dtype=np.float64)
        self.values = np.empty((len(keys), 3))
        for ch in range(3):
            self.values[:, ch] = np.bincount(where, weights=code * (weight * albedo[:, ch])[rows],
                                             minlength=len(keys))
        self.columns = (keys % (2 * n_texels)).astype(np.uint32)
        self.indptr = np.searchsorted(keys // (2 * n_texels), np.arange(n_patches + 1)).astype(np.int64)
        self.res = int(source.res)

    @property
    def nbytes(self) -> int:
        return self.values.nbytes + self.columns.nbytes + self.indptr.nbytes

    def apply(self, light) -> np.ndarray:
        """``s = G light``, ``(C, 3)`` float64, from the shell light's coefficients ``light (2 T, 3)``
        (:func:`prtlab.portals._shade.shell_coefficients`)."""
        from ._shade import _threads_for

        out = np.empty((len(self.indptr) - 1, 3))
        with _threads_for(3 * len(self.columns)):
            _kernels.source_light_kernel(self.indptr, self.columns, self.values, np.ascontiguousarray(light), out)
        return out


def _channel_major(sums) -> np.ndarray:
    """``(C, C, 3)`` bounce sums as contiguous float32 ``(3, C, C)``: each channel's rows contiguous for the frame."""
    return np.ascontiguousarray(np.moveaxis(np.asarray(sums), 2, 0), dtype=np.float32)


def quantize_rows(gather):
    """16-bit codes ``round(65535 F / max_row)`` (uint16, ``(V, C)``) and the per-row scales ``max_row / 65535``
    (float32): each entry is off by at most ``max_row / 131070``. (8 bits were off by up to 1.2% per vertex on a
    130-vertex closed room: a row has few large entries, so their rounding errors do not cancel.)"""
    gather = np.asarray(gather, dtype=np.float64)
    top = gather.max(axis=1, initial=0.0) if gather.size else np.zeros(len(gather))
    scale = np.where(top > 0, top / 65535.0, 1.0)
    codes = np.rint(gather / scale[:, None]).astype(np.uint16)
    return np.ascontiguousarray(codes), scale.astype(np.float32)


def _centroid_pattern(n: int) -> np.ndarray:
    """Barycentrics ``(n^2, 3)`` of the centroids of the ``n^2`` equal sub-triangles of a triangle split ``n`` ways
    per edge."""
    uv = [((i + 1 / 3) / n, (j + 1 / 3) / n) for i in range(n) for j in range(n - i)]
    uv += [((i + 2 / 3) / n, (j + 2 / 3) / n) for i in range(n - 1) for j in range(n - 1 - i)]
    uv = np.array(uv)
    return np.column_stack([1.0 - uv.sum(1), uv])


def hat_points(caster: RayCaster, vertex_offset, vertex_normals, rows: slice, split: int = 4):
    """Points that average a function over each vertex's hat function (its linear interpolation weight).

    For the vertices ``rows`` (global caster order): every triangle touching one is split ``split`` ways per edge
    and each sub-triangle's centroid ``x`` (normal: the vertex normals interpolated) gets, for each corner ``u`` in
    ``rows``, the weight ``b_u(x) A / (split^2 a_u)`` (``b_u`` its barycentric, ``A`` the triangle's area, ``a_u`` a
    third of the areas round ``u``), so that ``sum_x w_ux f(x)`` is the hat-weighted mean of ``f`` about ``u``.

    Returns
    -------
    points, normals : (X, 3) float64
    weights : scipy.sparse.csr_matrix (rows, X)
    """
    from scipy.sparse import csr_matrix

    faces = np.concatenate([caster.faces(i) + vertex_offset[i] for i in range(caster.n_objects)])
    verts = np.concatenate([caster.world_vertices(i) for i in range(caster.n_objects)])
    touch = np.nonzero(np.any((faces >= rows.start) & (faces < rows.stop), axis=1))[0]
    f = faces[touch]
    pattern = _centroid_pattern(split)
    s = len(pattern)
    points = np.einsum("sk,tkc->tsc", pattern, verts[f]).reshape(-1, 3)
    normals = np.einsum("sk,tkc->tsc", pattern, vertex_normals[f]).reshape(-1, 3)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    v = verts[f]
    area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    a_u = np.bincount(faces.ravel(), weights=np.repeat(0.5 * np.linalg.norm(np.cross(
        verts[faces[:, 1]] - verts[faces[:, 0]], verts[faces[:, 2]] - verts[faces[:, 0]]), axis=1) / 3.0, 3),
        minlength=len(verts))
    x_index = np.arange(len(touch) * s).reshape(len(touch), s)
    w = pattern[None, :, :] * (area / s)[:, None, None]  # (t, s, 3)
    u = np.broadcast_to(f[:, None, :], w.shape)
    x = np.broadcast_to(x_index[:, :, None], w.shape)
    mine = (u >= rows.start) & (u < rows.stop)
    weights = csr_matrix((w[mine] / a_u[u[mine]], (u[mine] - rows.start, x[mine])),
                         shape=(rows.stop - rows.start, len(points)))
    return points, normals, weights


def mass_matrix(caster: RayCaster):
    """The consistent mass matrix of linear (hat) elements over every caster object, ``M_uv = int phi_u phi_v``
    (``A / 12 (1 + [u = v])`` per triangle), ``scipy.sparse.csr_matrix (N, N)``; its row sums are the vertex
    areas (:func:`vertex_areas`)."""
    from scipy.sparse import coo_matrix

    rows, cols, vals, offset = [], [], [], 0
    for i in range(caster.n_objects):
        v, f = caster.world_vertices(i), caster.faces(i)
        a = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
        for p in range(3):
            for q in range(3):
                rows.append(f[:, p] + offset)
                cols.append(f[:, q] + offset)
                vals.append(a / 12.0 * (2.0 if p == q else 1.0))
        offset += len(v)
    return coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(offset, offset)).tocsr()


#: row chunks per thread of the direct pass and of the gather product under :func:`tasks_on`
TASK_CHUNKS = 8

#: the direct pass's row chunks of each transfer under :func:`tasks_on`, by chunk count
_DIRECT_CUTS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def tasks_on() -> bool:
    """Whether :func:`shade_surface` runs the default frame's passes as tasks (:data:`prtlab._tasks.TASKS`): on as
    many Python threads as numba has threads, each kernel on one numba thread (its docstring), so that the small
    serial passes overlap the direct pass, the gather's memory traffic overlaps the direct pass's arithmetic and no
    parallel region waits for a descheduled thread; on one thread (or numba's ``workqueue`` layer, or a thread of
    the tasks' pool) the same tasks one after another (the near partners' rows still read with their chunk of the
    gather). Every row's sums are those of the passes run one after another, so the frame is the same bit for bit
    (tests); off, the passes run one after another, every thread in each kernel."""
    return _tasks.TASKS


def _cuts(n: int, k: int, indptr=None) -> list:
    """``[(a, b), ..]`` cutting ``n`` rows into at most ``k`` non-empty chunks of about equal rows (or entries of the
    CSR ``indptr``)."""
    if indptr is None:
        cuts = [n * i // k for i in range(k + 1)]
    else:
        cuts = [0] + np.searchsorted(indptr, (np.arange(1, k, dtype=np.int64) * int(indptr[-1])) // k).tolist() + [n]
    return [(a, b) for a, b in zip(cuts[:-1], cuts[1:]) if b > a]


def shade_surface(direct, albedo, cube, source_operator: SourceOperator, surface: SurfaceTransfer,
                  bounces: int) -> tuple[np.ndarray, np.ndarray]:
    """The default frame's direct and indirect radiance, ``(V, 3)`` float64 each, numba tiers, from a checked shell
    light ``cube (6, r, r, 3)`` and ``(V, 3)`` float64 ``albedo``: with ``L = shell_coefficients(cube)``, ``L_d =
    direct_from_light(direct, albedo, L)`` and ``surface.frame(source_operator.apply(L), bounces, direct=L_d)``.

    With :func:`tasks_on`, as tasks on Python threads, each kernel on one numba thread (the same bits; on one
    thread, one after another): one thread runs the chain (the light's Haar coefficients, ``G L``, ``S_B s`` and
    ``S_(B-1) s``, the near rays' patch reads ``N_patch S_B s``), then row chunks of the gather product, each
    followed by the near partners among its rows (their rows still in cache: read apart, the scattered rows took
    2.6x as long, 1.56 against 0.60 ms on one thread); the others row chunks of the direct pass's pulse rows (which
    read no Haar coefficient), then its Haar rows; a thread takes the other queue's chunks once its own is done.
    Then the near rays' point reads in one serial kernel (``L_ind += rho (N_point (L_d + rho F S_(B-1) s) -
    N_patch S_B s)``)."""
    from ._shade import direct_from_light, direct_operands, direct_rows, shell_coefficients

    if not tasks_on() or bounces <= 0 or not direct.n_vertices or direct.n_vertices != len(surface.patch):
        light = shell_coefficients(cube)
        radiance = direct_from_light(direct, albedo, light)
        return radiance, surface.frame(source_operator.apply(light), bounces, direct=radiance)
    threads = numba.get_num_threads()
    bounces = int(bounces)
    n = direct.n_vertices
    cube = np.asarray(cube, dtype=np.float64)
    n_texels = cube.shape[0] * cube.shape[1] * cube.shape[2]
    light = np.zeros((2 * n_texels, 3))  # shell_coefficients(cube): its Haar half filled by the chain
    light[:n_texels] = cube.reshape(n_texels, 3)
    operands = direct_operands(direct, albedo, light)
    light_t = operands[9]  # (3, 2 T): its Haar half copied in by the chain
    radiance = np.empty((n, 3))
    indirect = np.empty((n, 3))
    near = surface.near
    partners = surface.partners if near is not None and bounces > 1 else np.zeros(0, dtype=np.int64)
    partner_light = np.empty((len(partners), 3))
    lights = {}
    haar_ready, ready = threading.Event(), threading.Event()
    claimed = itertools.count()  # the chain's claim: next() on a count is atomic under the GIL
    errors = []

    def chain():  # run by the first thread to claim it
        try:
            try:
                light[n_texels:] = haar2d(cube, channels=True).reshape(n_texels, 3)  # as shell_coefficients
                light_t[:, n_texels:] = light[n_texels:].T
            finally:
                haar_ready.set()
            source = np.asarray(source_operator.apply(light), dtype=np.float64)
            lights["B"] = np.ascontiguousarray(surface._light(source, bounces, "numba").T)
            if len(partners):
                lights["B-1"] = np.ascontiguousarray(surface._light(source, bounces - 1, "numba").T)
            if near is not None:
                lights["patch"] = near[0] @ np.asarray(lights["B"].T, dtype=np.float64)
        except BaseException as error:  # before the chunks waiting on it wake: they see it and stop
            errors.append(error)
        finally:
            haar_ready.set()
            ready.set()

    def product(a, b, pa, pb):  # rows a .. b - 1, then the partners among them
        _kernels.gather_product_kernel(surface.codes, surface.scale, lights["B"], surface.albedo[a:b], indirect[a:b],
                                       surface._all_rows[a:b])
        if pb > pa:
            _kernels.gather_product_kernel(surface.codes, surface.scale, lights["B-1"], surface.partner_albedo[pa:pb],
                                           partner_light[pa:pb], partners[pa:pb])

    k = TASK_CHUNKS * threads
    key = (k, len(partners))
    if key not in _DIRECT_CUTS.setdefault(direct, {}):  # pulse row chunks, Haar row chunks (if any)
        haar_rows = bool(np.any(direct.basis == SparseTransfer.HAAR))
        _DIRECT_CUTS[direct][key] = (_cuts(n, k, direct.indptr), _cuts(n, 2 * threads, direct.indptr) if haar_rows
                                     else [])
    if key not in surface.task_cuts:  # row chunks and the partners among them
        surface.task_cuts[key] = [(a, b, *np.searchsorted(partners, (a, b)).tolist()) for a, b in _cuts(n, k)]
    pulse_cuts, haar_cuts = _DIRECT_CUTS[direct][key]
    rows = [(None, direct_rows, (operands, a, b, radiance, 0)) for a, b in pulse_cuts]
    rows += [(haar_ready, direct_rows, (operands, a, b, radiance, 1)) for a, b in haar_cuts]
    gather = [(ready, product, cut) for cut in surface.task_cuts[key]]
    queues = ((rows, itertools.count()), (gather, itertools.count()))

    def drain(order):
        for tasks, claim in order:
            for i in iter(claim.__next__, None):
                if i >= len(tasks):
                    break
                event, f, args = tasks[i]
                if event is not None:
                    if next(claimed) == 0:
                        chain()
                    event.wait()
                if errors:
                    return
                f(*args)

    def first_worker():
        try:
            if next(claimed) == 0:
                chain()
            drain(queues[::-1])
        except BaseException as error:  # raised by the caller once every thread has ended
            errors.append(error)

    def worker():
        try:
            drain(queues)
        except BaseException as error:
            errors.append(error)

    if threads == 1 or _tasks.on_pool() or not _tasks.concurrent_kernels():
        first_worker()
    else:
        pool = _tasks.pool(threads)
        futures = [pool.submit(first_worker)] + [pool.submit(worker) for _ in range(threads - 2)]
        numba.set_num_threads(1)
        try:
            worker()
        finally:
            numba.set_num_threads(threads)
            futures_wait(futures)
    if errors:
        raise errors[0]
    if near is not None:  # the near rays' point reads
        m = near[1].tocsr()
        slot = surface.partner_slot if len(partners) else np.full(n, -1, dtype=np.int64)
        _kernels.near_point_kernel(m.indptr, m.indices, m.data, radiance, slot, partner_light, lights["patch"],
                                   surface.albedo, indirect)
    return radiance, indirect

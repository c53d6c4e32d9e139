"""Numba kernels of the per-frame passes (one per shader pass); the specifications are in ``_passes.py``."""

from __future__ import annotations

import math

import numba
import numpy as np

from prtlab.geometry import _embree
from prtlab.geometry._raycast import barycentric_normal
from prtlab.sh._product_kernels import _tile_product
from prtlab.shadowfields._kernels import locate_point, sample_corners


@numba.njit(cache=True, fastmath=False)  # set: callees inherit a caller's fastmath unless set
def _strict_corners(rpos, s, t, n_r, res):
    """:func:`sample_corners` compiled without fastmath and not inlined by numba: the fastmath kernels that call it
    get the cell and the weights' factors rounded as the float64 tier rounds them (contracted or reassociated, a
    weight near 0 would err by ``~res 2**-53`` absolute, not relative)."""
    return sample_corners(rpos, s, t, n_r, res)


#: Columns of the per-vertex placement that :func:`eq13_kernel` makes first: the fractional sphere index, the cube
#: face (an integer as a float), the face coordinates and the factor ``(r_max / max(r, r_max))^2``.
_RPOS, _FACE, _S, _T, _SCALE = 0, 1, 2, 3, 4


def eq13_kernel(flat_rows, values, column_scale, scaled, points, translate, rotation, size, center, radii, res,
                sh_rotation, transfer, in_cell_order, out):
    """Eq. 13 at receiver vertices: ``Phi[v, k', m] = sum_i S_m(x_v)[i] T[v, k', i]``, ``S`` the trilinear blend
    of the 8 sample points around the vertex on the source's spheres (times ``(r_max / r)^2`` beyond the outermost).

    Each vertex is placed in the source's object frame first (``((x - translate) @ rotation) / size``, located on
    the spheres as ``SphereGrid.locate``) and its transfer turned into that frame (``sh_rotation @ T``, the
    block-diagonal SH rotation, or as given when ``sh_rotation`` is empty). Per value, the 8 corners' rows are
    blended term by term with their weights and the blend is dotted with the transfer, summed in any order
    (``reassoc``, ``contract``): a value is a sum of ``8 n2`` products with at most ``n2 + 13`` roundings on any
    term's path (the weight's 4, a stored row's scale, the row's product, the blend's 7, the transfer's product, the
    dot's ``n2 - 1``), so it errs by at most ``(n2 + 14) 2**-53`` times the sum of its terms' magnitudes, as does
    the float64 tier (given the same placement and transfer). A corner without a row (``flat_rows`` -1: the field is 0
    there) adds nothing; a corner of weight 0 adds ``0 * row`` (the field must be finite).

    flat_rows : (n_r * 6 * res * res,) int32, the row in ``values`` of each sample point ``(r, face, i, j)``, or -1
    values : (n_rows, M, n2) float64, float32 or int16, M = K * N
    column_scale : (n_rows, M) float32, each row block's factor when ``scaled`` (int16 storage; exact in float64)
    points : (V, 3) receiver vertices, world space; translate (3,), rotation (3, 3), size: the source's pose
    center (3,), radii (n_r,) >= 2 increasing, res: the spheres and their faces' texels
    sh_rotation : (n2, n2) or (0, 0)
    transfer : (V, K', n2) ``P_n(V_j G_jk')`` in the world frame
    in_cell_order : bool, take the vertices sorted by cell (:func:`_cell_order`; the same values, bit for bit): for
        fields larger than the caches, whose rows random vertices would gather from memory
    out : (V, K', M)

    Returns False, with ``out`` untouched, if a point or a transfer value is not finite. A Python function calling
    the parallel kernels in turn: a cached non-parallel numba function that calls a parallel one can crash when
    loaded from numba's cache (numba issue 8578).
    """
    n_v = points.shape[0]
    place = np.empty((n_v, 5))
    if not _place_vertices(points, translate, rotation, size, center, radii, transfer, place):
        return False
    n_r = radii.shape[0]
    order = _cell_order(place, n_r, res) if in_cell_order else np.arange(n_v)
    _eq13_blocks(flat_rows, values, column_scale, scaled, order, place, sh_rotation, transfer, n_r, res, out)
    return True


@numba.njit(cache=True, parallel=True, nogil=True)
def _place_vertices(points, translate, rotation, size, center, radii, transfer, place):
    """The placement of :func:`eq13_kernel`: the pose as explicit sums, then ``SphereGrid.locate``'s steps
    (:func:`locate_point`) and the factor; False if a point or a transfer value is not finite (``place`` then
    partly written)."""
    n_v = points.shape[0]
    finite = np.ones(n_v, np.bool_)
    r_max = radii[radii.shape[0] - 1]
    for v in numba.prange(n_v):
        ok = np.isfinite(points[v, 0]) and np.isfinite(points[v, 1]) and np.isfinite(points[v, 2])
        for kp in range(transfer.shape[1]):
            for i in range(transfer.shape[2]):
                ok = ok and np.isfinite(transfer[v, kp, i])
        finite[v] = ok
        if not ok:
            continue
        d = (points[v, 0] - translate[0], points[v, 1] - translate[1], points[v, 2] - translate[2])
        x = (d[0] * rotation[0, 0] + d[1] * rotation[1, 0] + d[2] * rotation[2, 0]) / size
        y = (d[0] * rotation[0, 1] + d[1] * rotation[1, 1] + d[2] * rotation[2, 1]) / size
        z = (d[0] * rotation[0, 2] + d[1] * rotation[1, 2] + d[2] * rotation[2, 2]) / size
        rpos, face, s, t, r = locate_point(x - center[0], y - center[1], z - center[2], radii)
        f = r_max / max(r, r_max)
        place[v, _RPOS], place[v, _FACE], place[v, _S], place[v, _T], place[v, _SCALE] = rpos, face, s, t, f * f
    return finite.all()


@numba.njit(cache=True, nogil=True)
def _cell_order(place, n_r, res):
    """Vertex indices sorted (stably, by counting) by the sample point of each vertex's first trilinear corner
    ``(r0, face, i0, j0)``: vertices taken in this order gather their 8 rows from a few neighbouring cells."""
    n_v = place.shape[0]
    key = np.empty(n_v, np.int64)
    start = np.zeros(n_r * 6 * res * res + 1, np.int64)
    for v in range(n_v):
        r0, _, _, i0, _, _, j0, _, _ = _strict_corners(place[v, _RPOS], place[v, _S], place[v, _T], n_r, res)
        key[v] = ((r0 * 6 + int(place[v, _FACE])) * res + i0) * res + j0
        start[key[v] + 1] += 1
    for k in range(len(start) - 1):
        start[k + 1] += start[k]
    order = np.empty(n_v, np.int64)
    for v in range(n_v):
        order[start[key[v]]] = v
        start[key[v]] += 1
    return order


#: Vertices per block of :func:`_eq13_blocks`: their inputs gathered and their outputs scattered in short loops.
EQ13_BLOCK = 64


@numba.njit(cache=True, inline="always")
def _blend_dot(values, k0, k1, k2, k3, k4, k5, k6, k7, w0, w1, w2, w3, w4, w5, w6, w7, tr, b, kp, m, n2):
    """``sum_i (sum_c w_c values[k_c, m, i]) tr[b, kp, i]`` over ``i < n2``: the 8 rows blended term by term (8
    loads and 8 multiply-adds a lane), then the dot product (one reduction a value)."""
    x = 0.0
    for i in range(n2):
        x += (((w0 * values[k0, m, i] + w1 * values[k1, m, i]) + (w2 * values[k2, m, i] + w3 * values[k3, m, i]))
              + ((w4 * values[k4, m, i] + w5 * values[k5, m, i]) + (w6 * values[k6, m, i] + w7 * values[k7, m, i]))
              ) * tr[b, kp, i]
    return x


@numba.njit(cache=True, parallel=True, fastmath={"reassoc", "contract"}, nogil=True)
def _eq13_blocks(flat_rows, values, column_scale, scaled, order, place, sh_rotation, transfer, n_r, res, out):
    """The body of :func:`eq13_kernel`, vertices taken in ``order`` in blocks of :data:`EQ13_BLOCK`.

    A block's placements and transfers (turned by ``sh_rotation``) are gathered and its outputs scattered in loops
    of short independent loads and stores (in cell order, a vertex's own data is a cache miss that the long Eq. 13
    body cannot overlap); every vertex runs the same arithmetic in either order. A corner without a row takes
    weight 0 and another corner's row; a vertex with none gets 0.
    """
    n_m, n2 = values.shape[1], values.shape[2]
    n_kp = transfer.shape[1]
    n_v = order.shape[0]
    turn = sh_rotation.shape[0] > 0
    for block in numba.prange((n_v + EQ13_BLOCK - 1) // EQ13_BLOCK):
        lo = block * EQ13_BLOCK
        n = min(EQ13_BLOCK, n_v - lo)
        loc = np.empty((n, 5))
        tr = np.empty((n, n_kp, n2))
        phi = np.empty((n, n_kp, n_m))
        for b in range(n):
            v = order[lo + b]
            for c in range(5):
                loc[b, c] = place[v, c]
            for kp in range(n_kp):
                if turn:  # block-diagonal: band l holds the coefficients l^2 .. (l + 1)^2 - 1
                    band = 0
                    for a in range(n2):
                        if a >= (band + 1) * (band + 1):
                            band += 1
                        x = 0.0
                        for c in range(band * band, (band + 1) * (band + 1)):
                            x += sh_rotation[a, c] * transfer[v, kp, c]
                        tr[b, kp, a] = x
                else:
                    for i in range(n2):
                        tr[b, kp, i] = transfer[v, kp, i]
        for b in range(n):
            r0, r1, fr, i0, i1, fi, j0, j1, fj = _strict_corners(loc[b, _RPOS], loc[b, _S], loc[b, _T], n_r, res)
            face = int(loc[b, _FACE])
            a0, a1 = (r0 * 6 + face) * res, (r1 * 6 + face) * res
            k0, k1 = flat_rows[(a0 + i0) * res + j0], flat_rows[(a0 + i0) * res + j1]
            k2, k3 = flat_rows[(a0 + i1) * res + j0], flat_rows[(a0 + i1) * res + j1]
            k4, k5 = flat_rows[(a1 + i0) * res + j0], flat_rows[(a1 + i0) * res + j1]
            k6, k7 = flat_rows[(a1 + i1) * res + j0], flat_rows[(a1 + i1) * res + j1]
            some = max(max(max(k0, k1), max(k2, k3)), max(max(k4, k5), max(k6, k7)))
            if some < 0:
                for kp in range(n_kp):
                    for m in range(n_m):
                        phi[b, kp, m] = 0.0
                continue
            sv = loc[b, _SCALE]
            gr, gi, gj = 1.0 - fr, 1.0 - fi, 1.0 - fj
            u0 = gr * gi * gj * sv if k0 >= 0 else 0.0
            u1 = gr * gi * fj * sv if k1 >= 0 else 0.0
            u2 = gr * fi * gj * sv if k2 >= 0 else 0.0
            u3 = gr * fi * fj * sv if k3 >= 0 else 0.0
            u4 = fr * gi * gj * sv if k4 >= 0 else 0.0
            u5 = fr * gi * fj * sv if k5 >= 0 else 0.0
            u6 = fr * fi * gj * sv if k6 >= 0 else 0.0
            u7 = fr * fi * fj * sv if k7 >= 0 else 0.0
            k0, k1, k2, k3 = (k0 if k0 >= 0 else some), (k1 if k1 >= 0 else some), (k2 if k2 >= 0 else some), \
                (k3 if k3 >= 0 else some)
            k4, k5, k6, k7 = (k4 if k4 >= 0 else some), (k5 if k5 >= 0 else some), (k6 if k6 >= 0 else some), \
                (k7 if k7 >= 0 else some)
            for m in range(n_m):
                w0, w1, w2, w3, w4, w5, w6, w7 = u0, u1, u2, u3, u4, u5, u6, u7
                if scaled:
                    w0, w1 = w0 * np.float64(column_scale[k0, m]), w1 * np.float64(column_scale[k1, m])
                    w2, w3 = w2 * np.float64(column_scale[k2, m]), w3 * np.float64(column_scale[k3, m])
                    w4, w5 = w4 * np.float64(column_scale[k4, m]), w5 * np.float64(column_scale[k5, m])
                    w6, w7 = w6 * np.float64(column_scale[k6, m]), w7 * np.float64(column_scale[k7, m])
                for kp in range(n_kp):
                    if n2 == 16:  # the paper's order 4: a constant trip count, fully vectorised
                        phi[b, kp, m] = _blend_dot(values, k0, k1, k2, k3, k4, k5, k6, k7, w0, w1, w2, w3, w4, w5,
                                                   w6, w7, tr, b, kp, m, 16)
                    else:
                        phi[b, kp, m] = _blend_dot(values, k0, k1, k2, k3, k4, k5, k6, k7, w0, w1, w2, w3, w4, w5,
                                                   w6, w7, tr, b, kp, m, n2)
        for b in range(n):
            v = order[lo + b]
            for kp in range(n_kp):
                for m in range(n_m):
                    out[v, kp, m] = phi[b, kp, m]


@numba.njit(cache=True, parallel=True)
def bounce_kernel(irradiance, weights, out):
    """Eq. 12 before the view factors: ``out[v, k', c] += sum_m irradiance[v, k', m] weights[m, c]``.

    irradiance : (V, K', M) basis irradiance from one source; weights : (M, C) the source's weights
    """
    n_v, n_kp, n_m = irradiance.shape
    n_c = weights.shape[1]
    for v in numba.prange(n_v):
        for kp in range(n_kp):
            for c in range(n_c):
                acc = 0.0
                for m in range(n_m):
                    acc += irradiance[v, kp, m] * weights[m, c]
                out[v, kp, c] += acc


@numba.njit(cache=True, nogil=True)
def outgoing_kernel(light, h, colour, out):
    """``out[v, c] = sum_k h[v, k] colour[k, c] light[v, k, c]`` (:func:`._passes.outgoing_radiance`; serial: a
    frame calls it per receiver, inside its tasks)."""
    n_v, n_k, n_c = light.shape
    for v in range(n_v):
        for c in range(n_c):
            acc = 0.0
            for k in range(n_k):
                acc += h[v, k] * colour[k, c] * light[v, k, c]
            out[v, c] = acc


@numba.njit(cache=True, parallel=True)
def project_hits_kernel(starts, d_idx, value, wy, out):
    """SH projection of a radiance known on the rays that hit: ``out[p, m, i] = sum_h value[h, m] wy[d_h, i]``.

    starts : (P + 1,) the hits of point p are ``starts[p]:starts[p + 1]`` (hits sorted by point)
    d_idx : (H,) quadrature direction of each hit
    value : (H, M) radiance of each hit per (k, i)
    wy : (D, n2) quadrature weight times ``Y_i`` per direction
    out : (P, M, n2), zeroed by the caller
    """
    n_m = value.shape[1]
    n2 = wy.shape[1]
    for p in numba.prange(out.shape[0]):
        for h in range(starts[p], starts[p + 1]):
            d = d_idx[h]
            for m in range(n_m):
                v = value[h, m]
                if v != 0.0:
                    for i in range(n2):
                        out[p, m, i] += v * wy[d, i]


@numba.njit(cache=True, parallel=True)
def hit_basis_kernel(tri, uv, vertex_normals, basis, w_in, psi, shading_n):
    """The source's basis functions at ray hits, 0 on back faces, and the hits' shading normals.

    tri : (H, 3) hit triangle's vertices; uv : (H, 2) barycentrics (of vertices 1, 2)
    vertex_normals : (V, 3); basis : (N, V) ``Psi_i`` at the vertices; w_in : (H, 3) ray directions
    psi : (H, N) out, ``sum_c bary_c Psi_i(tri_c)`` where the shading normal faces the ray's origin, else 0
    shading_n : (H, 3) out, the normalised barycentric blend of the vertex normals
    """
    n_b = basis.shape[0]
    for h in numba.prange(tri.shape[0]):
        b1, b2 = uv[h, 0], uv[h, 1]
        b0 = 1.0 - b1 - b2
        i0, i1, i2 = tri[h, 0], tri[h, 1], tri[h, 2]
        nx, ny, nz = barycentric_normal(vertex_normals, i0, i1, i2, b0, b1, b2)
        length = max(math.sqrt(nx * nx + ny * ny + nz * nz), 1e-300)
        nx, ny, nz = nx / length, ny / length, nz / length
        shading_n[h, 0], shading_n[h, 1], shading_n[h, 2] = nx, ny, nz
        front = nx * w_in[h, 0] + ny * w_in[h, 1] + nz * w_in[h, 2] < 0.0
        for i in range(n_b):
            psi[h, i] = (b0 * basis[i, i0] + b1 * basis[i, i1] + b2 * basis[i, i2]) if front else 0.0


#: Items (rows, points) below which the pipeline runs a kernel's serial twin (``*_serial``: the same loop body,
#: no parallel region; a move_one frame launches about 1,400 regions, most of them on a few hundred items).
SERIAL_ITEMS = 4096


@numba.njit(cache=True, inline="always")
def _masked_product_tile(vis, occ, at, rows, gi, gj, gk, gv, task, tile):
    """:func:`masked_product_kernel`'s work on the ``tile`` positions of ``at`` from ``task * tile`` on."""
    n2 = vis.shape[1]
    start = task * tile
    width = min(tile, at.shape[0] - start)
    a_t = np.zeros((n2, tile))
    b_t = np.zeros((n2, tile))
    o_t = np.empty((n2, tile))
    for q in range(width):
        r = at[start + q]
        for i in range(n2):
            a_t[i, q] = vis[r, i]
            b_t[i, q] = occ[rows[r], i]
    _tile_product(a_t, b_t, gi, gj, gk, gv, o_t)
    for q in range(width):
        r = at[start + q]
        for k in range(n2):
            vis[r, k] = o_t[k, q]


#: Positions of ``at`` a task of :func:`masked_product_kernel` takes.
PRODUCT_TILE = 64


@numba.njit(cache=True, parallel=True, nogil=True)
def masked_product_kernel(vis, occ, at, rows, gi, gj, gk, gv):
    """``vis[a] = P_n(vis[a] occ[rows[a]])`` in place for every ``a`` in ``at``: one occluder's factor of the
    visibility product (``prtlab.sh.product`` truncated to the order of ``vis``) at the receiver rows it
    may shadow, without gathering them first.

    vis : (R, n2) visibility at the rows being computed; occ : (V, n2) the occluder's field at all receiver
    vertices; at : (A,) positions in ``vis``; rows : (R,) receiver vertex of each position;
    (gi, gj, gk, gv) the sparse Gaunt entries of order n.
    """
    n_tiles = (at.shape[0] + PRODUCT_TILE - 1) // PRODUCT_TILE
    for task in numba.prange(n_tiles):
        _masked_product_tile(vis, occ, at, rows, gi, gj, gk, gv, task, PRODUCT_TILE)


@numba.njit(cache=True, nogil=True)
def masked_product_serial(vis, occ, at, rows, gi, gj, gk, gv):
    """:func:`masked_product_kernel` on one thread (no parallel region): the same tiles and arithmetic."""
    n_tiles = (at.shape[0] + PRODUCT_TILE - 1) // PRODUCT_TILE
    for task in range(n_tiles):
        _masked_product_tile(vis, occ, at, rows, gi, gj, gk, gv, task, PRODUCT_TILE)


#: Positions of ``vis`` a task of :func:`visibility_product_kernel` takes (a multiple of ``PRODUCT_TILE``).
VISIBILITY_BLOCK = 256


@numba.njit(cache=True, inline="always")
def _tile_product_runs(at, bt, gi, gj, gv, starts, ot, width):
    """``prtlab.sh._product_kernels._tile_product_prefix`` with the Gaunt entries of each output coefficient k
    (``starts[k]:starts[k + 1]`` of entries sorted by k) added four at a time: the same terms added in the same
    order (the same bits), a quarter of the loads and stores of ``ot``."""
    for k in range(starts.shape[0] - 1):
        for q in range(width):
            ot[k, q] = 0.0
        e = starts[k]
        end = starts[k + 1]
        while e + 4 <= end:
            i0, j0, v0 = gi[e], gj[e], gv[e]
            i1, j1, v1 = gi[e + 1], gj[e + 1], gv[e + 1]
            i2, j2, v2 = gi[e + 2], gj[e + 2], gv[e + 2]
            i3, j3, v3 = gi[e + 3], gj[e + 3], gv[e + 3]
            for q in range(width):
                acc = ot[k, q] + v0 * at[i0, q] * bt[j0, q]
                acc = acc + v1 * at[i1, q] * bt[j1, q]
                acc = acc + v2 * at[i2, q] * bt[j2, q]
                ot[k, q] = acc + v3 * at[i3, q] * bt[j3, q]
            e += 4
        while e < end:
            i0, j0, v0 = gi[e], gj[e], gv[e]
            for q in range(width):
                ot[k, q] += v0 * at[i0, q] * bt[j0, q]
            e += 1


@numba.njit(cache=True, inline="always")
def _visibility_product_block(vis, fields, which, masks, rows, gi, gj, gv, starts, block):
    """:func:`visibility_product_kernel`'s work on the positions ``block * VISIBILITY_BLOCK`` on: per factor, in
    order, the products at the block's positions its mask sets, in tiles of up to ``PRODUCT_TILE``."""
    n2 = vis.shape[1]
    start = block * VISIBILITY_BLOCK
    stop = min(start + VISIBILITY_BLOCK, vis.shape[0])
    at = np.empty(stop - start, np.int64)
    a_t = np.empty((n2, PRODUCT_TILE))
    b_t = np.empty((n2, PRODUCT_TILE))
    o_t = np.empty((n2, PRODUCT_TILE))
    for f in range(which.shape[0]):
        occ = fields[which[f]]
        n_at = 0
        for a in range(start, stop):
            if masks[f, a]:
                at[n_at] = a
                n_at += 1
        for first in range(0, n_at, PRODUCT_TILE):
            width = min(PRODUCT_TILE, n_at - first)
            for q in range(width):
                r = at[first + q]
                for i in range(n2):
                    a_t[i, q] = vis[r, i]
                    b_t[i, q] = occ[rows[r], i]
            _tile_product_runs(a_t, b_t, gi, gj, gv, starts, o_t, width)
            for q in range(width):
                r = at[first + q]
                for k in range(n2):
                    vis[r, k] = o_t[k, q]


@numba.njit(cache=True, parallel=True, nogil=True)
def visibility_product_kernel(vis, fields, which, masks, rows, gi, gj, gv, starts):
    """``vis[a] = P_n(... P_n(vis[a] occ_1[rows[a]]) ... occ_F[rows[a]])`` in place, over the factors ``f``
    (in order) whose ``masks[f, a]`` is set: every occluder's factor of the visibility product in one call, each
    product the arithmetic of :func:`masked_product_kernel` (the same bits as one call of it per factor).

    vis : (R, n2) visibility at the rows being computed; fields : (n_occ, V, n2) occlusion fields at all
    receiver vertices; which : (F,) the field of each factor; masks : (F, R) bool, where each factor applies;
    rows : (R,) receiver vertex of each position; (gi, gj, gv) the sparse Gaunt entries of order n sorted by
    their k, ``starts`` (n2 + 1,) where each k's entries start. Parallel over blocks of ``VISIBILITY_BLOCK``
    positions.
    """
    n_blocks = (vis.shape[0] + VISIBILITY_BLOCK - 1) // VISIBILITY_BLOCK
    for block in numba.prange(n_blocks):
        _visibility_product_block(vis, fields, which, masks, rows, gi, gj, gv, starts, block)


@numba.njit(cache=True, nogil=True)
def visibility_product_serial(vis, fields, which, masks, rows, gi, gj, gv, starts):
    """:func:`visibility_product_kernel` on one thread (no parallel region): the same blocks and arithmetic."""
    n_blocks = (vis.shape[0] + VISIBILITY_BLOCK - 1) // VISIBILITY_BLOCK
    for block in range(n_blocks):
        _visibility_product_block(vis, fields, which, masks, rows, gi, gj, gv, starts, block)


@numba.njit(cache=True, inline="always")
def _may_block_at(x, v, occluder_centre, radius_sum, reach, source_centre):
    """:func:`may_block_kernel`'s test of point ``v``."""
    cx, cy, cz = occluder_centre[0], occluder_centre[1], occluder_centre[2]
    sx, sy, sz = source_centre[0], source_centre[1], source_centre[2]
    px, py, pz = x[v, 0], x[v, 1], x[v, 2]
    dx, dy, dz = sx - px, sy - py, sz - pz
    ox, oy, oz = cx - px, cy - py, cz - pz
    t = (ox * dx + oy * dy + oz * dz) / max(dx * dx + dy * dy + dz * dz, 1e-300)
    t = min(max(t, 0.0), 1.0)
    gx, gy, gz = px + t * dx - cx, py + t * dy - cy, pz + t * dz - cz
    return (gx * gx + gy * gy + gz * gz <= radius_sum * radius_sum) and (ox * ox + oy * oy + oz * oz
                                                                         <= reach * reach)


@numba.njit(cache=True, parallel=True, nogil=True)
def may_block_kernel(x, occluder_centre, radius_sum, reach, source_centre, out):
    """``out[v]``: whether an occluder (bounding sphere about ``occluder_centre``, its field reaching ``reach``
    from it) may block a ray from ``x[v]`` to a source (centre ``source_centre``): the occluder's centre is
    within ``radius_sum`` (occluder radius + source radius) of the segment ``x[v] -> source_centre`` and
    within ``reach`` of ``x[v]``. The specification is ``Interreflection._may_block`` (``method="reference"``).
    """
    for v in numba.prange(x.shape[0]):
        out[v] = _may_block_at(x, v, occluder_centre, radius_sum, reach, source_centre)


@numba.njit(cache=True, nogil=True)
def may_block_serial(x, occluder_centre, radius_sum, reach, source_centre, out):
    """:func:`may_block_kernel` on one thread (no parallel region)."""
    for v in range(x.shape[0]):
        out[v] = _may_block_at(x, v, occluder_centre, radius_sum, reach, source_centre)


#: Origins a task of :func:`source_hits_kernel` takes: ray ``j`` of each fills a packet's lanes (parallel rays
#: from neighbouring points) before ray ``j + 1``.
SOURCE_HIT_POINTS = 16


def source_hit_tasks(n_points: int) -> int:
    """Tasks (ray slots) of one :func:`source_hits_kernel` call of ``n_points`` origins."""
    return -(-int(n_points) // SOURCE_HIT_POINTS)


@numba.njit(cache=True, parallel=True, nogil=True)
def source_hits_kernel(tracer, origins, dirs, centre, r2, lo, hi, tnear, triangle, uv):
    """Closest hits on a one-object caster of the rays from each of ``origins`` (P, 3) along each of ``dirs``
    (D, 3): ``triangle[p, j]`` the face hit (int32, -1 where the ray misses it or fails ``may_hit``'s test of the
    sphere ``(centre, r2)`` and box ``[lo, hi]``, then not cast) and ``uv[p, j]`` its float32 barycentrics.
    Rays are staged as ``RayCaster.closest_hit`` stages them (no normals, ``tmax`` inf) and traced through
    ``tracer`` (``_raycast._Tracer``: one ray at a time, or 16 at a time). A task (its slot; ``tracer`` holds at
    least :func:`source_hit_tasks` of them) takes :data:`SOURCE_HIT_POINTS` consecutive origins and casts ray
    ``j`` of each after ray ``j - 1`` of all, a packet traced when its 16 lanes are filled: the hits of each ray
    do not depend on the grouping."""
    n_points, n_dirs = origins.shape[0], dirs.shape[0]
    w = _embree.PACKET
    group = SOURCE_HIT_POINTS
    n_tasks = (n_points + group - 1) // group
    counter = np.zeros(1, dtype=np.int64)
    for _ in numba.prange(tracer.threads):
        lane_point = np.empty(w, np.int64)
        lane_dir = np.empty(w, np.int64)
        origin = np.zeros((7, group))  # rows: the origin, centre - origin, its squared length
        may_hit = np.empty(group, np.bool_)
        while True:
            block = _embree.fetch_add(counter, 1)
            if block >= n_tasks:
                break
            f32, u32 = tracer.slot_f32[block], tracer.slot_u32[block]
            valid = tracer.valid[block]
            first = block * group
            n_group = min(group, n_points - first)
            _stage_group(origins, first, n_group, centre, origin, triangle)
            n_lanes = 0
            for j in range(n_dirs + 1):
                if j < n_dirs:
                    dx, dy, dz = dirs[j, 0], dirs[j, 1], dirs[j, 2]
                    length = np.sqrt(dx * dx + dy * dy + dz * dz)
                    ux, uy, uz = dx / length, dy / length, dz / length
                    _may_hit_group(origin, n_group, r2, dx, dy, dz, lo, hi, may_hit)
                    for k in range(n_group):
                        if not may_hit[k]:
                            continue
                        p = first + k
                        ox, oy, oz = origin[0, k], origin[1, k], origin[2, k]
                        if not tracer.packet:
                            _embree.set_ray(f32, u32, ox + tnear * ux, oy + tnear * uy, oz + tnear * uz, ux, uy, uz,
                                            np.inf)
                            _embree.rtc_call(tracer.function, tracer.scene, f32.ctypes.data)
                            if u32[_embree.HIT_GEOM] != _embree.INVALID_ID:
                                triangle[p, j] = np.int32(u32[_embree.HIT_PRIM])
                                uv[p, j, 0] = f32[_embree.HIT_U]
                                uv[p, j, 1] = f32[_embree.HIT_V]
                            continue
                        _embree.set_packet_ray(f32, u32, n_lanes, ox + tnear * ux, oy + tnear * uy, oz + tnear * uz,
                                               ux, uy, uz, np.inf)
                        valid[n_lanes] = -1
                        lane_point[n_lanes] = p
                        lane_dir[n_lanes] = j
                        n_lanes += 1
                        if n_lanes == w:
                            _source_hits_packet(tracer, f32, u32, valid, n_lanes, lane_point, lane_dir, triangle, uv)
                            n_lanes = 0
                elif n_lanes > 0:
                    _source_hits_packet(tracer, f32, u32, valid, n_lanes, lane_point, lane_dir, triangle, uv)


@numba.njit(cache=True, inline="always")
def _stage_group(origins, first, n_group, centre, origin, triangle):
    """``origin``'s rows for the ``n_group`` origins from ``first`` (the origins, ``centre`` minus them, its squared
    length: what :func:`_may_hit_group` reads), and their rows of ``triangle`` set to -1 (no hit yet)."""
    for k in range(n_group):
        ox, oy, oz = origins[first + k, 0], origins[first + k, 1], origins[first + k, 2]
        cx, cy, cz = centre[0] - ox, centre[1] - oy, centre[2] - oz
        origin[0, k], origin[1, k], origin[2, k] = ox, oy, oz
        origin[3, k], origin[4, k], origin[5, k] = cx, cy, cz
        origin[6, k] = cx * cx + cy * cy + cz * cz
        triangle[first + k, :] = -1


@numba.njit(cache=True, error_model="numpy")
def _may_hit_group(origin, n_group, r2, dx, dy, dz, lo, hi, may_hit):
    """``may_hit[k]``: ``_raycast.may_hit_ray`` of the ray along ``d`` from each of the first ``n_group`` origins
    (``origin``'s rows: the origins, ``centre`` minus them, its squared length), its arithmetic without its
    branches (the box always tested), so that the origins are tested side by side: the same tests."""
    lx, ly, lz, hx, hy, hz = lo[0], lo[1], lo[2], hi[0], hi[1], hi[2]
    for k in range(n_group):
        ox, oy, oz = origin[0, k], origin[1, k], origin[2, k]
        dist2 = origin[6, k]
        along = origin[3, k] * dx + origin[4, k] * dy + origin[5, k] * dz
        ok = (dist2 <= r2) | ((along > 0.0) & (dist2 - along * along <= r2))
        enter, leave = 0.0, np.inf
        if dx == 0.0:
            ok &= not ((ox < lx) | (ox > hx))
        else:
            t1, t2 = (lx - ox) / dx, (hx - ox) / dx
            enter, leave = max(enter, min(t1, t2)), min(leave, max(t1, t2))
        if dy == 0.0:
            ok &= not ((oy < ly) | (oy > hy))
        else:
            t1, t2 = (ly - oy) / dy, (hy - oy) / dy
            enter, leave = max(enter, min(t1, t2)), min(leave, max(t1, t2))
        if dz == 0.0:
            ok &= not ((oz < lz) | (oz > hz))
        else:
            t1, t2 = (lz - oz) / dz, (hz - oz) / dz
            enter, leave = max(enter, min(t1, t2)), min(leave, max(t1, t2))
        may_hit[k] = ok & (enter <= leave)


@numba.njit(cache=True, inline="always")
def _source_hits_packet(tracer, f32, u32, valid, n_lanes, lane_point, lane_dir, triangle, uv):
    """Trace the first ``n_lanes`` lanes of a packet and write each lane's hit at its ``(point, direction)``."""
    w = _embree.PACKET
    for k in range(n_lanes, w):
        valid[k] = 0
    _embree.rtc_call_packet(tracer.function, valid.ctypes.data, tracer.scene, f32.ctypes.data)
    for k in range(n_lanes):
        if u32[_embree.HIT_GEOM * w + k] != _embree.INVALID_ID:
            p, j = lane_point[k], lane_dir[k]
            triangle[p, j] = np.int32(u32[_embree.HIT_PRIM * w + k])
            uv[p, j, 0] = f32[_embree.HIT_U * w + k]
            uv[p, j, 1] = f32[_embree.HIT_V * w + k]


#: Bound of Embree's float32 error in a hit's position on a plane, relative to the largest magnitude in its
#: arithmetic (origin, distance, vertices) over the cosine of the ray with the plane: 64 float32 roundings.
FLAT_ROUNDING = 2.0 ** -18


@numba.njit(cache=True, parallel=True, nogil=True)
def flat_source_hits_kernel(plane, tracer, origins, dirs, centre, r2, lo, hi, tnear, triangle, uv):
    """:func:`source_hits_kernel`'s front hits on a flat source, located on its plane, traced only where that
    cannot tell. Returns the number of rays traced.

    Each ray passing the same ``may_hit`` test is staged as there (unit direction ``u``, origin ``o + tnear u``)
    and met with the plane; the face whose float64 barycentrics at that point all exceed ``eps`` (the hit
    position's bound ``FLAT_ROUNDING (|o|_inf + t + extent) / |cos|`` over the least face height) is the face
    Embree hits, its float32 barycentrics those within ``eps`` of Embree's. ``triangle[p, j]``: that face where
    the ray certainly hits the front (every vertex normal, within ``plane.spread`` of ``plane.shading``, faces
    the ray's origin); -1 where it certainly adds no term (a miss, a back face, behind the origin, outside the
    mesh). A ray this cannot tell (within ``eps`` of an edge, a hole, a grazing ray, an origin on the plane) is
    traced through ``tracer`` (``_raycast._Tracer``, one ray at a time, a slot per task of
    :data:`SOURCE_HIT_POINTS` origins): :func:`source_hits_kernel`'s bits. ``plane``:
    :class:`prtlab.interreflection._fields.FlatSource`; faces must not overlap.
    """
    n_points, n_dirs = origins.shape[0], dirs.shape[0]
    group = SOURCE_HIT_POINTS
    nx, ny, nz = plane.normal[0], plane.normal[1], plane.normal[2]
    ax, ay, az = plane.origin[0], plane.origin[1], plane.origin[2]
    sx, sy, sz = plane.shading[0], plane.shading[1], plane.shading[2]
    e1x, e1y, e1z = plane.axes[0, 0], plane.axes[0, 1], plane.axes[0, 2]
    e2x, e2y, e2z = plane.axes[1, 0], plane.axes[1, 1], plane.axes[1, 2]
    low_s, low_r, high_s, high_r = plane.low[0], plane.low[1], plane.high[0], plane.high[1]
    inv_s, inv_r, cells = plane.inv_cell[0], plane.inv_cell[1], plane.cells
    faces, affine = plane.cell_faces, plane.cell_affine
    slots = faces.shape[1]
    tilt, extent, inv_height = plane.spread + 1e-12, plane.extent, plane.inv_height
    n_tasks = (n_points + group - 1) // group
    traced = np.zeros(n_tasks, np.int64)
    for task in numba.prange(n_tasks):
        f32, u32 = tracer.slot_f32[task], tracer.slot_u32[task]
        origin = np.zeros((7, group))
        may_hit = np.empty(group, np.bool_)
        first = task * group
        n_group = min(group, n_points - first)
        n_traced = 0
        _stage_group(origins, first, n_group, centre, origin, triangle)
        for j in range(n_dirs):
            dx, dy, dz = dirs[j, 0], dirs[j, 1], dirs[j, 2]
            length = np.sqrt(dx * dx + dy * dy + dz * dz)
            ux, uy, uz = dx / length, dy / length, dz / length
            _may_hit_group(origin, n_group, r2, dx, dy, dz, lo, hi, may_hit)
            facing = sx * ux + sy * uy + sz * uz
            cos = nx * ux + ny * uy + nz * uz
            if facing > tilt:
                continue  # a back face or no hit: no term
            unsure_side = facing >= -tilt or abs(cos) < 1e-9  # grazing
            inv_cos = 1.0 / cos if cos != 0.0 else 0.0
            rel = FLAT_ROUNDING * abs(inv_cos)
            for k in range(n_group):
                if not may_hit[k]:
                    continue
                p = first + k
                px, py, pz = origin[0, k] + tnear * ux, origin[1, k] + tnear * uy, origin[2, k] + tnear * uz
                located, cell, slot, s, r = False, 0, 0, 0.0, 0.0
                if not unsure_side:
                    t = -(nx * (px - ax) + ny * (py - ay) + nz * (pz - az)) * inv_cos
                    err = rel * (max(abs(px), abs(py), abs(pz)) + abs(t) + extent)
                    if t < -err:
                        continue  # the plane is behind the origin
                    hx, hy, hz = px + t * ux - ax, py + t * uy - ay, pz + t * uz - az
                    s = hx * e1x + hy * e1y + hz * e1z
                    r = hx * e2x + hy * e2y + hz * e2z
                    if s < low_s - err or s > high_s + err or r < low_r - err or r > high_r + err:
                        continue  # outside the mesh's bounds
                    ci = min(max(int(math.floor((s - low_s) * inv_s)), 0), cells - 1)
                    cj = min(max(int(math.floor((r - low_r) * inv_r)), 0), cells - 1)
                    eps = err * inv_height
                    cell = ci * cells + cj
                    inside = 0
                    for m in range(slots):  # every slot, no branch: at most one face holds the point (no overlaps)
                        b1 = affine[cell, 0, m] * s + affine[cell, 1, m] * r + affine[cell, 2, m]
                        b2 = affine[cell, 3, m] * s + affine[cell, 4, m] * r + affine[cell, 5, m]
                        within = min(1.0 - b1 - b2, b1, b2) >= eps
                        inside += within
                        slot += within * m
                    located = inside == 1 and t > err
                if located:
                    triangle[p, j] = faces[cell, slot]
                    uv[p, j, 0] = affine[cell, 0, slot] * s + affine[cell, 1, slot] * r + affine[cell, 2, slot]
                    uv[p, j, 1] = affine[cell, 3, slot] * s + affine[cell, 4, slot] * r + affine[cell, 5, slot]
                    continue
                _embree.set_ray(f32, u32, px, py, pz, ux, uy, uz, np.inf)  # as source_hits_kernel stages it
                _embree.rtc_call(tracer.function, tracer.scene, f32.ctypes.data)
                n_traced += 1
                if u32[_embree.HIT_GEOM] != _embree.INVALID_ID:
                    triangle[p, j] = np.int32(u32[_embree.HIT_PRIM])
                    uv[p, j, 0] = f32[_embree.HIT_U]
                    uv[p, j, 1] = f32[_embree.HIT_V]
        traced[task] = n_traced
    return traced.sum()


#: Front hits of one point gathered (their ``h_k Psi_i`` and direction) before they are added to its projection.
HIT_BLOCK = 64
#: Points a task of :func:`project_source_hits_kernel` takes (its scratch allocated once for them).
HIT_POINTS = 8


@numba.njit(cache=True)
def project_source_hits_reference(triangle, uv, faces, vertex_normals, basis_t, h, dirs, wy, out):
    """:func:`project_source_hits_kernel`'s specification, serial: each front hit's terms added straight into
    ``out`` in the order of ``j``, a term ``h_k Psi_i wy[j, c]`` skipped where ``h_k Psi_i`` is zero."""
    n_dirs = triangle.shape[1]
    n_b, n_k, n2 = basis_t.shape[1], h.shape[0], wy.shape[1]
    psi = np.empty(n_b)
    for p in range(triangle.shape[0]):
        for j in range(n_dirs):
            t = triangle[p, j]
            if t < 0:
                continue
            b1, b2 = np.float64(uv[p, j, 0]), np.float64(uv[p, j, 1])
            b0 = 1.0 - b1 - b2
            i0, i1, i2 = faces[t, 0], faces[t, 1], faces[t, 2]
            nx, ny, nz = barycentric_normal(vertex_normals, i0, i1, i2, b0, b1, b2)
            length = max(math.sqrt(nx * nx + ny * ny + nz * nz), 1e-300)
            nx, ny, nz = nx / length, ny / length, nz / length
            if not nx * dirs[j, 0] + ny * dirs[j, 1] + nz * dirs[j, 2] < 0.0:
                continue  # a back face: psi = 0, every term skipped as project_hits_kernel skips zeros
            for i in range(n_b):
                psi[i] = b0 * basis_t[i0, i] + b1 * basis_t[i1, i] + b2 * basis_t[i2, i]
            for k in range(n_k):
                for i in range(n_b):
                    v = h[k] * psi[i]
                    if v != 0.0:
                        m = k * n_b + i
                        for c in range(n2):
                            out[p, m, c] += v * wy[j, c]


@numba.njit(cache=True)
def _front_hit_values(triangle, uv, faces, vertex_normals, basis_t, h, dirs, p, rays, start, stop, value, hit):
    """The front hits among the rays ``rays[start:stop]`` of point ``p`` (each hits the source), in order:
    ``value[q, k N + i] = h_k Psi_i`` and ``hit[q]`` the ray of the ``q``-th. Returns their count and whether
    some ``h_k Psi_i`` is zero."""
    n_b, n_k = basis_t.shape[1], h.shape[0]
    n_hits = 0
    zero = False
    for r in range(start, stop):
        j = rays[r]
        t = triangle[p, j]
        b1, b2 = np.float64(uv[p, j, 0]), np.float64(uv[p, j, 1])
        b0 = 1.0 - b1 - b2
        i0, i1, i2 = faces[t, 0], faces[t, 1], faces[t, 2]
        nx, ny, nz = barycentric_normal(vertex_normals, i0, i1, i2, b0, b1, b2)
        length = max(math.sqrt(nx * nx + ny * ny + nz * nz), 1e-300)
        nx, ny, nz = nx / length, ny / length, nz / length
        if not nx * dirs[j, 0] + ny * dirs[j, 1] + nz * dirs[j, 2] < 0.0:
            continue  # a back face
        for k in range(n_k):
            hk = h[k]
            for i in range(n_b):
                v = hk * (b0 * basis_t[i0, i] + b1 * basis_t[i1, i] + b2 * basis_t[i2, i])
                value[n_hits, k * n_b + i] = v
                zero |= v == 0.0
        hit[n_hits] = j
        n_hits += 1
    return n_hits, zero


@numba.njit(cache=True)
def _add_hits(value, hit, n_hits, wy, acc):
    """``acc[m n2 + c] += value[q, m] wy[hit[q], c]`` for ``q < n_hits`` in order, zero ``value`` skipped."""
    n2 = wy.shape[1]
    for m in range(value.shape[1]):
        for q in range(n_hits):
            v = value[q, m]
            if v != 0.0:
                j = hit[q]
                for c in range(n2):
                    acc[m * n2 + c] += v * wy[j, c]


@numba.njit(cache=True, inline="always")
def _madd4(a0, a1, a2, a3, v0, v1, v2, v3, w):
    """``a_r + v_r w`` for four rows."""
    return a0 + v0 * w, a1 + v1 * w, a2 + v2 * w, a3 + v3 * w


@numba.njit(cache=True)
def _add_hits16(value, hit, n_hits, wy, acc):
    """:func:`_add_hits` for ``n2 = 16`` and no zero ``value``: tiles of 4 hits x 4 rows x 16 coefficients, each
    entry's terms still added one at a time in the order of ``q``."""
    n_m = value.shape[1]
    q = 0
    while q + 4 <= n_hits:
        j0, j1, j2, j3 = hit[q], hit[q + 1], hit[q + 2], hit[q + 3]
        m = 0
        while m + 4 <= n_m:
            v00, v01, v02, v03 = value[q, m], value[q, m + 1], value[q, m + 2], value[q, m + 3]
            v10, v11, v12, v13 = value[q + 1, m], value[q + 1, m + 1], value[q + 1, m + 2], value[q + 1, m + 3]
            v20, v21, v22, v23 = value[q + 2, m], value[q + 2, m + 1], value[q + 2, m + 2], value[q + 2, m + 3]
            v30, v31, v32, v33 = value[q + 3, m], value[q + 3, m + 1], value[q + 3, m + 2], value[q + 3, m + 3]
            for c in range(16):
                a0, a1, a2, a3 = acc[m * 16 + c], acc[m * 16 + 16 + c], acc[m * 16 + 32 + c], acc[m * 16 + 48 + c]
                a0, a1, a2, a3 = _madd4(a0, a1, a2, a3, v00, v01, v02, v03, wy[j0, c])
                a0, a1, a2, a3 = _madd4(a0, a1, a2, a3, v10, v11, v12, v13, wy[j1, c])
                a0, a1, a2, a3 = _madd4(a0, a1, a2, a3, v20, v21, v22, v23, wy[j2, c])
                a0, a1, a2, a3 = _madd4(a0, a1, a2, a3, v30, v31, v32, v33, wy[j3, c])
                acc[m * 16 + c], acc[m * 16 + 16 + c], acc[m * 16 + 32 + c], acc[m * 16 + 48 + c] = a0, a1, a2, a3
            m += 4
        while m < n_m:
            v0, v1, v2, v3 = value[q, m], value[q + 1, m], value[q + 2, m], value[q + 3, m]
            for c in range(16):
                acc[m * 16 + c] = acc[m * 16 + c] + v0 * wy[j0, c] + v1 * wy[j1, c] + v2 * wy[j2, c] + v3 * wy[j3, c]
            m += 1
        q += 4
    while q < n_hits:
        j = hit[q]
        for m in range(n_m):
            v = value[q, m]
            for c in range(16):
                acc[m * 16 + c] += v * wy[j, c]
        q += 1


@numba.njit(cache=True, parallel=True, nogil=True)
def project_source_hits_kernel(triangle, uv, faces, vertex_normals, basis_t, h, dirs, wy, out):
    """:func:`hit_basis_kernel` then :func:`project_hits_kernel` in one pass over :func:`source_hits_kernel`'s
    output, for a source whose ``h_k`` is a constant ``h`` (K,): ``out[p, k N + i, c] += h_k Psi_i(hit) wy[j, c]``
    over the rays ``j`` of point ``p`` that hit (``triangle[p, j] >= 0``) the front of the source, in the order of
    ``j``; the same arithmetic, term for term, as the two kernels over ``np.nonzero(triangle >= 0)`` and as
    :func:`project_source_hits_reference`, bit for bit whatever ``out`` holds on entry.

    triangle : (P, D) int32 face hit or -1; uv : (P, D, 2) float32 barycentrics; faces : (F, 3) int64
    vertex_normals : (V, 3); basis_t : (V, N) ``Psi_i`` at the vertices, a vertex's values contiguous (the
    transpose of ``hit_basis_kernel``'s ``basis``); dirs : (D, 3) ray directions; wy : (D, n2); out : (P, K N, n2)

    A point's row of ``out`` is summed in a scratch copy of it, :data:`HIT_BLOCK` front hits at a time (their
    ``h_k Psi_i`` first, then their terms; for ``n2 = 16`` in register tiles), and written back once. Tiles add
    every term, so a block with a zero ``h_k Psi_i`` takes the loop that skips it (adding its signed zero would
    turn a ``-0.0`` in ``out`` into ``+0.0``).
    """
    n_points, n_dirs = triangle.shape
    n_b, n_k, n2 = basis_t.shape[1], h.shape[0], wy.shape[1]
    n_m = n_k * n_b
    for chunk in numba.prange((n_points + HIT_POINTS - 1) // HIT_POINTS):
        rays = np.empty(n_dirs, np.int64)
        value = np.empty((HIT_BLOCK, n_m))
        hit = np.empty(HIT_BLOCK, np.int64)
        acc = np.empty(n_m * n2)
        for p in range(chunk * HIT_POINTS, min(n_points, (chunk + 1) * HIT_POINTS)):
            n_rays = 0
            for j in range(n_dirs):  # the rays that hit, without a branch
                rays[n_rays] = j
                n_rays += triangle[p, j] >= 0
            if n_rays == 0:
                continue
            for m in range(n_m):
                for c in range(n2):
                    acc[m * n2 + c] = out[p, m, c]
            for start in range(0, n_rays, HIT_BLOCK):
                n_hits, zero = _front_hit_values(triangle, uv, faces, vertex_normals, basis_t, h, dirs, p, rays,
                                                 start, min(n_rays, start + HIT_BLOCK), value, hit)
                if n2 == 16 and not zero:
                    _add_hits16(value, hit, n_hits, wy, acc)
                else:
                    _add_hits(value, hit, n_hits, wy, acc)
            for m in range(n_m):
                for c in range(n2):
                    out[p, m, c] = acc[m * n2 + c]


@numba.njit(cache=True, nogil=True)
def near_decided_kernel(mask, lit, corners, out):
    """``out[q]`` (int8): the code its triangle's three vertices ``corners[q]`` agree on, a vertex's code being 1
    where no sample of its shadow ``mask`` row is set and some entry of its ``lit`` row is non-zero, 2 where every
    sample is set, else 0 (``Interreflection._near_decided``; the AND of the three codes)."""
    code = np.zeros(mask.shape[0], np.int8)
    for v in range(mask.shape[0]):
        blocked = 0
        for j in range(mask.shape[1]):
            blocked += mask[v, j]
        if blocked == mask.shape[1]:
            code[v] = 2
        elif blocked == 0:
            for k in range(lit.shape[1]):
                if lit[v, k] != 0.0:
                    code[v] = 1
                    break
    for q in range(corners.shape[0]):
        out[q] = code[corners[q, 0]] & code[corners[q, 1]] & code[corners[q, 2]]

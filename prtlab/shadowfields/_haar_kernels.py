"""Numba kernels of the all-frequency (Haar) shadow fields.

Kernels take only arrays and scalars and check nothing; the public functions in
``_haar.py`` / ``_haar_direct.py`` validate and coerce. Cubemap texels and Haar
coefficients are addressed by one flat index ``f r^2 + i r + j`` (face, row,
column; the layout of :func:`prtlab.wavelet.haar2d` for coefficients).
"""

from __future__ import annotations

import numba
import numpy as np

# --------------------------------------------------------------------------- Haar synthesis


@numba.njit(cache=True)
def haar_point_value(dense, texel, res):
    """Value at one texel of the cubemap whose Haar coefficients are ``dense`` (flat, ``6 r^2``).

    The basis functions of :func:`prtlab.wavelet.haar2d` in texel space: the scaling
    function is ``1 / r`` on the face; the wavelets of a node with blocks of ``m x m``
    texels are ``+-1 / m`` on it ("01" changes sign between column halves, "10"
    between row halves, "11" is their product).
    """
    rr = res * res
    f = texel // rr
    i = (texel // res) % res
    j = texel % res
    base = f * rr
    val = dense[base] / res
    h = 1
    while h < res:
        m = res // h
        p = i // m
        q = j // m
        half = m // 2
        sr = 1.0 if i - p * m < half else -1.0
        sc = 1.0 if j - q * m < half else -1.0
        d01 = dense[base + p * res + h + q]
        d10 = dense[base + (h + p) * res + q]
        d11 = dense[base + (h + p) * res + h + q]
        val += (sc * d01 + sr * d10 + sr * sc * d11) / m
        h *= 2
    return val


@numba.njit(cache=True)
def haar_synthesis(dense, res, out, work):
    """All texel values (flat ``6 r^2``) of the Haar coefficients ``dense``: the inverse of ``haar2d``.

    ``work`` is scratch of ``r^2``. Per level, the ``h x h`` scaling block ``S`` and the
    node's wavelets give the ``2h x 2h`` block ``a, b, c, d = (S +- d01 +- d10 +- d11) / 2``.
    """
    rr = res * res
    for f in range(6):
        base = f * rr
        out[base] = dense[base]
        h = 1
        while h < res:
            # current scaling (h x h) sits in out[base + p * res + q]; build 2h x 2h in work
            for p in range(h):
                for q in range(h):
                    s = out[base + p * res + q]
                    d01 = dense[base + p * res + h + q]
                    d10 = dense[base + (h + p) * res + q]
                    d11 = dense[base + (h + p) * res + h + q]
                    work[2 * p * res + 2 * q] = 0.5 * (s + d01 + d10 + d11)
                    work[2 * p * res + 2 * q + 1] = 0.5 * (s - d01 + d10 - d11)
                    work[(2 * p + 1) * res + 2 * q] = 0.5 * (s + d01 - d10 - d11)
                    work[(2 * p + 1) * res + 2 * q + 1] = 0.5 * (s - d01 - d10 + d11)
            for a in range(2 * h):
                for b in range(2 * h):
                    out[base + a * res + b] = work[a * res + b]
            h *= 2


# --------------------------------------------------------------------------- visibility pass


@numba.njit(cache=True, inline="always")
def blends_nothing(weights, v):
    """True when every blend weight ``weights[v, :]`` is zero (vertex ``v`` takes nothing from the field)."""
    for c in range(weights.shape[1]):
        if weights[v, c] != 0.0:
            return False
    return True


@numba.njit(cache=True, parallel=True)
def visibility_factor_kernel(tab_idx, tab_val, corners, weights, texel_map, query, count, res, n_blocks, vis):
    """Multiply one factor's visibility into ``vis`` at each vertex's query texels.

    tab_idx, tab_val : (P, keep) int32, float64 -- sparse Haar coefficients of the P samples, largest
        magnitude first (the loop over a sample's coefficients stops at its first zero)
    corners, weights : (V, 8) int64, float64 -- samples blended at each vertex (all weights 0: V = 1)
    texel_map : (6 r^2,) int64 -- world texel -> texel of the factor's own frame (rotation)
    query : (V, T) int64 world texels; count : (V,) int64 used entries; vis : (V, T) in/out

    Vertices are split into ``n_blocks`` blocks (a few per thread); each block reuses one dense coefficient
    buffer, cleared after each vertex at the entries it touched.
    """
    n = 6 * res * res
    keep = tab_idx.shape[1]
    n_v = corners.shape[0]
    for blk in numba.prange(n_blocks):
        dense = np.zeros(n)
        tex = np.empty(n)
        work = np.empty(res * res)
        for v in range(blk * n_v // n_blocks, (blk + 1) * n_v // n_blocks):
            if blends_nothing(weights, v):
                continue
            for c in range(8):
                w = weights[v, c]
                if w == 0.0:
                    continue
                p = corners[v, c]
                for k in range(keep):
                    if tab_val[p, k] == 0.0:  # stored largest first: the rest are unused slots
                        break
                    dense[tab_idx[p, k]] += w * tab_val[p, k]
            m = count[v]
            if 4 * m > n:
                haar_synthesis(dense, res, tex, work)
                for q in range(m):
                    vis[v, q] *= tex[texel_map[query[v, q]]]
            else:
                for q in range(m):
                    vis[v, q] *= haar_point_value(dense, texel_map[query[v, q]], res)
            for c in range(8):
                if weights[v, c] != 0.0:
                    p = corners[v, c]
                    for k in range(keep):
                        if tab_val[p, k] == 0.0:
                            break
                        dense[tab_idx[p, k]] = 0.0


# --------------------------------------------------------------------------- area-light rasterisation


@numba.njit(cache=True)
def _clip(poly, n, a, out):
    """Sutherland-Hodgman: the part of polygon ``poly[:n]`` (3D, rows) with ``a . x >= 0``; returns its size."""
    m = 0
    for k in range(n):
        x0 = poly[k]
        x1 = poly[(k + 1) % n]
        d0 = a[0] * x0[0] + a[1] * x0[1] + a[2] * x0[2]
        d1 = a[0] * x1[0] + a[1] * x1[1] + a[2] * x1[2]
        if d0 >= 0.0:
            out[m, 0], out[m, 1], out[m, 2] = x0[0], x0[1], x0[2]
            m += 1
        if (d0 >= 0.0) != (d1 >= 0.0):
            t = d0 / (d0 - d1)
            for c in range(3):
                out[m, c] = x0[c] + t * (x1[c] - x0[c])
            m += 1
    return m


@numba.njit(cache=True)
def _solid_angle_moment(poly, n, mom):
    """Solid angle of the convex spherical polygon spanned by ``poly[:n]`` (seen from the origin),
    and its moment ``int w dw`` written to ``mom`` (Lambert's edge formula ``1/2 sum theta_e u_e``)."""
    mom[0] = mom[1] = mom[2] = 0.0
    if n < 3:
        return 0.0
    omega = 0.0
    a = poly[0]
    la = np.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
    cen0 = cen1 = cen2 = 0.0
    for k in range(n):
        x0 = poly[k]
        x1 = poly[(k + 1) % n]
        l0 = np.sqrt(x0[0] * x0[0] + x0[1] * x0[1] + x0[2] * x0[2])
        l1 = np.sqrt(x1[0] * x1[0] + x1[1] * x1[1] + x1[2] * x1[2])
        if l0 == 0.0 or l1 == 0.0:
            continue
        cen0 += x0[0] / l0
        cen1 += x0[1] / l0
        cen2 += x0[2] / l0
        cx = x0[1] * x1[2] - x0[2] * x1[1]
        cy = x0[2] * x1[0] - x0[0] * x1[2]
        cz = x0[0] * x1[1] - x0[1] * x1[0]
        lc = np.sqrt(cx * cx + cy * cy + cz * cz)
        dot = x0[0] * x1[0] + x0[1] * x1[1] + x0[2] * x1[2]
        if lc > 0.0:
            theta = np.arctan2(lc, dot)
            mom[0] += 0.5 * theta * cx / lc
            mom[1] += 0.5 * theta * cy / lc
            mom[2] += 0.5 * theta * cz / lc
        if 1 <= k <= n - 2 and la > 0.0:
            b = x0
            c = x1
            trip = a[0] * (b[1] * c[2] - b[2] * c[1]) + a[1] * (b[2] * c[0] - b[0] * c[2]) + a[2] * (
                b[0] * c[1] - b[1] * c[0])
            ab = a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
            ac = a[0] * c[0] + a[1] * c[1] + a[2] * c[2]
            bc = b[0] * c[0] + b[1] * c[1] + b[2] * c[2]
            omega += 2.0 * np.arctan2(trip, la * l0 * l1 + ab * l1 + ac * l0 + bc * la)
    if mom[0] * cen0 + mom[1] * cen1 + mom[2] * cen2 < 0.0:
        mom[0], mom[1], mom[2] = -mom[0], -mom[1], -mom[2]
    return abs(omega)


@numba.njit(cache=True)
def _face_range(poly, n, axis, s_ax, t_ax, res):
    """Texel row/column range covered by a polygon already clipped to a face's pyramid."""
    j0, j1, i0, i1 = res, -1, res, -1
    for k in range(n):
        x = poly[k]
        depth = x[0] * axis[0] + x[1] * axis[1] + x[2] * axis[2]
        if depth <= 0.0:
            return 0, res - 1, 0, res - 1
        sc = (x[0] * s_ax[0] + x[1] * s_ax[1] + x[2] * s_ax[2]) / depth
        tc = (x[0] * t_ax[0] + x[1] * t_ax[1] + x[2] * t_ax[2]) / depth
        j = min(max(int(np.floor(0.5 * (sc + 1.0) * res)), 0), res - 1)
        i = min(max(int(np.floor(0.5 * (tc + 1.0) * res)), 0), res - 1)
        j0, j1, i0, i1 = min(j0, j), max(j1, j), min(i0, i), max(i1, i)
    return j0, j1, i0, i1


@numba.njit(cache=True)
def _light_polygon(point, normal, corners, light_normal, poly, tmp):
    """The light quad seen from ``point``, clipped to the upper hemisphere of ``normal``; returns its size."""
    side = 0.0
    for c in range(3):
        side += (point[c] - corners[0, c]) * light_normal[c]
    if side <= 0.0:
        return 0
    for k in range(4):
        for c in range(3):
            tmp[k, c] = corners[k, c] - point[c]
    return _clip(tmp, 4, normal, poly)


@numba.njit(cache=True)
def _clip_slab(poly, n, axis, dir_ax, lo, hi, out, buf, plane):
    """Clip to the slab ``lo <= (x . dir_ax) / (x . axis) <= hi`` of a face (two planes); result in ``out``."""
    for c in range(3):
        plane[c] = dir_ax[c] - lo * axis[c]
    m = _clip(poly, n, plane, buf)
    if m == 0:
        return 0
    for c in range(3):
        plane[c] = hi * axis[c] - dir_ax[c]
    return _clip(buf, m, plane, out)


@numba.njit(cache=True)
def _clip_to_cell(poly, n, axis, s_ax, t_ax, s0, s1, t0, t1, buf_a, buf_b, plane):
    """Clip to the pyramid of the face rectangle ``[s0, s1] x [t0, t1]``; result in ``buf_a`` (``plane``: scratch (3,))."""
    m = _clip_slab(poly, n, axis, s_ax, s0, s1, buf_b, buf_a, plane)
    if m == 0:
        return 0
    m = _clip_slab(buf_b, m, axis, t_ax, t0, t1, buf_b, buf_a, plane)
    for k in range(m):
        for c in range(3):
            buf_a[k, c] = buf_b[k, c]
    return m


@numba.njit(cache=True, parallel=True)
def area_light_count_kernel(points, normals, corners, light_normal, frames, res, count):
    """Upper bound of the texels an area light covers at each point (bounding texel ranges per face)."""
    for v in numba.prange(points.shape[0]):
        poly = np.empty((16, 3))
        tmp = np.empty((16, 3))
        buf = np.empty((16, 3))
        plane = np.empty(3)
        n = _light_polygon(points[v], normals[v], corners, light_normal, poly, tmp)
        total = 0
        if n > 0:
            for f in range(6):
                m = _clip_to_cell(poly, n, frames[f, 0], frames[f, 1], frames[f, 2], -1.0, 1.0, -1.0, 1.0, tmp, buf,
                                  plane)
                if m >= 3:
                    j0, j1, i0, i1 = _face_range(tmp, m, frames[f, 0], frames[f, 1], frames[f, 2], res)
                    total += (j1 - j0 + 3) * (i1 - i0 + 1)  # +2 columns: rows may round outward
        count[v] = total


@numba.njit(cache=True, inline="always")
def _cone_planes(poly, n, edge):
    """Inward normals ``edge[:n]`` of the faces of the cone from the origin over ``poly[:n]`` (planes
    through the origin and an edge)."""
    c0 = c1 = c2 = 0.0
    for e in range(n):
        c0 += poly[e, 0]
        c1 += poly[e, 1]
        c2 += poly[e, 2]
    orient = 0.0
    for e in range(n):
        a, b = poly[e], poly[(e + 1) % n]
        edge[e, 0] = a[1] * b[2] - a[2] * b[1]
        edge[e, 1] = a[2] * b[0] - a[0] * b[2]
        edge[e, 2] = a[0] * b[1] - a[1] * b[0]
        orient += edge[e, 0] * c0 + edge[e, 1] * c1 + edge[e, 2] * c2
    if orient < 0.0:
        for e in range(n):
            edge[e, 0], edge[e, 1], edge[e, 2] = -edge[e, 0], -edge[e, 1], -edge[e, 2]


@numba.njit(cache=True, inline="always")
def _texel_in_cone(axis, s_ax, t_ax, s0, s1, t0, t1, edge, n, corner):
    """True when the 4 corner directions of the face texel ``[s0, s1] x [t0, t1]`` are all inside the
    cone of :func:`_cone_planes` (``corner``: scratch (3,))."""
    for q in range(4):
        sc = s0 if q % 2 == 0 else s1
        tc = t0 if q < 2 else t1
        for c in range(3):
            corner[c] = axis[c] + sc * s_ax[c] + tc * t_ax[c]
        for e in range(n):
            if edge[e, 0] * corner[0] + edge[e, 1] * corner[1] + edge[e, 2] * corner[2] < 0.0:
                return False
    return True


@numba.njit(cache=True, parallel=True)
def area_light_pieces_kernel(points, normals, corners, light_normal, frames, res, texel_omega, texel_moment,
                             texel, omega, moment, count):
    """Exact partial coverage of the texels by an area light at each point.

    For every texel the light's quad (clipped to the point's upper hemisphere) meets,
    the piece ``texel pyramid x light``: its world texel, solid angle and moment
    ``int w dw`` (exact for a convex polygon). A texel whose 4 corner directions lie
    inside the light's cone is whole: its tabulated ``texel_omega`` (6 r^2,) and
    ``texel_moment`` (6 r^2, 3) are used without clipping. ``texel, omega, moment`` are
    ``(V, T_max)``, ``(V, T_max)``, ``(V, T_max, 3)``; ``count`` (V,) gets the pieces found.
    """
    rr = res * res
    for v in numba.prange(points.shape[0]):
        edge = np.empty((16, 3))
        corner = np.empty(3)
        poly = np.empty((16, 3))
        tmp = np.empty((16, 3))
        buf = np.empty((16, 3))
        cell = np.empty((16, 3))
        row = np.empty((16, 3))
        mom = np.empty(3)
        plane = np.empty(3)
        n = _light_polygon(points[v], normals[v], corners, light_normal, poly, tmp)
        k = 0
        if n > 0:
            _cone_planes(poly, n, edge)
            for f in range(6):
                axis, s_ax, t_ax = frames[f, 0], frames[f, 1], frames[f, 2]
                m = _clip_to_cell(poly, n, axis, s_ax, t_ax, -1.0, 1.0, -1.0, 1.0, tmp, buf, plane)
                if m < 3:
                    continue
                _, _, i0, i1 = _face_range(tmp, m, axis, s_ax, t_ax, res)
                for i in range(i0, i1 + 1):  # one row strip of the face, then its texels
                    t0 = 2.0 * i / res - 1.0
                    t1 = 2.0 * (i + 1) / res - 1.0
                    mr = _clip_slab(tmp, m, axis, t_ax, t0, t1, row, buf, plane)
                    if mr < 3:
                        continue
                    r0, r1, _, _ = _face_range(row, mr, axis, s_ax, t_ax, res)
                    for j in range(r0, r1 + 1):
                        s0 = 2.0 * j / res - 1.0
                        s1 = 2.0 * (j + 1) / res - 1.0
                        if _texel_in_cone(axis, s_ax, t_ax, s0, s1, t0, t1, edge, n, corner):
                            if k < texel.shape[1]:
                                t = f * rr + i * res + j
                                texel[v, k] = t
                                omega[v, k] = texel_omega[t]
                                for c in range(3):
                                    moment[v, k, c] = texel_moment[t, c]
                                k += 1
                            continue
                        mc = _clip_slab(row, mr, axis, s_ax, s0, s1, cell, buf, plane)
                        if mc < 3:
                            continue
                        om = _solid_angle_moment(cell, mc, mom)
                        if om <= 0.0 or k >= texel.shape[1]:  # (the count kernel's bound holds every piece)
                            continue
                        texel[v, k] = f * rr + i * res + j
                        omega[v, k] = om
                        moment[v, k, 0], moment[v, k, 1], moment[v, k, 2] = mom[0], mom[1], mom[2]
                        k += 1
        count[v] = k


# --------------------------------------------------------------------------- direct pass


@numba.njit(cache=True, parallel=True)
def direct_kernel(vis, g_weight, radiance, count, out):
    """``out[v, k, c] = sum_p vis[v, p] g_weight[v, p, k] radiance[v, p, c]`` over the first ``count[v]`` pieces."""
    n_k = g_weight.shape[2]
    n_c = radiance.shape[2]
    for v in numba.prange(vis.shape[0]):
        for k in range(n_k):
            for c in range(n_c):
                acc = 0.0
                for p in range(count[v]):
                    acc += vis[v, p] * g_weight[v, p, k] * radiance[v, p, c]
                out[v, k, c] += acc

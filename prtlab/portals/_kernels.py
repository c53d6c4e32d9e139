"""Numba kernels of the portals pipeline's per-frame passes (arrays and scalars only, no checks)."""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, parallel=True)
def indirect_pass_kernel(transfer, light_sh, out):
    """out[v, c] += sum_i transfer[v, i, c] * light_sh[i, c], c in 0..2 (float32 transfer, float64 sums)."""
    n_vertices, n_coeffs, n_channels = transfer.shape
    for v in numba.prange(n_vertices):
        a0 = a1 = a2 = 0.0
        for i in range(n_coeffs):  # memory order: (i, c) contiguous per vertex
            a0 += transfer[v, i, 0] * light_sh[i, 0]
            a1 += transfer[v, i, 1] * light_sh[i, 1]
            a2 += transfer[v, i, 2] * light_sh[i, 2]
        out[v, 0] += a0
        out[v, 1] += a1
        out[v, 2] += a2


@numba.njit(cache=True, nogil=True)
def shell_resample_kernel(image, taps, weights, out):
    """out[t, c] = sum_s weights[t, s] * image[taps[t, s], c]: equirect pixels to cubemap texel averages.

    Serial on purpose: ~1e6 multiply-adds per frame at res 64 (well under a millisecond), where a parallel region's
    start-up and a descheduled worker thread on a shared machine cost more. The three channels share each tap's
    load; the tap index is read as unsigned (no negative-index branch); sums in the order of the taps.
    """
    n_texels, n_taps = taps.shape
    for t in range(n_texels):
        a0 = 0.0
        a1 = 0.0
        a2 = 0.0
        for s in range(n_taps):
            w = weights[t, s]
            p = np.uint64(taps[t, s])
            a0 += w * image[p, 0]
            a1 += w * image[p, 1]
            a2 += w * image[p, 2]
        out[t, 0] = a0
        out[t, 1] = a1
        out[t, 2] = a2


@numba.njit(cache=True, inline="always")
def _signed_row_dot(indptr, indices, codes, sign_bit, light, row, offset):
    """``sum_e (+-codes[e]) light[offset + index(e), :3]`` over the entries of one sparse 8-bit row."""
    low = sign_bit - 1
    b0 = 0.0
    b1 = 0.0
    b2 = 0.0
    for e in range(indptr[row], indptr[row + 1]):
        raw = np.int64(indices[e])
        k = (raw & low) + offset
        w = np.float64(codes[e])
        if raw >= sign_bit:
            w = -w
        b0 += w * light[k, 0]
        b1 += w * light[k, 1]
        b2 += w * light[k, 2]
    return b0, b1, b2


@numba.njit(cache=True, parallel=True, fastmath=True, nogil=True)
def direct_pass_kernel(indptr, indices, codes, scale, basis, sign_bit, light, albedo, out):
    """Sparse 8-bit direct transfer times the shell light, times the albedo (3 channels).

    ``light (2 N, 3)``: rows ``0..N-1`` the shell texels (pulse coefficients), rows ``N..2N-1`` its Haar
    coefficients; ``basis[v]`` (0 pulse, 1 Haar) picks the half. ``indices`` carry the sign in ``sign_bit``::

        out[v, c] = albedo[v, c] * scale[v] / 255 * sum_e (+-codes[e]) light[basis[v] N + index(e), c]

    ``fastmath``: the sums may be reassociated (float64 roundoff; inputs are finite, checked by the callers).
    """
    n_vertices = indptr.shape[0] - 1
    n = light.shape[0] // 2
    for v in numba.prange(n_vertices):
        a0, a1, a2 = _signed_row_dot(indptr, indices, codes, sign_bit, light, v, n * np.int64(basis[v]))
        s = np.float64(scale[v]) / 255.0
        out[v, 0] = a0 * s * albedo[v, 0]
        out[v, 1] = a1 * s * albedo[v, 1]
        out[v, 2] = a2 * s * albedo[v, 2]


@numba.njit(cache=True, inline="always")
def _masked_term(codes, e, j, rest, f0, f1, f2, k):
    """Lane ``j`` of a run's masked tail: ``codes[e + j] f[:, k + j]`` if ``j < rest``, else exactly 0 (the code read
    and the light texel ``k + j`` must exist and be finite), branch-free."""
    w = np.float32(codes[e + j]) * np.float32(j < rest)
    return w * f0[k + j], w * f1[k + j], w * f2[k + j]


@numba.njit(cache=True, parallel=True, fastmath=True, nogil=True)
def direct_runs_kernel(indptr, run_ptr, run_start, run_len, indices, codes, scale, basis, sign_bit, light_t, lit,
                       light32_t, albedo, out, part):
    """:func:`direct_pass_kernel` with the pulse rows read as runs of consecutive texels, skipping the runs whose
    texels the shell light leaves black (exactly zero: the ground below the horizon); same sums, float64.

    ``run_ptr (V + 1)``: the runs of vertex ``v`` are ``run_ptr[v]:run_ptr[v + 1]``, run ``q`` covering texels
    ``run_start[q] .. run_start[q] + run_len[q] - 1`` and the vertex's next ``run_len[q]`` entries (pulse rows only;
    a Haar row has no runs and is read entry by entry). ``light_t (3, 2 N)`` channel-major float64; ``lit (N + 1,)``
    the running count of texels with a non-zero channel (``lit[k + m] == lit[k]``: texels ``k .. k + m - 1`` black);
    ``light32_t (3, N + 7)`` the texels in float32, then 7 zero (finite) columns for the masked lanes.

    Haar rows: entries in pairs into two sets of float64 sums; the index test (never true for a transfer of the
    light's resolution) ends the loop early, which keeps LLVM from vectorising it with gathers (0.83x of the
    gathers' time, one thread; the same in :func:`source_light_kernel`).

    A run of 8 entries or more goes 8 at a time through the vectorised loop and its last ``length mod 8`` as 7
    masked lanes into separate sums (runs average 11.7 entries at res 64: the vectorised loop's scalar remainder, one
    dependency chain through the row's sums, took a third of the pass); a shorter run (res 32 averages 4.4) in a
    plain loop into those sums.

    Pulse rows sum in float32 from ``light32_t`` (forward error at most ``(n + 2) eps_32`` times the row's sum of
    absolute terms, ``n`` its entries; measured 5e-7 of the 45k frame's largest value, against the 8-bit codes'
    ``1/510``); Haar rows (signed, cancelling terms) in float64.

    ``part``: 0 the pulse rows only, 1 the Haar rows only (the others' ``out`` rows left as they are; a pulse row
    reads no Haar coefficient of ``light_t``), 2 every row.
    """
    n_vertices = indptr.shape[0] - 1
    n = np.uint64(light_t.shape[1] // 2)
    n_codes = np.uint64(codes.shape[0])
    n_light = np.uint64(light_t.shape[1])
    one = np.uint64(1)
    seven = np.uint64(7)
    low = np.uint64(sign_bit - 1)
    sign = np.uint64(sign_bit)
    l0 = light_t[0]
    l1 = light_t[1]
    l2 = light_t[2]
    f0 = light32_t[0]
    f1 = light32_t[1]
    f2 = light32_t[2]
    for v in numba.prange(n_vertices):
        if part != 2 and basis[v] != part:
            continue
        a0 = 0.0
        a1 = 0.0
        a2 = 0.0
        # unsigned indices: numba adds a negative-index (wraparound) branch to every signed index, which kept the
        # inner loop from vectorising (the pass took 2.2x the time)
        if basis[v] == 0:
            b0 = np.float32(0.0)
            b1 = np.float32(0.0)
            b2 = np.float32(0.0)
            c0 = np.float32(0.0)  # the runs' last (length mod 8) entries, apart: no dependency chain through b
            c1 = np.float32(0.0)
            c2 = np.float32(0.0)
            e = np.uint64(indptr[v])
            for q in range(run_ptr[v], run_ptr[v + 1]):
                k0 = np.uint64(run_start[q])
                m = np.uint64(run_len[q])
                if lit[k0 + m] != lit[k0]:
                    m8 = m & ~seven
                    for t in range(m8):  # vectorised; the length a multiple of 8 leaves its scalar loop idle
                        w = np.float32(codes[e + t])
                        k = k0 + t
                        b0 += w * f0[k]
                        b1 += w * f1[k]
                        b2 += w * f2[k]
                    rest = m - m8
                    if m8 == 0:  # a short run: its entries in a plain loop (7 lanes would cost more)
                        for t in range(m):
                            w = np.float32(codes[e + t])
                            k = k0 + t
                            c0 += w * f0[k]
                            c1 += w * f1[k]
                            c2 += w * f2[k]
                    elif rest != 0:
                        e8 = e + m8
                        k8 = k0 + m8
                        if e8 + seven < n_codes:  # the last 1..7 entries as 7 masked lanes, no loop
                            p0, p1, p2 = _masked_term(codes, e8, np.uint64(0), rest, f0, f1, f2, k8)
                            q0, q1, q2 = _masked_term(codes, e8, np.uint64(1), rest, f0, f1, f2, k8)
                            r0, r1, r2 = _masked_term(codes, e8, np.uint64(2), rest, f0, f1, f2, k8)
                            s0, s1, s2 = _masked_term(codes, e8, np.uint64(3), rest, f0, f1, f2, k8)
                            t0, t1, t2 = _masked_term(codes, e8, np.uint64(4), rest, f0, f1, f2, k8)
                            u0, u1, u2 = _masked_term(codes, e8, np.uint64(5), rest, f0, f1, f2, k8)
                            v0, v1, v2 = _masked_term(codes, e8, np.uint64(6), rest, f0, f1, f2, k8)
                            c0 += (p0 + q0) + (r0 + s0) + ((t0 + u0) + v0)
                            c1 += (p1 + q1) + (r1 + s1) + ((t1 + u1) + v1)
                            c2 += (p2 + q2) + (r2 + s2) + ((t2 + u2) + v2)
                        else:  # the transfer's last entries: no lanes past its end
                            for t in range(rest):
                                w = np.float32(codes[e8 + t])
                                c0 += w * f0[k8 + t]
                                c1 += w * f1[k8 + t]
                                c2 += w * f2[k8 + t]
                e += m
            a0 = np.float64(b0 + c0)
            a1 = np.float64(b1 + c1)
            a2 = np.float64(b2 + c2)
        else:  # entries in pairs, two sets of sums; the index test ends the loop early: no gathers (as below)
            h0 = 0.0
            h1 = 0.0
            h2 = 0.0
            e = np.uint64(indptr[v])
            end = np.uint64(indptr[v + 1])
            while e + one < end:
                raw = np.uint64(indices[e])
                raw_b = np.uint64(indices[e + one])
                k = (raw & low) + n
                k_b = (raw_b & low) + n
                if k >= n_light or k_b >= n_light:
                    break
                w = np.float64(codes[e]) * (1.0 - 2.0 * np.float64(raw >= sign))
                w_b = np.float64(codes[e + one]) * (1.0 - 2.0 * np.float64(raw_b >= sign))
                a0 += w * l0[k]
                a1 += w * l1[k]
                a2 += w * l2[k]
                h0 += w_b * l0[k_b]
                h1 += w_b * l1[k_b]
                h2 += w_b * l2[k_b]
                e += np.uint64(2)
            if e < end:  # the row's last entry (odd count)
                raw = np.uint64(indices[e])
                k = (raw & low) + n
                w = np.float64(codes[e]) * (1.0 - 2.0 * np.float64(raw >= sign))
                a0 += w * l0[k]
                a1 += w * l1[k]
                a2 += w * l2[k]
            a0 += h0
            a1 += h1
            a2 += h2
        s = np.float64(scale[v]) / 255.0
        out[v, 0] = a0 * s * albedo[v, 0]
        out[v, 1] = a1 * s * albedo[v, 1]
        out[v, 2] = a2 * s * albedo[v, 2]


@numba.njit(cache=True, parallel=True)
def glossy_direct_pass_kernel(indptr, indices, codes, scale, basis, sign_bit, light, rows, weights, ks, out):
    """Specular direct radiance of glossy vertices: the sparse rows ``rows[v, q]`` (one per discretised
    outgoing direction) blended with ``weights[v, q]``, times ``ks[v]``; ``light`` as in :func:`direct_pass_kernel`."""
    n_vertices, n_rows = rows.shape
    n = light.shape[0] // 2
    for v in numba.prange(n_vertices):
        a0 = a1 = a2 = 0.0
        for q in range(n_rows):
            w_row = weights[v, q]
            if w_row == 0.0:
                continue
            row = rows[v, q]
            b0, b1, b2 = _signed_row_dot(indptr, indices, codes, sign_bit, light, row, n * np.int64(basis[row]))
            s = w_row * np.float64(scale[row]) / 255.0
            a0 += s * b0
            a1 += s * b1
            a2 += s * b2
        out[v, 0] = a0 * ks[v, 0]
        out[v, 1] = a1 * ks[v, 1]
        out[v, 2] = a2 * ks[v, 2]


@numba.njit(cache=True, parallel=True)
def glossy_lobe_kernel(indptr, indices, values, dirs, reflected, exponent, ks, light, out):
    """Specular direct radiance of glossy vertices by their Phong lobe at the shell texels they see:
    ``out[v] = ks[v] (e_v + 2) / 2 sum_p values[p] max(0, dirs[k_p] . reflected[v])^e_v light[k_p]`` over the
    row ``indptr[v]:indptr[v + 1]`` (texel ``k_p = indices[p]``), 3 channels."""
    for v in numba.prange(len(indptr) - 1):
        r0, r1, r2 = reflected[v, 0], reflected[v, 1], reflected[v, 2]
        e = exponent[v]
        a0 = a1 = a2 = 0.0
        for p in range(indptr[v], indptr[v + 1]):
            k = indices[p]
            c = dirs[k, 0] * r0 + dirs[k, 1] * r1 + dirs[k, 2] * r2
            if c <= 0.0:
                continue
            w = np.float64(values[p]) * c**e
            a0 += w * light[k, 0]
            a1 += w * light[k, 1]
            a2 += w * light[k, 2]
        norm = 0.5 * (e + 2.0)
        out[v, 0] = a0 * norm * ks[v, 0]
        out[v, 1] = a1 * norm * ks[v, 1]
        out[v, 2] = a2 * norm * ks[v, 2]


@numba.njit(cache=True, parallel=True)
def glossy_indirect_pass_kernel(matrix, light_sh, basis_out, out):
    """out[v, c] = sum_j basis_out[v, j] sum_i matrix[v, j, i, c] light_sh[i, c] (Appendix Eq. 6), 3 channels."""
    n_vertices, n_out, n_in, _ = matrix.shape
    for v in numba.prange(n_vertices):
        a0 = a1 = a2 = 0.0
        for j in range(n_out):
            y = basis_out[v, j]
            b0 = b1 = b2 = 0.0
            for i in range(n_in):
                b0 += matrix[v, j, i, 0] * light_sh[i, 0]
                b1 += matrix[v, j, i, 1] * light_sh[i, 1]
                b2 += matrix[v, j, i, 2] * light_sh[i, 2]
            a0 += y * b0
            a1 += y * b1
            a2 += y * b2
        out[v, 0] = a0
        out[v, 1] = a1
        out[v, 2] = a2


@numba.njit(cache=True, parallel=True, fastmath=True, nogil=True)
def source_light_kernel(indptr, columns, values, light, out):
    """``out[c, ch] = sum_e values[e, ch] light[columns[e], ch]`` over the CSR rows ``c`` (the patches' mean direct
    radiance from the shell light's pulse and Haar coefficients, :class:`prtlab.portals._surface.SourceOperator`).

    ``columns`` unsigned (uint32): a signed index costs a negative-index branch per entry. Entries in pairs into two
    sets of sums (two dependency chains); the column test (never true for an operator built for ``light``) ends the
    loop early, which keeps LLVM from vectorising it with gathers (0.79x of the gathers' time, one thread).
    ``fastmath``: the sums may be reassociated (float64 roundoff; inputs are finite)."""
    n_rows = indptr.shape[0] - 1
    n_columns = np.uint64(light.shape[0])
    one = np.uint64(1)
    for c in numba.prange(n_rows):
        a0 = a1 = a2 = 0.0
        b0 = b1 = b2 = 0.0
        e = np.uint64(indptr[c])
        end = np.uint64(indptr[c + 1])
        while e + one < end:
            k = np.uint64(columns[e])
            kb = np.uint64(columns[e + one])
            if k >= n_columns or kb >= n_columns:
                break
            a0 += values[e, 0] * light[k, 0]
            a1 += values[e, 1] * light[k, 1]
            a2 += values[e, 2] * light[k, 2]
            b0 += values[e + one, 0] * light[kb, 0]
            b1 += values[e + one, 1] * light[kb, 1]
            b2 += values[e + one, 2] * light[kb, 2]
            e += np.uint64(2)
        if e < end:  # the row's last entry (odd count)
            k = np.uint64(columns[e])
            a0 += values[e, 0] * light[k, 0]
            a1 += values[e, 1] * light[k, 1]
            a2 += values[e, 2] * light[k, 2]
        out[c, 0] = a0 + b0
        out[c, 1] = a1 + b1
        out[c, 2] = a2 + b2


@numba.njit(cache=True, parallel=True, fastmath=True, nogil=True)
def bounce_light_kernel(sums_t, source, out):
    """``out[ch, c] = sum_d sums_t[ch, c, d] float32(source[d, ch])`` in float32 (``S_B s``): channel-major sums
    ``(3, C, C)`` and out ``(3, C)``, one contiguous row ``(ch, c)`` per iteration (the sum over ``d`` vectorises)."""
    n_channels, n, _ = sums_t.shape
    source_t = np.empty((n_channels, n), dtype=np.float32)
    for ch in range(n_channels):
        for d in range(n):
            source_t[ch, d] = np.float32(source[d, ch])
    for r in numba.prange(n_channels * n):
        ch = r // n
        c = r - ch * n
        row = sums_t[ch, c]
        s = source_t[ch]
        acc = np.float32(0.0)
        for d in range(n):
            acc += row[d] * s[d]
        out[ch, c] = acc


@numba.njit(cache=True, nogil=True)
def light_layout_kernel(light, light_t, lit, light32_t):
    """The shell light's coefficients ``light (2 T, 3)`` in :func:`direct_runs_kernel`'s layouts: ``light_t (3, 2 T)``
    channel-major float64, ``lit (T + 1,)`` the running count of texels with a non-zero channel, ``light32_t (3, T +
    7)`` the texels in float32 and 7 zero columns. One serial pass (``6 T`` values)."""
    n2 = light.shape[0]
    n = n2 // 2
    lit[0] = 0
    for k in range(n2):
        x0 = light[k, 0]
        x1 = light[k, 1]
        x2 = light[k, 2]
        light_t[0, k] = x0
        light_t[1, k] = x1
        light_t[2, k] = x2
        if k < n:
            light32_t[0, k] = np.float32(x0)
            light32_t[1, k] = np.float32(x1)
            light32_t[2, k] = np.float32(x2)
            lit[k + 1] = lit[k] + (1 if (x0 != 0.0 or x1 != 0.0 or x2 != 0.0) else 0)
    for k in range(n, light32_t.shape[1]):
        light32_t[0, k] = 0.0
        light32_t[1, k] = 0.0
        light32_t[2, k] = 0.0


@numba.njit(cache=True, parallel=True, fastmath=True, nogil=True)
def gather_product_kernel(codes, scale, light_t, albedo, out, rows):
    """``out[i, ch] = albedo[v, ch] scale[v] sum_c codes[v, c] light_t[ch, c]`` for ``v = rows[i]`` (float32 sums
    over the 16-bit codes, channel-major ``light_t (3, C)`` so that the sum over ``c`` reads contiguous memory and
    vectorises; ``albedo`` and ``out`` have one row per entry of ``rows``)."""
    n = len(rows)
    m = codes.shape[1]
    u0 = light_t[0]
    u1 = light_t[1]
    u2 = light_t[2]
    for i in numba.prange(n):
        v = rows[i]
        a0 = np.float32(0.0)
        a1 = np.float32(0.0)
        a2 = np.float32(0.0)
        row = codes[v]
        for c in range(m):
            g = np.float32(row[c])
            a0 += g * u0[c]
            a1 += g * u1[c]
            a2 += g * u2[c]
        s = np.float64(scale[v])
        out[i, 0] = albedo[i, 0] * s * a0
        out[i, 1] = albedo[i, 1] * s * a1
        out[i, 2] = albedo[i, 2] * s * a2


@numba.njit(cache=True, nogil=True)
def near_point_kernel(indptr, indices, data, radiance, slot, partner_light, patch_read, albedo, out):
    """``out[i, ch] += albedo[i, ch] (sum_e data[e] point[indices[e], ch] - patch_read[i, ch])`` over the CSR rows
    ``i`` (the near rays' point reads, :meth:`prtlab.portals._surface.SurfaceTransfer.near_correction`), ``point[v]
    = radiance[v] + partner_light[slot[v]]`` where ``slot[v] >= 0``, else ``radiance[v]``.

    Serial (a few 1e4 entries). No ``fastmath``: each row sums its entries in order from 0 with separate multiplies
    and adds, as scipy's CSR product does, and the terms are those numpy forms, so the same bits (tested)."""
    n_rows = indptr.shape[0] - 1
    for i in range(n_rows):
        y0 = 0.0
        y1 = 0.0
        y2 = 0.0
        for e in range(indptr[i], indptr[i + 1]):
            j = indices[e]
            a = data[e]
            p0 = radiance[j, 0]
            p1 = radiance[j, 1]
            p2 = radiance[j, 2]
            s = slot[j]
            if s >= 0:
                p0 = p0 + partner_light[s, 0]
                p1 = p1 + partner_light[s, 1]
                p2 = p2 + partner_light[s, 2]
            y0 += a * p0
            y1 += a * p1
            y2 += a * p2
        out[i, 0] += albedo[i, 0] * (y0 - patch_read[i, 0])
        out[i, 1] += albedo[i, 1] * (y1 - patch_read[i, 1])
        out[i, 2] += albedo[i, 2] * (y2 - patch_read[i, 2])

"""The two run-time passes of Guerrero et al. 2008 (Secs. 5-7), as batched CPU loops.

First pass (:func:`first_pass`, Eqs. 3-11): diffuse reflection at every
surface sample point under the environment with visibility
``exp(sum of blocker logs)``, projection to each light's SH with the
Voronoi-cell sums, product with the surface-albedo SH.

Second pass (:func:`second_pass`, Eqs. 12-24): at every receiver, the direct
soft shadow (Eq. 8) and the indirect light of every spherical light,
``sum_i L~_i V~_i`` (Eq. 14) with the average radiance ``L~_i = w'_theta .
L^c_i`` (Eq. 18; ``w_theta`` rotated to the receiver direction in the
light's own frame, which is how rotations of lights are handled, Sec. 7.1)
and the average visibility ``V~_i = (exp(G_front) - exp(G_front + G_i)) .
rho_n`` (Eqs. 23-24), where ``G_front`` sums the logs of the blockers in
front of light ``i``:

* per-sphere blocking: every adjusted sphere closer to ``p`` than ``i``
  (centre distance), except the spheres of ``i``'s object that intersect
  ``i`` (their occlusion is precomputed in the samples, Sec. 6.2);
* per-object blocking (Sec. 7.2): all spheres of the objects closer to
  ``p`` (object-centre distance), plus the closer non-intersecting spheres
  of ``i``'s own object.

Every light is used with the per-receiver adjustment of
:func:`prtlab.spherelights.adjust_blockers`, as emitter and as blocker.

The blocker accumulation (the paper's dominant cost) is one numba kernel,
``_accumulate_blockers``, parallel over receivers, with a numpy reference
tier; the exponentials run in :func:`prtlab.sh.exp`'s batched kernels.
"""

from __future__ import annotations

import functools
import math

import numba
import numpy as np

from prtlab import sh
from prtlab.sh._explog import _HYB_THRESHOLD, _ol_table
from prtlab.sh._gaunt import _gaunt_block
from prtlab.sh._kernels import LOW_BANDS
from prtlab.sh._product_kernels import _ol_one, _tile_product

from ._shadows import (
    _add_rotated_zh,
    _add_rotated_zh_low,
    _adjust,
    _lookup_log,
    blocker_log_table,
    environment_transfer,
    transfer_matrix,
)
from ._tables import N_THETA_K, THETA_MAX_K, _irradiance_kernel_table, _w_theta_table, irradiance_kernel_zh, w_theta_zh

__all__ = ["first_pass", "second_pass", "accumulate_blockers", "emission_times_direction"]


@numba.njit(cache=True, parallel=True)
def _accumulate_blockers(points, normals, centres, radii, sl_object, obj_centres, intersect, table, order,
                         per_object, g_sphere, g_front, theta, axis):
    """Per receiver: rotated blocker logs g_sphere (B, S, n2), front sums g_front (B, S, n2),
    angular radii theta (B, S) (-1: culled) and unit directions p -> c' axis (B, S, 3)."""
    n_recv = points.shape[0]
    n_sph = centres.shape[0]
    n_obj = obj_centres.shape[0]
    n2 = order * order
    for b in numba.prange(n_recv):
        ybuf = np.empty((1, n2))
        g = np.empty(order)
        dist = np.empty(n_sph)
        px, py, pz = points[b, 0], points[b, 1], points[b, 2]
        nx, ny, nz = normals[b, 0], normals[b, 1], normals[b, 2]
        for s in range(n_sph):
            for k in range(n2):
                g_sphere[b, s, k] = 0.0
                g_front[b, s, k] = 0.0
            cx, cy, cz, r = _adjust(px, py, pz, nx, ny, nz, centres[s, 0], centres[s, 1], centres[s, 2], radii[s])
            dx, dy, dz = cx - px, cy - py, cz - pz
            d = math.sqrt(dx * dx + dy * dy + dz * dz)
            dist[s] = d
            if r <= 0.0 or d <= 0.0:
                theta[b, s] = -1.0
                axis[b, s, 0] = 0.0
                axis[b, s, 1] = 0.0
                axis[b, s, 2] = 0.0
                continue
            sin_t = r / d
            th = 0.5 * math.pi if sin_t >= 1.0 else math.asin(sin_t)
            theta[b, s] = th
            axis[b, s, 0] = dx / d
            axis[b, s, 1] = dy / d
            axis[b, s, 2] = dz / d
            _lookup_log(th, table, order, g)
            _add_rotated_zh(g, dx / d, dy / d, dz / d, order, ybuf, 1.0, g_sphere[b, s])
        if per_object:
            od = np.empty(n_obj)
            for o in range(n_obj):
                ex = obj_centres[o, 0] - px
                ey = obj_centres[o, 1] - py
                ez = obj_centres[o, 2] - pz
                od[o] = ex * ex + ey * ey + ez * ez
            acc = np.zeros(n2)
            for o in np.argsort(od):
                for i in range(n_sph):
                    if sl_object[i] != o:
                        continue
                    for k in range(n2):
                        g_front[b, i, k] = acc[k]
                    for j in range(n_sph):
                        if j != i and sl_object[j] == o and dist[j] < dist[i] and not intersect[i, j]:
                            for k in range(n2):
                                g_front[b, i, k] += g_sphere[b, j, k]
                for j in range(n_sph):
                    if sl_object[j] == o:
                        for k in range(n2):
                            acc[k] += g_sphere[b, j, k]
        else:
            for i in range(n_sph):
                for j in range(n_sph):
                    if j != i and dist[j] < dist[i] and not intersect[i, j]:
                        for k in range(n2):
                            g_front[b, i, k] += g_sphere[b, j, k]


def _accumulate_reference(points, normals, centres, radii, sl_object, obj_centres, intersect, order, per_object):
    """numpy specification of ``_accumulate_blockers``."""
    from ._shadows import adjust_blockers

    n_recv, n_sph = points.shape[0], centres.shape[0]
    ca, ra = adjust_blockers(points, normals, centres, radii)
    d = ca - points[:, None, :]
    dist = np.linalg.norm(d, axis=-1)
    live = (ra > 0) & (dist > 0)
    theta = np.where(live, np.arcsin(np.minimum(np.where(live, ra / np.where(dist > 0, dist, 1), 0), 1.0)), -1.0)
    axis = np.where(live[..., None], d / np.where(dist > 0, dist, 1.0)[..., None], 0.0)
    g_sphere = np.zeros((n_recv, n_sph, order * order))
    if live.any():
        g = sh.blocker_log_zh(theta[live], order)
        g_sphere[live] = sh.zh_rotate(g, axis[live], method="reference")
    g_front = np.zeros_like(g_sphere)
    for b in range(n_recv):
        if per_object:
            od = np.sum((obj_centres - points[b]) ** 2, axis=1)
            acc = np.zeros(order * order)
            for o in np.argsort(od, kind="stable"):
                members = np.nonzero(sl_object == o)[0]
                for i in members:
                    mask = (sl_object == o) & (dist[b] < dist[b, i]) & ~intersect[i]
                    mask[i] = False
                    g_front[b, i] = acc + g_sphere[b, mask].sum(axis=0)
                acc = acc + g_sphere[b, members].sum(axis=0)
        else:
            for i in range(n_sph):
                mask = (dist[b] < dist[b, i]) & ~intersect[i]
                mask[i] = False
                g_front[b, i] = g_sphere[b, mask].sum(axis=0)
    return g_sphere, g_front, theta, axis


def accumulate_blockers(points, normals, centres, radii, sl_object, intersect, order: int, *,
                        blocking: str = "object", method: str = "numba"):
    """Blocker logs of every light at every receiver and the sums in front of each (Eqs. 21-23, Sec. 7.2).

    Parameters
    ----------
    points, normals : (B, 3) float
    centres : (S, 3) float
    radii : (S,) float
        Spherical lights in world space.
    sl_object : (S,) int
        Object of each light (``0..O-1``).
    intersect : (S, S) bool
        Lights whose occlusion is precomputed (same object, intersecting).
    order : int
    blocking : {"object", "sphere"}
    method : {"numba", "reference"}

    Returns
    -------
    g_sphere : (B, S, n*n) float64
        Rotated log of each adjusted light (0 where culled).
    g_front : (B, S, n*n) float64
        Sum of the logs in front of each light.
    theta : (B, S) float64
        Angular radius of each adjusted light (-1 where culled).
    axis : (B, S, 3) float64
        Unit direction from the receiver to the adjusted centre.

    References
    ----------
    Guerrero et al. 2008, Eqs. 20-23 and Sec. 7.2; Ren et al. 2006.
    """
    if blocking not in ("object", "sphere"):
        raise ValueError(f"blocking must be 'object' or 'sphere', got {blocking!r}")
    if method not in ("numba", "reference"):
        raise ValueError(f"method must be 'numba' or 'reference', got {method!r}")
    p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    n = np.ascontiguousarray(n / np.linalg.norm(n, axis=1, keepdims=True))
    c, r, obj, inter, obj_centres = _light_arrays(centres, radii, sl_object, intersect)
    if method == "reference":
        return _accumulate_reference(p, n, c, r, obj, obj_centres, inter, order, blocking == "object")
    B, S, n2 = p.shape[0], c.shape[0], order * order
    g_sphere = np.empty((B, S, n2))
    g_front = np.empty((B, S, n2))
    theta = np.empty((B, S))
    axis = np.empty((B, S, 3))
    if B and S:
        _accumulate_blockers(p, n, c, r, obj, obj_centres, inter, blocker_log_table(order), order,
                             blocking == "object", g_sphere, g_front, theta, axis)
    return g_sphere, g_front, theta, axis


#: Sample counts below which :func:`first_pass` runs its parallel kernels on one thread. Its kernels
#: are small (S * 92 samples, a few ms of work); on a loaded machine every parallel region waits for a
#: descheduled worker (a scheduler time slice), measured at the squirrel scale (1288 samples, load ~4 on
#: 2 cores): 10 ms on one thread against 37 ms on two.
_SERIAL_BELOW = 8192


def first_pass(sample_points, sample_normals, sample_valid, centres, radii, env_sh, cell_sums, albedo_sh, *,
               exp_method: str = "hyb", ground=None, extra_irradiance=None) -> np.ndarray:
    """Light intensity distributions of the spherical lights (Eqs. 3-11).

    Parameters
    ----------
    sample_points, sample_normals : (S, m, 3) float
        Surface sample points of each light, world space.
    sample_valid : (S, m) bool
    centres : (S_all, 3) float
    radii : (S_all,) float
        Every light of the scene as a blocker (world space).
    env_sh : (N*N, 3) float
        Environment radiance of any order ``N >= n`` (``3n - 2``: the exact
        transfer, see :func:`prtlab.spherelights.environment_transfer`).
    cell_sums : (m, n*n) float
        Voronoi-cell sums ``(4 pi / N) Y_j`` (:func:`voronoi_cell_sums`), in the light's own frame.
    albedo_sh : (S, n*n, 3) float
        Surface-albedo SH of each light, own frame.
    exp_method : {"hyb", "ol", "exact"}
    ground : (G, 7) float, optional
        Ground rectangles (:func:`prtlab.spherelights.ground_rectangles`) that hide
        the environment from the samples (an extension; see ``_ground``).
    extra_irradiance : (S, m, 3) float, optional
        Irradiance at the samples from other sources, added to the environment's
        (the local lights of Sec. 7.3, computed by :func:`second_pass` at the samples).

    Returns
    -------
    emission : (S, n*n, 3) float64
        ``L^c_S = (sum_j L_{p_j} (4 pi / N) Y_j) * c_S`` (Eqs. 10-11) with
        ``L_p = E_p / pi`` the exit radiance of a white Lambertian surface
        (Eq. 8; the albedo enters through ``c_S``); own frame of each light.
    """
    from ._ground import ground_blocked_transfer
    from ._shadows import blocker_log_sum

    # a few thousand samples: the parallel kernels of this pass run on one thread (see _SERIAL_BELOW)
    threads = numba.get_num_threads()
    if np.asarray(sample_valid).size < _SERIAL_BELOW:
        numba.set_num_threads(1)
    try:
        S, m = sample_valid.shape
        env = np.asarray(env_sh, dtype=np.float64)
        order = math.isqrt(np.asarray(albedo_sh).shape[1])
        radiance = np.zeros((S, m, 3))
        if sample_valid.any():
            pts = np.asarray(sample_points, dtype=np.float64)[sample_valid]
            nrm = np.asarray(sample_normals, dtype=np.float64)[sample_valid]
            nrm = nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
            vis = sh.exp(blocker_log_sum(pts, nrm, centres, radii, order), method=exp_method, channels=False)  # Eq. 6
            t = environment_transfer(nrm, env, order)  # Eq. 8
            if ground is not None and len(ground):
                t = t - ground_blocked_transfer(pts, nrm, env, ground, order=order)
            radiance[sample_valid] = np.einsum("bk,bkc->bc", vis, t) / np.pi
        if extra_irradiance is not None:
            extra = np.asarray(extra_irradiance, dtype=np.float64)
            if extra.shape != (S, m, 3):
                raise ValueError(f"extra_irradiance must have shape {(S, m, 3)} (lights, samples, RGB), "
                                 f"got {extra.shape}")
            radiance += np.where(sample_valid[..., None], extra, 0.0) / np.pi
        light = np.einsum("smc,mk->skc", radiance, cell_sums)  # Eq. 10
    finally:
        numba.set_num_threads(threads)
    return np.einsum("ijk,sic,sjc->skc", _dense_gaunt(order), light, np.asarray(albedo_sh, dtype=np.float64))  # Eq. 11


def second_pass(points, normals, centres, radii, sl_object, intersect, sl_rotation, emission, env_sh, *,
                blocking: str = "object", exp_method: str = "hyb", indirect: bool = True,
                average: str = "cosine", method: str = "fused") -> tuple[np.ndarray, np.ndarray]:
    """Direct and indirect irradiance at receivers (Eqs. 8, 12-24).

    Parameters
    ----------
    points, normals : (B, 3) float
    centres, radii, sl_object, intersect
        As :func:`accumulate_blockers`.
    sl_rotation : (S, 3, 3) float
        World-from-light rotation of each light (its object's rotation).
    emission : (S, n*n, 3) float
        ``L^c`` of each light in its own frame (:func:`first_pass`).
    env_sh : (N*N, 3) float
        Environment radiance of any order ``N >= n`` (``3n - 2``: exact transfer). The order ``n``
        is the emission's.
    blocking : {"object", "sphere"}
    exp_method : {"hyb", "ol", "exact"}
    indirect : bool
        False: shadows only (the ``shadows only`` column of Sec. 8.5).
    average : {"cosine", "paper"}
        Average radiance of a light. ``"paper"``: Eqs. 15-18, ``L~ = w'_theta .
        L^c`` (the receiver cosine taken constant over the light and the
        ``1/d^2`` of the solid angle left out). ``"cosine"`` (default): the
        receiver-cosine-weighted average ``L~ = E_n / (pi s^2 n . a)`` with the
        exact unoccluded irradiance ``E_n`` of the light
        (:func:`irradiance_kernel_zh`); the paper's form underestimates the
        indirect light of a light near the receiver by up to 20 % (its bright
        upper part is seen at steeper angles than its dark underside).
    method : {"fused", "numba", "reference"}
        ``"fused"``: one numba loop over receivers doing the whole pass
        (``_second_pass_fused``; OL and HYB; ``exp_method="exact"`` falls back
        to ``"numba"``); ``"numba"``: the accumulation kernel, then batched
        :func:`prtlab.sh.exp` and numpy (the specification of the fused tier);
        ``"reference"``: the same with the numpy accumulation.

    Returns
    -------
    direct : (B, 3) float64
        ``E = V_p . T_n`` (Eq. 8 times pi).
    indirect : (B, 3) float64
        ``sum_i L~_i V~_i`` (Eq. 14, irradiance): ``L~_i = w'_theta . L^c_i``
        (Eq. 18), ``V~_i = (exp(G_front) - exp(G_front + G_i)) . rho_n``
        (Eqs. 23-24), ``rho_n`` the clamped cosine about ``n``.
        Exit radiance of a Lambertian receiver: ``albedo / pi`` times these.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    env = np.asarray(env_sh, dtype=np.float64)
    order = math.isqrt(np.asarray(emission).shape[-2])
    B, S, n2 = p.shape[0], np.asarray(centres).reshape(-1, 3).shape[0], order * order
    if B == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    if method not in ("numba", "reference", "fused"):
        raise ValueError(f"method must be 'fused', 'numba' or 'reference', got {method!r}")
    if average not in ("cosine", "paper"):
        raise ValueError(f"average must be 'cosine' or 'paper', got {average!r}")
    if method == "fused" and exp_method in ("hyb", "ol"):
        return _second_pass_fused_call(p, n, centres, radii, sl_object, intersect, sl_rotation, emission, env,
                                       blocking, exp_method, indirect, average == "cosine")
    method = "numba" if method == "fused" else method
    g_sphere, g_front, theta, axis = accumulate_blockers(p, n, centres, radii, sl_object, intersect, order,
                                                         blocking=blocking, method=method)
    # direct (Eq. 8): all blockers
    vis = sh.exp(g_sphere.sum(axis=1), method=exp_method, channels=False)
    direct = np.einsum("bk,bkc->bc", vis, environment_transfer(n, env, order))
    ind = np.zeros((B, 3))
    if not indirect or S == 0:
        return direct, ind
    live = theta >= 0
    rows_b, rows_s = np.nonzero(live)
    if rows_b.size == 0:
        return direct, ind
    gf = g_front[rows_b, rows_s]
    stacked = np.concatenate([gf, gf + g_sphere[rows_b, rows_s]], axis=0)
    e = sh.exp(stacked, method=exp_method, channels=False)
    v_sl = e[: rows_b.size] - e[rows_b.size :]  # Eq. 23
    cos = sh.zh_rotate(sh.clamped_cosine_zh(order), n)
    v_avg = np.einsum("tk,tk->t", v_sl, cos[rows_b])  # Eq. 24
    # Eq. 18: w_theta about the direction light -> receiver, in the light's own frame (Sec. 7.1)
    rot = np.asarray(sl_rotation, dtype=np.float64)
    em = np.asarray(emission, dtype=np.float64)
    to_recv = -axis[rows_b, rows_s]
    local = np.einsum("tji,tj->ti", rot[rows_s], to_recv)
    th = theta[rows_b, rows_s]
    if average == "paper":
        w = sh.zh_rotate(w_theta_zh(th, order), local)
        l_avg = np.einsum("tk,tkc->tc", w, em[rows_s])
    else:
        # E_n = s n.(Lu . K) - (n.b) L . K in the light's frame, over pi s^2 (n . a)
        k = sh.zh_rotate(irradiance_kernel_zh(th, order + 1), local)
        lu = emission_times_direction(em)
        n_loc = np.einsum("tji,tj->ti", rot[rows_s], n[rows_b])
        s_t = np.sin(np.minimum(th, THETA_MAX_K))
        e_n = (s_t[:, None] * np.einsum("tj,tjkc,tk->tc", n_loc, lu[rows_s], k)
               - np.einsum("tj,tj->t", n_loc, local)[:, None] * np.einsum("tkc,tk->tc", em[rows_s], k[:, :n2]))
        cos_na = np.einsum("tj,tj->t", n[rows_b], axis[rows_b, rows_s])
        proj = np.pi * s_t**2 * cos_na
        l_avg = np.where(proj[:, None] > 0, e_n / np.where(proj > 0, proj, 1.0)[:, None], 0.0)
        # visible fraction V~ / V~' (both order n): exact for an unoccluded light
        cz = sh.clamped_cosine_zh(order)
        v_open = np.array([_cap_visibility(math.cos(a), b_, cz, order) for a, b_ in zip(th, cos_na)])
        frac = np.where(v_open > 0, np.clip(v_avg / np.where(v_open > 0, v_open, 1.0), 0.0, 1.0), 0.0)
        v_avg = frac * proj
    np.add.at(ind, rows_b, l_avg * v_avg[:, None])  # Eq. 14
    return direct, ind


@numba.njit(cache=True)
def _cap_visibility(cos_theta, cos_na, cos_zh, order):
    """``P_n(1 - B) . rho_n``: the order-``n`` unoccluded average visibility of a cap of angular radius
    ``theta`` at angle ``acos(cos_na)`` from the normal, ``sum_l q_l c_l P_l(n . a)`` with
    ``q_l = 2 pi K_l int_{cos theta}^1 P_l``."""
    # Legendre values at cos_theta (up to l = order) and at cos_na (up to order - 1)
    pc_prev, pc = 1.0, cos_theta  # P_0, P_1 at cos theta
    pa_prev, pa = 1.0, cos_na
    total = 2.0 * math.pi * math.sqrt(1.0 / (4.0 * math.pi)) * (1.0 - cos_theta) * cos_zh[0]
    p_lm1 = 1.0  # P_{l-1}(c)
    for l in range(1, order):
        pc_next = ((2 * l + 1) * cos_theta * pc - l * pc_prev) / (l + 1)  # P_{l+1}(c)
        q = 2.0 * math.pi * math.sqrt((2 * l + 1) / (4.0 * math.pi)) * (p_lm1 - pc_next) / (2 * l + 1)
        total += q * cos_zh[l] * pa
        p_lm1 = pc
        pc_prev, pc = pc, pc_next
        pa_prev, pa = pa, ((2 * l + 1) * cos_na * pa - l * pa_prev) / (l + 1)
    return total


@functools.lru_cache(maxsize=None)
def _coordinate_products(order: int) -> np.ndarray:
    """``X (3, (n+1)**2, n*n)``: ``X[j] @ f`` is the SH (order n + 1, exact) of ``f(u) u_j`` for an order-n ``f``."""
    from prtlab.sh._gaunt import _gaunt_block

    gi, gj, gk, gv = _gaunt_block(order, 2, order + 1)
    out = np.zeros((3, (order + 1) ** 2, order * order))
    c1 = math.sqrt(4.0 * math.pi / 3.0)
    for j, idx in enumerate((3, 1, 2)):  # x = c Y_1,1, y = c Y_1,-1, z = c Y_1,0
        sel = gj == idx
        np.add.at(out[j], (gk[sel], gi[sel]), c1 * gv[sel])
    out.setflags(write=False)
    return out


@functools.lru_cache(maxsize=None)
def _dense_gaunt(order: int) -> np.ndarray:
    """Dense ``G (n*n, n*n, n*n)`` of the order-``n`` product (``c_k = sum_ij G_ijk a_i b_j``)."""
    from prtlab.sh._gaunt import _gaunt_block

    gi, gj, gk, gv = _gaunt_block(order, order, order)
    out = np.zeros((order * order,) * 3)
    np.add.at(out, (gi, gj, gk), gv)
    out.setflags(write=False)
    return out


def emission_times_direction(emission) -> np.ndarray:
    """SH of ``L(u) u_j`` for each light and coordinate ``j`` (x, y, z): ``(S, 3, (n+1)**2, C)``, exact.

    Parameters
    ----------
    emission : (S, n*n, C) float
        Light SH in the light's own frame.
    """
    em = np.asarray(emission, dtype=np.float64)
    order = math.isqrt(em.shape[1])
    return np.einsum("jqk,skc->sjqc", _coordinate_products(order), em)


# --------------------------------------------------------------------------- fused second pass (the fast tier)


def _light_arrays(centres, radii, sl_object, intersect):
    """The spherical lights as contiguous arrays, checked to agree in S, and each object's mean centre."""
    c = np.ascontiguousarray(centres, dtype=np.float64).reshape(-1, 3)
    r = np.ascontiguousarray(radii, dtype=np.float64).reshape(-1)
    obj = np.ascontiguousarray(sl_object, dtype=np.int64).reshape(-1)
    inter = np.ascontiguousarray(intersect, dtype=np.bool_)
    if r.shape[0] != c.shape[0] or obj.shape[0] != c.shape[0] or inter.shape != (c.shape[0], c.shape[0]):
        raise ValueError("centres (S, 3), radii (S,), sl_object (S,) and intersect (S, S) must agree in S")
    n_obj = int(obj.max()) + 1 if obj.size else 0
    obj_centres = np.zeros((n_obj, 3))
    for o in range(n_obj):
        obj_centres[o] = c[obj == o].mean(axis=0)
    return c, r, obj, inter, obj_centres


def _second_pass_fused_call(p, n, centres, radii, sl_object, intersect, sl_rotation, emission, env, blocking,
                            exp_method, indirect, cosine):
    order = math.isqrt(np.asarray(emission).shape[-2])
    c, r, obj, inter, obj_centres = _light_arrays(centres, radii, sl_object, intersect)
    hi = 2 * order - 1
    transfer = np.ascontiguousarray(transfer_matrix(env, order).reshape(hi * hi, order * order, 3)
                                    .transpose(0, 2, 1).reshape(hi * hi, 3 * order * order))
    r_max, tab_a, tab_b = _ol_table(order)
    gi, gj, gk, gv = _gaunt_block(order, order, order)
    direct = np.empty((p.shape[0], 3))
    ind = np.empty((p.shape[0], 3))
    # writeable C copies: one compiled signature whatever the caller passes
    rot = np.array(np.broadcast_to(np.asarray(sl_rotation, dtype=np.float64), (c.shape[0], 3, 3)), order="C")
    em = np.array(np.asarray(emission, dtype=np.float64).reshape(c.shape[0], order * order, 3), order="C")
    if cosine and indirect and c.shape[0]:
        lu = np.ascontiguousarray(emission_times_direction(em).transpose(0, 2, 1, 3).reshape(c.shape[0], -1, 9))
    else:
        lu = np.zeros((c.shape[0], (order + 1) ** 2, 9))
    _second_pass_fused(np.array(p, order="C"), np.array(n, order="C"), np.array(c), np.array(r), np.array(obj),
                       obj_centres, np.array(inter),
                       blocker_log_table(order), order, blocking == "object", transfer,
                       np.ascontiguousarray(sh.clamped_cosine_zh(2 * order - 1)),
                       np.ascontiguousarray(sh.clamped_cosine_zh(order)), np.ascontiguousarray(_w_theta_table(order)),
                       rot, em, bool(indirect and c.shape[0] > 0), exp_method == "hyb", r_max, tab_a, tab_b,
                       _HYB_THRESHOLD, gi, gj, gk, gv, bool(cosine), np.ascontiguousarray(_irradiance_kernel_table(order + 1)),
                       lu, direct, ind)
    return direct, ind



#: Receivers per task of the fused kernel (scratch arrays are allocated once per task).
_CHUNK = 256


@numba.njit(cache=True)
def _exp_row(x, hyb, r_max, tab_a, tab_b, threshold, gi, gj, gk, gv, h, v, w, out):
    """exp* of one vector x (n2, 1) into out (n2, 1): OL, or HYB (scaling and squaring over OL), as prtlab.sh."""
    n2 = x.shape[0]
    if not hyb:
        _ol_one(x, r_max, tab_a, tab_b, out)
        return
    norm2 = 0.0
    for i in range(1, n2):
        norm2 += x[i, 0] * x[i, 0]
    norm = math.sqrt(norm2)
    k = 0
    if norm > threshold:
        k = max(0, int(math.ceil(math.log2(norm / threshold))))
        while norm / 2.0**k > threshold:
            k += 1
    scale = 1.0 / 2.0**k
    h[0, 0] = 0.0
    for i in range(1, n2):
        h[i, 0] = x[i, 0] * scale
    _ol_one(h, r_max, tab_a, tab_b, v)
    for _ in range(k):
        _tile_product(v, v, gi, gj, gk, gv, w)
        for i in range(n2):
            v[i, 0] = w[i, 0]
    dc = math.exp(x[0, 0] / math.sqrt(4.0 * math.pi))
    for i in range(n2):
        out[i, 0] = dc * v[i, 0]


@numba.njit(cache=True)
def _exp_lanes(x, hyb, r_max, tab_a, tab_b, threshold, gi, gj, gk, gv, h, v, w, ks, out):
    """exp* of the columns (lanes) of x (n2, L) into out, as :func:`_exp_row` column by column but with the
    squarings of HYB batched over the lanes (each lane keeps its own number of squarings)."""
    n2, n_lanes = x.shape
    if not hyb:
        _ol_one(x, r_max, tab_a, tab_b, out)
        return
    k_max = 0
    for q in range(n_lanes):
        norm2 = 0.0
        for i in range(1, n2):
            norm2 += x[i, q] * x[i, q]
        norm = math.sqrt(norm2)
        k = 0
        if norm > threshold:
            k = max(0, int(math.ceil(math.log2(norm / threshold))))
            while norm / 2.0**k > threshold:
                k += 1
        ks[q] = k
        k_max = max(k_max, k)
        scale = 1.0 / 2.0**k
        h[0, q] = 0.0
        for i in range(1, n2):
            h[i, q] = x[i, q] * scale
    _ol_one(h, r_max, tab_a, tab_b, v)
    for t in range(k_max):
        _tile_product(v, v, gi, gj, gk, gv, w)
        for q in range(n_lanes):
            if t < ks[q]:
                for i in range(n2):
                    v[i, q] = w[i, q]
    sqrt4pi = math.sqrt(4.0 * math.pi)
    for q in range(n_lanes):
        dc = math.exp(x[0, q] / sqrt4pi)
        for i in range(n2):
            out[i, q] = dc * v[i, q]


@numba.njit(cache=True, parallel=True)
def _second_pass_fused(points, normals, centres, radii, sl_object, obj_centres, intersect, table, order, per_object,
                       transfer_t, cos_zh_hi, cos_zh, w_table, rot, emission, indirect, hyb, r_max, tab_a, tab_b,
                       threshold, gi, gj, gk, gv, cosine, k_table, lu, direct_out, indirect_out):
    """Second pass per receiver (Eqs. 8, 14, 18, 21-24), one loop: blocker logs, front sums, exponentials,
    average visibility and average radiance. Same quantities as the composed numpy/batched tier."""
    n_recv = points.shape[0]
    n_sph = centres.shape[0]
    n_obj = obj_centres.shape[0]
    n2 = order * order
    n_theta = w_table.shape[0] - 1
    hi = 2 * order - 1
    n_chunks = (n_recv + _CHUNK - 1) // _CHUNK
    for chunk in numba.prange(n_chunks):
        ybuf = np.empty((1, max(hi * hi, (order + 1) * (order + 1))))
        g = np.empty(order)
        gs = np.zeros((n_sph, n2))
        n1 = (order + 1) * (order + 1)
        krot = np.zeros(n1)
        kz = np.empty(order + 1)
        dist = np.empty(n_sph)
        theta = np.empty(n_sph)
        axis = np.empty((n_sph, 3))
        x = np.empty((n2, 1))
        e1 = np.empty((n2, 1))
        h = np.empty((n2, 1))
        v = np.empty((n2, 1))
        w = np.empty((n2, 1))
        total = np.zeros(n2)
        cosr = np.zeros(n2)
        cos_hi = np.zeros(hi * hi)
        wrot = np.zeros(n2)
        wz = np.empty(order)
        od = np.empty(n_obj)
        live = np.empty(n_sph, dtype=np.int64)
        xl = np.empty((n2, 2 * n_sph))
        hl = np.empty((n2, 2 * n_sph))
        vl = np.empty((n2, 2 * n_sph))
        wl = np.empty((n2, 2 * n_sph))
        el = np.empty((n2, 2 * n_sph))
        kl = np.empty(2 * n_sph, dtype=np.int64)
        ydir = np.empty(3 * n2)
        fr = np.empty(n2)
        run = np.empty(n2)
        osum = np.empty((n_obj, n2))
        pre = np.empty((n_obj, n2))
        oord = np.empty(n_obj, dtype=np.int64)
        la = np.empty(9)
        le = np.empty(3)
        for b in range(chunk * _CHUNK, min(n_recv, (chunk + 1) * _CHUNK)):
            px, py, pz = points[b, 0], points[b, 1], points[b, 2]
            nx, ny, nz = normals[b, 0], normals[b, 1], normals[b, 2]
            for k in range(n2):
                total[k] = 0.0
            for s in range(n_sph):
                for k in range(n2):
                    gs[s, k] = 0.0
                cx, cy, cz, r = _adjust(px, py, pz, nx, ny, nz, centres[s, 0], centres[s, 1], centres[s, 2], radii[s])
                dx, dy, dz = cx - px, cy - py, cz - pz
                d = math.sqrt(dx * dx + dy * dy + dz * dz)
                dist[s] = d
                if r <= 0.0 or d <= 0.0:
                    theta[s] = -1.0
                    continue
                sin_t = r / d
                th = 0.5 * math.pi if sin_t >= 1.0 else math.asin(sin_t)
                theta[s] = th
                axis[s, 0] = dx / d
                axis[s, 1] = dy / d
                axis[s, 2] = dz / d
                _lookup_log(th, table, order, g)
                if order <= LOW_BANDS:
                    _add_rotated_zh_low(g, dx / d, dy / d, dz / d, order, ybuf, gs[s])
                else:
                    _add_rotated_zh(g, dx / d, dy / d, dz / d, order, ybuf, 1.0, gs[s])
                for k in range(n2):
                    total[k] += gs[s, k]
            # direct (Eq. 8)
            for k in range(n2):
                x[k, 0] = total[k]
            _exp_row(x, hyb, r_max, tab_a, tab_b, threshold, gi, gj, gk, gv, h, v, w, e1)
            # T_n = cos_{2n-1}(n) @ M (exact projection of L cos, see environment_transfer)
            for k in range(hi * hi):
                cos_hi[k] = 0.0
            _add_rotated_zh(cos_zh_hi, nx, ny, nz, hi, ybuf, 1.0, cos_hi)
            # T_n . e1 = sum_q cos_q (M[q] . e1) as y = sum_q cos_q M[q] (contiguous axpy over (c, k),
            # vectorisable without reassociation), then y . e1; the clamped cosine's odd bands > 1 vanish
            for t in range(3 * n2):
                ydir[t] = 0.0
            for l in range(hi):
                if cos_zh_hi[l] == 0.0:
                    continue
                for q in range(l * l, (l + 1) * (l + 1)):
                    cq = cos_hi[q]
                    for t in range(3 * n2):
                        ydir[t] += cq * transfer_t[q, t]
            for c in range(3):
                acc = 0.0
                for k in range(n2):
                    acc += ydir[c * n2 + k] * e1[k, 0]
                direct_out[b, c] = acc
                indirect_out[b, c] = 0.0
            if not indirect:
                continue
            for k in range(n2):
                cosr[k] = 0.0
            _add_rotated_zh(cos_zh, nx, ny, nz, order, ybuf, 1.0, cosr)
            for o in range(n_obj):
                ex = obj_centres[o, 0] - px
                ey = obj_centres[o, 1] - py
                ez = obj_centres[o, 2] - pz
                od[o] = ex * ex + ey * ey + ez * ez
            # front sums (Eq. 23), per object or per sphere (Sec. 7.2), into contiguous rows fr[i]: per object,
            # the prefix sums of the object sums in (distance, index) order plus the closer non-intersecting
            # lights of i's own object; lanes 2q (front) and 2q + 1 (front + own) of the exponentials
            if per_object:
                for o in range(n_obj):
                    oord[o] = o
                    for k in range(n2):
                        osum[o, k] = 0.0
                for o in range(1, n_obj):  # insertion sort by (od, index): stable, as the other tiers
                    t = oord[o]
                    j = o - 1
                    while j >= 0 and od[oord[j]] > od[t]:
                        oord[j + 1] = oord[j]
                        j -= 1
                    oord[j + 1] = t
                for s in range(n_sph):
                    o = sl_object[s]
                    for k in range(n2):
                        osum[o, k] += gs[s, k]
                for k in range(n2):
                    run[k] = 0.0
                for q in range(n_obj):
                    o = oord[q]
                    for k in range(n2):
                        pre[o, k] = run[k]
                        run[k] += osum[o, k]
            n_live = 0
            for i in range(n_sph):
                if theta[i] < 0.0:
                    continue
                live[n_live] = i
                if per_object:
                    oi = sl_object[i]
                    for k in range(n2):
                        fr[k] = pre[oi, k]
                    for j in range(n_sph):
                        if j != i and sl_object[j] == oi and dist[j] < dist[i] and not intersect[i, j]:
                            for k in range(n2):
                                fr[k] += gs[j, k]
                else:
                    for k in range(n2):
                        fr[k] = 0.0
                    for j in range(n_sph):
                        if j != i and dist[j] < dist[i] and not intersect[i, j]:
                            for k in range(n2):
                                fr[k] += gs[j, k]
                for k in range(n2):
                    xl[k, 2 * n_live] = fr[k]
                    xl[k, 2 * n_live + 1] = fr[k] + gs[i, k]
                n_live += 1
            if n_live == 0:
                continue
            _exp_lanes(xl[:, : 2 * n_live], hyb, r_max, tab_a, tab_b, threshold, gi, gj, gk, gv,
                       hl[:, : 2 * n_live], vl[:, : 2 * n_live], wl[:, : 2 * n_live], kl[: 2 * n_live],
                       el[:, : 2 * n_live])
            for q in range(n_live):
                i = live[q]
                v_avg = 0.0
                for k in range(n2):
                    v_avg += (el[k, 2 * q] - el[k, 2 * q + 1]) * cosr[k]  # Eqs. 23-24
                # Eq. 18: w_theta about light -> receiver in the light's frame
                lx = -(rot[i, 0, 0] * axis[i, 0] + rot[i, 1, 0] * axis[i, 1] + rot[i, 2, 0] * axis[i, 2])
                ly = -(rot[i, 0, 1] * axis[i, 0] + rot[i, 1, 1] * axis[i, 1] + rot[i, 2, 1] * axis[i, 2])
                lz = -(rot[i, 0, 2] * axis[i, 0] + rot[i, 1, 2] * axis[i, 1] + rot[i, 2, 2] * axis[i, 2])
                u = theta[i] * (n_theta / (0.5 * math.pi))
                jt = min(int(math.floor(u)), n_theta - 1)
                st = u - jt
                if cosine:
                    # E_n = s n.(Lu . K) - (n.b) L . K over pi s^2 (n . a), light frame (see irradiance_kernel_zh)
                    uk = min(theta[i], THETA_MAX_K) * (N_THETA_K / THETA_MAX_K)
                    jk = min(int(math.floor(uk)), N_THETA_K - 1)
                    sk = uk - jk
                    for l in range(order + 1):
                        kz[l] = (1.0 - sk) * k_table[jk, l] + sk * k_table[jk + 1, l]
                    for k in range(n1):
                        krot[k] = 0.0
                    _add_rotated_zh(kz, lx, ly, lz, order + 1, ybuf, 1.0, krot)
                    mx = rot[i, 0, 0] * nx + rot[i, 1, 0] * ny + rot[i, 2, 0] * nz
                    my = rot[i, 0, 1] * nx + rot[i, 1, 1] * ny + rot[i, 2, 1] * nz
                    mz = rot[i, 0, 2] * nx + rot[i, 1, 2] * ny + rot[i, 2, 2] * nz
                    s_i = math.sin(min(theta[i], THETA_MAX_K))
                    nb = mx * lx + my * ly + mz * lz
                    cos_na = nx * axis[i, 0] + ny * axis[i, 1] + nz * axis[i, 2]
                    proj = math.pi * s_i * s_i * cos_na
                    v_open = _cap_visibility(math.cos(theta[i]), cos_na, cos_zh, order)
                    if proj <= 0.0 or v_open <= 0.0:
                        continue
                    frac = min(max(v_avg / v_open, 0.0), 1.0)
                    # a[j, c] = sum_k krot_k Lu[i, j, k, c] and e[c] = sum_k krot_k L[i, k, c] as axpys over
                    # the contiguous (j, c) rows of lu (S, n1, 9) and emission (S, n2, 3)
                    for t in range(9):
                        la[t] = 0.0
                    for k in range(n1):
                        kr = krot[k]
                        for t in range(9):
                            la[t] += kr * lu[i, k, t]
                    for c in range(3):
                        le[c] = 0.0
                    for k in range(n2):
                        kr = krot[k]
                        for c in range(3):
                            le[c] += kr * emission[i, k, c]
                    for c in range(3):
                        acc = s_i * (mx * la[c] + my * la[3 + c] + mz * la[6 + c]) - nb * le[c]
                        indirect_out[b, c] += acc * frac
                    continue
                for l in range(order):
                    wz[l] = (1.0 - st) * w_table[jt, l] + st * w_table[jt + 1, l]
                for k in range(n2):
                    wrot[k] = 0.0
                _add_rotated_zh(wz, lx, ly, lz, order, ybuf, 1.0, wrot)
                for c in range(3):
                    l_avg = 0.0
                    for k in range(n2):
                        l_avg += wrot[k] * emission[i, k, c]
                    indirect_out[b, c] += l_avg * v_avg

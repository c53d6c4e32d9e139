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

from ._shadows import (
    _ZH_SCALE,
    _add_rotated_zh,
    _adjust,
    _basis_lanes,
    _blocker_lanes,
    _blocker_log_knots,
    _lookup_log,
    blocker_log_table,
    environment_transfer,
    transfer_matrix,
)
from ._tables import (
    N_THETA_K,
    THETA_MAX_K,
    _irradiance_kernel_table,
    _w_theta_table,
    irradiance_kernel_zh,
    w_theta_zh,
)

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
    B, S = p.shape[0], np.asarray(centres).reshape(-1, 3).shape[0]
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
    rows_b, rows_s, terms = light_terms(n, g_sphere, g_front, theta, axis, sl_rotation, emission, order,
                                        exp_method=exp_method, average=average)
    np.add.at(ind, rows_b, terms)  # Eq. 14
    return direct, ind


def light_terms(n, g_sphere, g_front, theta, axis, sl_rotation, emission, order: int, *, exp_method: str = "hyb",
                average: str = "cosine"):
    """The diffuse reflection ``L~_i V~_i`` of every live (receiver, light) pair, from the blocker logs.

    ``n (B, 3)`` unit normals and ``g_sphere, g_front, theta, axis`` as :func:`accumulate_blockers` returns
    them; the rest as :func:`second_pass`. Returns ``rows_b, rows_s (T,)`` (the pairs with ``theta >= 0``)
    and ``terms (T, 3)``, whose sum over the lights of a receiver is its indirect irradiance (Eq. 14):
    ``V~_i = (exp(G_front) - exp(G_front + G_i)) . rho_n`` (Eqs. 23-24) times ``w'_theta . L^c_i`` (Eq. 18,
    ``average="paper"``), or the light's cosine-weighted irradiance times the visible fraction ``V~_i / V~'_i``
    (``"cosine"``).
    """
    rows_b, rows_s = np.nonzero(theta >= 0)
    if rows_b.size == 0:
        return rows_b, rows_s, np.zeros((0, 3))
    n2 = order * order
    gf = g_front[rows_b, rows_s]
    e = sh.exp(np.concatenate([gf, gf + g_sphere[rows_b, rows_s]], axis=0), method=exp_method, channels=False)
    v_sl = e[: rows_b.size] - e[rows_b.size :]  # Eq. 23
    cos = sh.zh_rotate(sh.clamped_cosine_zh(order), n)
    v_avg = np.einsum("tk,tk->t", v_sl, cos[rows_b])  # Eq. 24
    # Eq. 18: w_theta about the direction light -> receiver, in the light's own frame (Sec. 7.1)
    rot = np.asarray(sl_rotation, dtype=np.float64)
    em = np.asarray(emission, dtype=np.float64)
    local = np.einsum("tji,tj->ti", rot[rows_s], -axis[rows_b, rows_s])
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
        v_open = _cap_visibility(np.cos(th), cos_na, order)
        frac = np.where(v_open > 0, np.clip(v_avg / np.where(v_open > 0, v_open, 1.0), 0.0, 1.0), 0.0)
        v_avg = frac * proj
    return rows_b, rows_s, l_avg * v_avg[:, None]


def _cap_visibility(cos_theta, cos_na, order: int) -> np.ndarray:
    """``P_n(1 - B) . rho_n`` per row: the order-``n`` unoccluded average visibility of a cap of angular radius
    ``acos(cos_theta)`` at angle ``acos(cos_na)`` from the normal, ``sum_l q_l c_l P_l(n . a)`` with
    ``q_l = 2 pi K_l int_{cos theta}^1 P_l = 2 pi K_l (P_{l-1}(c) - P_{l+1}(c)) / (2l + 1)`` (``P_{-1} = 1``)."""
    c = np.asarray(cos_theta, dtype=np.float64)
    a = np.asarray(cos_na, dtype=np.float64)
    cz = sh.clamped_cosine_zh(order)
    total = 2.0 * math.pi * math.sqrt(1.0 / (4.0 * math.pi)) * (1.0 - c) * cz[0]
    pc_prev, pc, pa_prev, pa, p_lm1 = np.ones_like(c), c, np.ones_like(a), a, np.ones_like(c)
    for l in range(1, order):
        pc_next = ((2 * l + 1) * c * pc - l * pc_prev) / (l + 1)
        q = 2.0 * math.pi * math.sqrt((2 * l + 1) / (4.0 * math.pi)) * (p_lm1 - pc_next) / (2 * l + 1)
        total = total + q * cz[l] * pa
        p_lm1 = pc
        pc_prev, pc = pc, pc_next
        pa_prev, pa = pa, ((2 * l + 1) * a * pa - l * pa_prev) / (l + 1)
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


#: Receivers per SIMD block of the fused second pass: the lanes of its innermost loops.
_LANES = 32
#: Blocks per parallel task (the scratch arrays are allocated once per task).
_BLOCKS_PER_TASK = 8


@functools.lru_cache(maxsize=None)
def _symmetric_gaunt(order: int):
    """Gaunt entries of the order-``n`` square ``v * v`` with ``i <= j`` (value doubled where ``i < j``),
    sorted by output ``k``: ``(pi, pj, pk, pv)``, about half the entries of the full product."""
    gi, gj, gk, gv = _gaunt_block(order, order, order)
    keep = gi <= gj
    val = np.where(gi < gj, 2.0, 1.0) * gv
    sel = np.nonzero(keep)[0]
    sel = sel[np.argsort(gk[sel], kind="stable")]
    out = tuple(np.ascontiguousarray(a[sel]) for a in (gi, gj, gk, val))
    for a in out:
        a.setflags(write=False)
    return out


def _front_lists(sl_object, intersect, per_object):
    """CSR lists of the lights each light may have in front (besides whole closer objects): ``(ptr (S+1,),
    idx)``; per object the non-intersecting other lights of its object, per sphere every non-intersecting other
    light, in index order. Which of them are in front is decided per receiver (centre distance)."""
    n_sph = sl_object.shape[0]
    cand = ~intersect & ~np.eye(n_sph, dtype=bool)
    if per_object:
        cand &= sl_object[:, None] == sl_object[None, :]
    ptr = np.zeros(n_sph + 1, dtype=np.int64)
    ptr[1:] = np.cumsum(cand.sum(axis=1))
    return ptr, np.ascontiguousarray(np.nonzero(cand)[1], dtype=np.int64)


def _second_pass_fused_call(p, n, centres, radii, sl_object, intersect, sl_rotation, emission, env, blocking,
                            exp_method, indirect, cosine):
    order = math.isqrt(np.asarray(emission).shape[-2])
    c, r, obj, inter, obj_centres = _light_arrays(centres, radii, sl_object, intersect)
    hi = 2 * order - 1
    transfer = np.ascontiguousarray(transfer_matrix(env, order).reshape(hi * hi, order * order, 3)
                                    .transpose(0, 2, 1).reshape(hi * hi, 3 * order * order))
    r_max, tab_a, tab_b = _ol_table(order)
    pi_, pj, pk, pv = _symmetric_gaunt(order)
    front_ptr, front_idx = _front_lists(obj, inter, blocking == "object")
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
                       obj_centres, front_ptr, front_idx, blocker_log_table(order), _blocker_log_knots(), order,
                       blocking == "object", transfer, np.ascontiguousarray(sh.clamped_cosine_zh(hi)),
                       np.ascontiguousarray(sh.clamped_cosine_zh(order)), np.ascontiguousarray(_w_theta_table(order)),
                       rot, em, bool(indirect and c.shape[0] > 0), exp_method == "hyb", r_max, tab_a, tab_b,
                       _HYB_THRESHOLD, pi_, pj, pk, pv, bool(cosine),
                       np.ascontiguousarray(_irradiance_kernel_table(order + 1)), lu, _LANES, direct, ind)
    return direct, ind


@numba.njit(cache=True, error_model="numpy")
def _ol_coefficients(r, r_max, tab_a, tab_b):
    """``(a, b)`` of the optimal-linear exponential at ``|f^| = r`` (as ``prtlab.sh``'s ``_ol_one``)."""
    n_tab = tab_a.shape[0]
    if r >= r_max:
        return tab_a[n_tab - 1], tab_b[n_tab - 1]
    j = min(int(math.sqrt(r / r_max) * (n_tab - 1)), n_tab - 2)
    r0 = r_max * (j / (n_tab - 1)) ** 2
    r1 = r_max * ((j + 1) / (n_tab - 1)) ** 2
    s = (r - r0) / (r1 - r0)
    return (1.0 - s) * tab_a[j] + s * tab_a[j + 1], (1.0 - s) * tab_b[j] + s * tab_b[j + 1]


@numba.njit(cache=True, error_model="numpy")
def _exp_hyb_columns(x, r_max, tab_a, tab_b, threshold, pi_, pj, pk, pv, h, v, w, col, ks, perm, out):
    """HYB ``exp*`` of the columns of ``x (n2, M)`` into ``out`` (as ``prtlab.sh``'s ``_exp_hyb``: ``k`` halvings
    to ``|f^| <= threshold``, OL, ``k`` squarings, the DC factor). The columns are ordered by ``k``
    (descending), so squaring ``t`` runs over the prefix of columns that still need it; a square uses the
    symmetric Gaunt pairs ``(pi, pj, pk, pv)``. ``h, v, w (n2, M)``, ``col (2, M)``, ``ks, perm (M,)``: scratch."""
    n2, m = x.shape
    sqrt4pi = math.sqrt(4.0 * math.pi)
    for p in range(m):
        col[0, p] = 0.0
    for i in range(1, n2):
        for p in range(m):
            col[0, p] += x[i, p] * x[i, p]
    k_max = 0
    for p in range(m):
        norm = math.sqrt(col[0, p])
        k = 0
        if norm > threshold:
            k = max(0, int(math.ceil(math.log2(norm / threshold))))
            while norm / 2.0**k > threshold:  # guard against rounding in log2, as prtlab.sh
                k += 1
        ks[p] = k
        k_max = max(k_max, k)
    pos = 0
    for kk in range(k_max, -1, -1):
        for p in range(m):
            if ks[p] == kk:
                perm[pos] = p
                pos += 1
    for t in range(m):
        p = perm[t]
        scale = 1.0 / 2.0 ** ks[p]
        h[0, t] = 0.0
        for i in range(1, n2):
            h[i, t] = x[i, p] * scale
    # OL of the scaled columns (DC 0: its factor exp(0) = 1)
    for t in range(m):
        col[0, t] = 0.0
    for i in range(1, n2):
        for t in range(m):
            col[0, t] += h[i, t] * h[i, t]
    for t in range(m):
        a, b = _ol_coefficients(math.sqrt(col[0, t]), r_max, tab_a, tab_b)
        v[0, t] = a * sqrt4pi
        col[1, t] = b
    for i in range(1, n2):
        for t in range(m):
            v[i, t] = col[1, t] * h[i, t]
    n_act = m
    for step in range(k_max):
        while n_act > 0 and ks[perm[n_act - 1]] <= step:
            n_act -= 1
        for k in range(n2):
            for t in range(n_act):
                w[k, t] = 0.0
        for e in range(pv.shape[0]):
            i = pi_[e]
            j = pj[e]
            k = pk[e]
            val = pv[e]
            for t in range(n_act):
                w[k, t] += val * v[i, t] * v[j, t]
        for k in range(n2):
            for t in range(n_act):
                v[k, t] = w[k, t]
    for t in range(m):
        p = perm[t]
        dc = math.exp(x[0, p] / sqrt4pi)
        for i in range(n2):
            out[i, p] = dc * v[i, t]


@numba.njit(cache=True, error_model="numpy")
def _cap_visibility_lanes(cos_t, i, lane, cos_zh, order, tmp):
    """:func:`_cap_visibility` of the lanes: ``lane[8, q]`` for ``cos theta = cos_t[i, q]`` and ``cos_na =
    lane[7, q]``; ``tmp (5, L)`` scratch (rows: P_(l-1), P_l at cos theta, P_(l-1), P_l at cos_na, P_(l-1))."""
    n_lanes = lane.shape[1]
    k0 = 2.0 * math.pi * math.sqrt(1.0 / (4.0 * math.pi))
    for q in range(n_lanes):
        tmp[0, q] = 1.0
        tmp[1, q] = cos_t[i, q]
        tmp[2, q] = 1.0
        tmp[3, q] = lane[7, q]
        tmp[4, q] = 1.0
        lane[8, q] = k0 * (1.0 - cos_t[i, q]) * cos_zh[0]
    for l in range(1, order):
        kl = 2.0 * math.pi * math.sqrt((2 * l + 1) / (4.0 * math.pi))
        czl = cos_zh[l]
        for q in range(n_lanes):
            pc = tmp[1, q]
            pc_next = ((2 * l + 1) * cos_t[i, q] * pc - l * tmp[0, q]) / (l + 1)
            pa = tmp[3, q]
            lane[8, q] += kl * (tmp[4, q] - pc_next) / (2 * l + 1) * czl * pa
            tmp[4, q] = pc
            tmp[0, q] = pc
            tmp[1, q] = pc_next
            tmp[3, q] = ((2 * l + 1) * lane[7, q] * pa - l * tmp[2, q]) / (l + 1)
            tmp[2, q] = pa


@numba.njit(cache=True, parallel=True, error_model="numpy")
def _second_pass_fused(points, normals, centres, radii, sl_object, obj_centres, front_ptr, front_idx, table, u_knots,
                       order, per_object, transfer_t, cos_zh_hi, cos_zh, w_table, rot, emission, indirect, hyb,
                       r_max, tab_a, tab_b, threshold, pi_, pj, pk, pv, cosine, k_table, lu, n_lanes, direct_out,
                       indirect_out):
    """Second pass (Eqs. 8, 14, 18, 21-24) over blocks of ``n_lanes`` receivers, the receivers of a block as the
    SIMD lanes of the inner loops: blocker logs, front sums, exponentials, average visibility and average
    radiance. Same quantities, to rounding, as the composed tier (``method="numba"``). ``n_lanes`` is an
    argument, not a compile-time constant: LLVM fully unrolls constant 16-trip loops into scalar code
    instead of vectorising them."""
    n_recv = points.shape[0]
    n_sph = centres.shape[0]
    n_obj = obj_centres.shape[0]
    n2 = order * order
    n1 = (order + 1) * (order + 1)
    hi = 2 * order - 1
    n_theta = w_table.shape[0] - 1
    sqrt4pi = math.sqrt(4.0 * math.pi)
    sin_k_max = math.sin(THETA_MAX_K)
    n_blocks = (n_recv + n_lanes - 1) // n_lanes
    n_tasks = (n_blocks + _BLOCKS_PER_TASK - 1) // _BLOCKS_PER_TASK
    for task in numba.prange(n_tasks):
        recv = np.empty((6, n_lanes))
        ynrm = np.empty((hi * hi, n_lanes))
        ybuf = np.empty((max(n1, n2), n_lanes))
        tmp = np.empty((7, n_lanes))
        glog = np.empty((order + 1, n_lanes))
        gs = np.empty((n_sph, n2, n_lanes))
        dist = np.empty((n_sph, n_lanes))
        theta = np.empty((n_sph, n_lanes))
        sin_t = np.empty((n_sph, n_lanes))
        cos_t = np.empty((n_sph, n_lanes))
        axis = np.empty((n_sph, 3, n_lanes))
        total = np.empty((n2, n_lanes))
        trans = np.empty((3 * n2, n_lanes))
        cosr = np.empty((n2, n_lanes))
        lane = np.empty((12, n_lanes))
        dsum = np.empty((3, n_lanes))
        isum = np.empty((3, n_lanes))
        od = np.empty((n_obj, n_lanes))
        oidx = np.empty(n_obj, dtype=np.int64)
        osum = np.empty((n_obj, n2, n_lanes))
        pre = np.empty((n_obj, n2, n_lanes))
        run = np.empty(n2)
        fr = np.empty((n2, n_lanes))
        vavg = np.empty((n_sph, n_lanes))
        krot = np.empty((n1, n_lanes))
        la = np.empty((9, n_lanes))
        le = np.empty((3, n_lanes))
        # HYB columns: the direct exponentials of a block (L), or one light's front and front + own (2 L)
        xd, hd, vd, wd, ed = (np.empty((n2, n_lanes)), np.empty((n2, n_lanes)), np.empty((n2, n_lanes)),
                              np.empty((n2, n_lanes)), np.empty((n2, n_lanes)))
        xl, hl, vl, wl, el = (np.empty((n2, 2 * n_lanes)), np.empty((n2, 2 * n_lanes)), np.empty((n2, 2 * n_lanes)),
                              np.empty((n2, 2 * n_lanes)), np.empty((n2, 2 * n_lanes)))
        cold = np.empty((2, n_lanes))
        coll = np.empty((2, 2 * n_lanes))
        ksd = np.empty(n_lanes, dtype=np.int64)
        permd = np.empty(n_lanes, dtype=np.int64)
        ksl = np.empty(2 * n_lanes, dtype=np.int64)
        perml = np.empty(2 * n_lanes, dtype=np.int64)
        for blk in range(task * _BLOCKS_PER_TASK, min(n_blocks, (task + 1) * _BLOCKS_PER_TASK)):
            b0 = blk * n_lanes
            nb = min(n_lanes, n_recv - b0)
            for q in range(n_lanes):  # a partial block repeats its last receiver
                b = b0 + min(q, nb - 1)
                for t in range(3):
                    recv[t, q] = points[b, t]
                    recv[3 + t, q] = normals[b, t]
            # blocker logs of every light (Eqs. 6-7, 20-22)
            for k in range(n2):
                for q in range(n_lanes):
                    total[k, q] = 0.0
            for s in range(n_sph):
                _blocker_lanes(recv, s, centres[s, 0], centres[s, 1], centres[s, 2], radii[s], table, u_knots, order,
                               glog, ybuf, tmp, gs, dist, theta, sin_t, cos_t, axis)
                for k in range(n2):
                    for q in range(n_lanes):
                        total[k, q] += gs[s, k, q]
            # direct (Eq. 8): T_n = cos_{2n-1}(n) @ M per lane (exact projection of L cos, see
            # environment_transfer; the clamped cosine's odd bands > 1 vanish), then T_n . exp*(total)
            _basis_lanes(recv, 3, hi, ynrm, tmp)
            for t in range(3 * n2):
                for q in range(n_lanes):
                    trans[t, q] = 0.0
            for l in range(hi):
                if cos_zh_hi[l] == 0.0:
                    continue
                f = _ZH_SCALE[l] * cos_zh_hi[l]
                for qq in range(l * l, (l + 1) * (l + 1)):
                    for q in range(n_lanes):
                        lane[0, q] = f * ynrm[qq, q]
                    for t in range(3 * n2):
                        m = transfer_t[qq, t]
                        for q in range(n_lanes):
                            trans[t, q] += lane[0, q] * m
            if hyb:
                for k in range(n2):
                    for q in range(n_lanes):
                        xd[k, q] = total[k, q]
                _exp_hyb_columns(xd, r_max, tab_a, tab_b, threshold, pi_, pj, pk, pv, hd, vd, wd, cold, ksd, permd,
                                 ed)
                for c in range(3):
                    for q in range(n_lanes):
                        dsum[c, q] = 0.0
                    for k in range(n2):
                        for q in range(n_lanes):
                            dsum[c, q] += trans[c * n2 + k, q] * ed[k, q]
            else:
                for q in range(n_lanes):
                    lane[1, q] = 0.0
                for k in range(1, n2):
                    for q in range(n_lanes):
                        lane[1, q] += total[k, q] * total[k, q]
                for c in range(3):
                    for q in range(n_lanes):
                        dsum[c, q] = 0.0
                    for k in range(1, n2):
                        for q in range(n_lanes):
                            dsum[c, q] += trans[c * n2 + k, q] * total[k, q]
                for q in range(n_lanes):
                    a, b = _ol_coefficients(math.sqrt(lane[1, q]), r_max, tab_a, tab_b)
                    dc = math.exp(total[0, q] / sqrt4pi)
                    for c in range(3):
                        dsum[c, q] = dc * (a * sqrt4pi * trans[c * n2, q] + b * dsum[c, q])
            for q in range(nb):
                for c in range(3):
                    direct_out[b0 + q, c] = dsum[c, q]
                    indirect_out[b0 + q, c] = 0.0
            if not indirect:
                continue
            for l in range(order):
                f = _ZH_SCALE[l] * cos_zh[l]
                for k in range(l * l, (l + 1) * (l + 1)):
                    for q in range(n_lanes):
                        cosr[k, q] = f * ynrm[k, q]
            # front sums (Eq. 23), per object or per sphere (Sec. 7.2): per object, the prefix sums of the object
            # sums in (distance, index) order, then the closer non-intersecting lights of i's own object
            if per_object:
                for o in range(n_obj):
                    for q in range(n_lanes):
                        ex = obj_centres[o, 0] - recv[0, q]
                        ey = obj_centres[o, 1] - recv[1, q]
                        ez = obj_centres[o, 2] - recv[2, q]
                        od[o, q] = ex * ex + ey * ey + ez * ez
                    for k in range(n2):
                        for q in range(n_lanes):
                            osum[o, k, q] = 0.0
                for s in range(n_sph):
                    o = sl_object[s]
                    for k in range(n2):
                        for q in range(n_lanes):
                            osum[o, k, q] += gs[s, k, q]
                for q in range(n_lanes):
                    for o in range(n_obj):
                        oidx[o] = o
                    for o in range(1, n_obj):  # insertion sort by (od, index): stable, as the other tiers
                        t = oidx[o]
                        j = o - 1
                        while j >= 0 and od[oidx[j], q] > od[t, q]:
                            oidx[j + 1] = oidx[j]
                            j -= 1
                        oidx[j + 1] = t
                    for k in range(n2):
                        run[k] = 0.0
                    for t in range(n_obj):
                        o = oidx[t]
                        for k in range(n2):
                            pre[o, k, q] = run[k]
                            run[k] += osum[o, k, q]
            # average visibility (Eqs. 23-24): V~_i = (exp*(front) - exp*(front + G_i)) . rho_n
            for i in range(n_sph):
                n_live = 0
                for q in range(n_lanes):
                    if theta[i, q] >= 0.0:
                        n_live += 1
                if n_live == 0:
                    for q in range(n_lanes):
                        vavg[i, q] = 0.0
                    continue
                if per_object:
                    oi = sl_object[i]
                    for k in range(n2):
                        for q in range(n_lanes):
                            fr[k, q] = pre[oi, k, q]
                else:
                    for k in range(n2):
                        for q in range(n_lanes):
                            fr[k, q] = 0.0
                for e in range(front_ptr[i], front_ptr[i + 1]):
                    j = front_idx[e]
                    for k in range(n2):
                        for q in range(n_lanes):
                            fr[k, q] += gs[j, k, q] if dist[j, q] < dist[i, q] else 0.0
                if hyb:
                    for k in range(n2):
                        for q in range(n_lanes):
                            live = theta[i, q] >= 0.0
                            xl[k, q] = fr[k, q] if live else 0.0
                            xl[k, n_lanes + q] = fr[k, q] + gs[i, k, q] if live else 0.0
                    _exp_hyb_columns(xl, r_max, tab_a, tab_b, threshold, pi_, pj, pk, pv, hl, vl, wl, coll, ksl,
                                     perml, el)
                    for q in range(n_lanes):
                        lane[0, q] = 0.0
                    for k in range(n2):
                        for q in range(n_lanes):
                            lane[0, q] += (el[k, q] - el[k, n_lanes + q]) * cosr[k, q]
                    for q in range(n_lanes):
                        vavg[i, q] = lane[0, q] if theta[i, q] >= 0.0 else 0.0
                else:
                    # OL is linear in f^ given |f^|: exp*(f) . rho = e^(f_0 / sqrt(4 pi)) (a sqrt(4 pi) rho_0
                    # + b f^ . rho^), so only norms and dot products are formed
                    for q in range(n_lanes):  # rows: |f^|^2, |o^|^2, f^ . rho^, o^ . rho^ (o = f + G_i)
                        lane[0, q] = 0.0
                        lane[1, q] = 0.0
                        lane[2, q] = 0.0
                        lane[3, q] = 0.0
                    for k in range(1, n2):
                        for q in range(n_lanes):
                            f = fr[k, q]
                            o = f + gs[i, k, q]
                            cr = cosr[k, q]
                            lane[0, q] += f * f
                            lane[1, q] += o * o
                            lane[2, q] += f * cr
                            lane[3, q] += o * cr
                    for q in range(n_lanes):
                        if theta[i, q] < 0.0:
                            vavg[i, q] = 0.0
                            continue
                        af, bf = _ol_coefficients(math.sqrt(lane[0, q]), r_max, tab_a, tab_b)
                        ao, bo = _ol_coefficients(math.sqrt(lane[1, q]), r_max, tab_a, tab_b)
                        f0 = fr[0, q]
                        o0 = f0 + gs[i, 0, q]
                        c0 = sqrt4pi * cosr[0, q]
                        vavg[i, q] = (math.exp(f0 / sqrt4pi) * (af * c0 + bf * lane[2, q])
                                      - math.exp(o0 / sqrt4pi) * (ao * c0 + bo * lane[3, q]))
            # average radiance (Eq. 18, or the cosine-weighted average) times V~, summed over the lights (Eq. 14)
            for c in range(3):
                for q in range(n_lanes):
                    isum[c, q] = 0.0
            for i in range(n_sph):
                n_live = 0
                for q in range(n_lanes):
                    if theta[i, q] >= 0.0:
                        n_live += 1
                if n_live == 0:
                    continue
                r00, r01, r02 = rot[i, 0, 0], rot[i, 0, 1], rot[i, 0, 2]
                r10, r11, r12 = rot[i, 1, 0], rot[i, 1, 1], rot[i, 1, 2]
                r20, r21, r22 = rot[i, 2, 0], rot[i, 2, 1], rot[i, 2, 2]
                for q in range(n_lanes):  # direction light -> receiver in the light's frame (Sec. 7.1)
                    ax, ay, az = axis[i, 0, q], axis[i, 1, q], axis[i, 2, q]
                    lane[4, q] = -(r00 * ax + r10 * ay + r20 * az)
                    lane[5, q] = -(r01 * ax + r11 * ay + r21 * az)
                    lane[6, q] = -(r02 * ax + r12 * ay + r22 * az)
                if cosine:
                    # E_n = s n.(Lu . K) - (n.b) L . K over pi s^2 (n . a), light frame (see irradiance_kernel_zh)
                    for q in range(n_lanes):
                        uk = min(max(theta[i, q], 0.0), THETA_MAX_K) * (N_THETA_K / THETA_MAX_K)
                        jk = min(int(math.floor(uk)), N_THETA_K - 1)
                        sk = uk - jk
                        for l in range(order + 1):
                            glog[l, q] = (1.0 - sk) * k_table[jk, l] + sk * k_table[jk + 1, l]
                    _basis_lanes(lane, 4, order + 1, ybuf, tmp)
                    for l in range(order + 1):
                        zs = _ZH_SCALE[l]
                        for k in range(l * l, (l + 1) * (l + 1)):
                            for q in range(n_lanes):
                                krot[k, q] = zs * glog[l, q] * ybuf[k, q]
                    # la[j, c] = sum_k krot_k Lu[i, k, (j, c)] and le[c] = sum_k krot_k L[i, k, c]
                    for t in range(9):
                        for q in range(n_lanes):
                            la[t, q] = 0.0
                    for k in range(n1):
                        for t in range(9):
                            m = lu[i, k, t]
                            for q in range(n_lanes):
                                la[t, q] += krot[k, q] * m
                    for c in range(3):
                        for q in range(n_lanes):
                            le[c, q] = 0.0
                    for k in range(n2):
                        for c in range(3):
                            m = emission[i, k, c]
                            for q in range(n_lanes):
                                le[c, q] += krot[k, q] * m
                    for q in range(n_lanes):  # rows 7, 8: n . a and the unoccluded V~' (_cap_visibility)
                        lane[7, q] = (recv[3, q] * axis[i, 0, q] + recv[4, q] * axis[i, 1, q]
                                      + recv[5, q] * axis[i, 2, q])
                    _cap_visibility_lanes(cos_t, i, lane, cos_zh, order, tmp)
                    for q in range(n_lanes):
                        nx, ny, nz = recv[3, q], recv[4, q], recv[5, q]
                        mx = r00 * nx + r10 * ny + r20 * nz
                        my = r01 * nx + r11 * ny + r21 * nz
                        mz = r02 * nx + r12 * ny + r22 * nz
                        s_i = sin_t[i, q] if theta[i, q] <= THETA_MAX_K else sin_k_max
                        nb_ = mx * lane[4, q] + my * lane[5, q] + mz * lane[6, q]
                        proj = math.pi * s_i * s_i * lane[7, q]
                        ok = theta[i, q] >= 0.0 and proj > 0.0 and lane[8, q] > 0.0
                        frac = min(max(vavg[i, q] / lane[8, q], 0.0), 1.0)
                        for c in range(3):
                            e_n = s_i * (mx * la[c, q] + my * la[3 + c, q] + mz * la[6 + c, q]) - nb_ * le[c, q]
                            isum[c, q] += e_n * frac if ok else 0.0
                else:
                    for q in range(n_lanes):
                        u = max(theta[i, q], 0.0) * (n_theta / (0.5 * math.pi))
                        jt = min(int(math.floor(u)), n_theta - 1)
                        st = u - jt
                        for l in range(order):
                            glog[l, q] = (1.0 - st) * w_table[jt, l] + st * w_table[jt + 1, l]
                    _basis_lanes(lane, 4, order, ybuf, tmp)
                    for l in range(order):
                        zs = _ZH_SCALE[l]
                        for k in range(l * l, (l + 1) * (l + 1)):
                            for q in range(n_lanes):
                                krot[k, q] = zs * glog[l, q] * ybuf[k, q]
                    for c in range(3):
                        for q in range(n_lanes):
                            le[c, q] = 0.0
                    for k in range(n2):
                        for c in range(3):
                            m = emission[i, k, c]
                            for q in range(n_lanes):
                                le[c, q] += krot[k, q] * m
                    for c in range(3):
                        for q in range(n_lanes):
                            isum[c, q] += le[c, q] * vavg[i, q] if theta[i, q] >= 0.0 else 0.0
            for q in range(nb):
                for c in range(3):
                    indirect_out[b0 + q, c] = isum[c, q]

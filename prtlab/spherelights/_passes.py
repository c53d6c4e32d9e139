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
tier; the exponentials run in :func:`prtlab.sh.exp`'s batched kernels. The
fast tier, ``_second_pass_fused``, runs the whole pass per block of 32
receivers (the SIMD lanes) in named steps (``_second_pass_block`` and below)
over four structured inputs: the lights, the tables, the exponential's tables
and the mode.
"""

from __future__ import annotations

import collections
import functools
import math

import numba
import numpy as np

from prtlab import sh
from prtlab._tasks import run_tasks, task_threads
from prtlab.sh._explog import _HYB_THRESHOLD, _ol_table
from prtlab.sh._gaunt import _gaunt_block
from prtlab.sh._product_kernels import _tile_product_prefix

from ._shadows import (
    _ZH_SCALE,
    BlockerLanes,
    LaneScratch,
    _add_rotated_zh,
    _adjust,
    _basis_lanes,
    _blocker_lanes,
    _blocker_log_knots,
    _lookup_log,
    _rotated_zh_lanes,
    blocker_log_table,
    environment_transfer,
    one_thread_below,
    transfer_matrix,
)
from ._square_kernels import SQUARE_COLUMNS, SQUARE_ORDERS, square_columns
from ._tables import (
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
#: Receivers below which :func:`second_pass`'s fused kernel runs on one thread (``one_thread_below``): under 32
#: blocks of ``_LANES`` receivers, a few ms of work.
_FUSED_SERIAL_BELOW = 1024


def first_pass(sample_points, sample_normals, sample_valid, centres, radii, env_sh, cell_sums, albedo_sh, *,
               exp_method: str = "hyb", ground=None, extra_irradiance=None, order: int | None = None,
               sample_weight=None, ground_projection=None, method: str = "fused") -> np.ndarray:
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
    cell_sums : (m, k*k) float
        Voronoi-cell sums ``(4 pi / N) Y_j`` (:func:`voronoi_cell_sums`), in the light's own frame, of the
        emission's SH order ``k``.
    albedo_sh : (S, k*k, 3) float
        Surface-albedo SH of each light, own frame.
    exp_method : {"hyb", "ol", "exact"}
    ground : (G, 7) float, optional
        Ground rectangles (:func:`prtlab.spherelights.ground_rectangles`) that hide
        the environment from the samples (an extension; see ``_ground``).
    ground_projection : (V, P*P) float, optional
        The valid samples' :func:`prtlab.spherelights.ground_hidden_projection` under ``ground`` (rows in the order of
        ``sample_points[sample_valid]``, ``P >= order + N - 1``), kept by a caller whose samples stay; default: made
        here. The ground's hidden transfer is then :func:`prtlab.spherelights.hidden_transfer` of it.
    extra_irradiance : (S, m, 3) float, optional
        Irradiance at the samples from other sources, added to the environment's
        (the local lights of Sec. 7.3, computed by :func:`second_pass` at the samples).
    order : int, optional
        SH order ``n <= k`` of the samples' visibility (Eq. 6); default the emission's order ``k``.
    sample_weight : (..., S, m) float, optional
        Weights of the samples' radiance (an extension: :func:`prtlab.spherelights.coverage_weights`); leading axes give one emission
        per set of weights from the same samples' light.
    method : {"fused", "numba"}
        How the samples' direct light (Eqs. 6-8) is found. ``"fused"`` (default): by :func:`second_pass`'s fused
        kernel (shadows only, every light a blocker; HYB, or OL without a ground); ``"numba"``:
        :func:`prtlab.spherelights.blocker_log_sum`, :func:`prtlab.sh.exp` and :func:`environment_transfer`,
        the specification of the fused tier (the two agree to rounding); ``exp_method="exact"`` takes it.

    Returns
    -------
    emission : (..., S, k*k, 3) float64
        ``L^c_S = (sum_j w_j L_{p_j} (4 pi / N) Y_j) * c_S`` (Eqs. 10-11; ``w_j = 1`` without ``sample_weight``)
        with ``L_p = E_p / pi`` the exit radiance of a white Lambertian surface
        (Eq. 8; the albedo enters through ``c_S``); own frame of each light.
    """
    from ._ground import ground_blocked_transfer, hidden_transfer
    from ._shadows import blocker_log_sum

    if method not in ("fused", "numba"):
        raise ValueError(f"method must be 'fused' or 'numba', got {method!r}")
    S, m = sample_valid.shape
    env = np.asarray(env_sh, dtype=np.float64)
    k = math.isqrt(np.asarray(albedo_sh).shape[1])
    order = k if order is None else int(order)
    radiance = np.zeros((S, m, 3))
    has_ground = ground is not None and len(ground) > 0
    fused = method == "fused" and (exp_method == "hyb" or (exp_method == "ol" and not has_ground))
    # a few thousand samples: the parallel kernels and matrix products of this pass run on one thread (the ground's
    # transfer in blocks, as tasks on the threads there were)
    threads = task_threads()
    with one_thread_below(np.asarray(sample_valid).size, _SERIAL_BELOW):
        if sample_valid.any():
            pts = np.asarray(sample_points, dtype=np.float64)[sample_valid]
            nrm = np.asarray(sample_normals, dtype=np.float64)[sample_valid]
            nrm = nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
            if ground_projection is not None and has_ground and np.shape(ground_projection)[0] != len(pts):
                raise ValueError(f"ground_projection must have a row per valid sample ({len(pts)}), got "
                                 f"{np.shape(ground_projection)}")
            if fused:  # Eqs. 6-8, V . T_n (and V, to take the ground's hidden transfer from T_n)
                n_all = np.asarray(radii).reshape(-1).shape[0]
                direct, _, vis = _second_pass_fused_call(
                    pts, nrm, centres, radii, np.arange(n_all), np.zeros((n_all, n_all), dtype=bool), np.eye(3),
                    np.zeros((n_all, order * order, 3)), env, "sphere", exp_method, False, False, order,
                    visibility=has_ground)
            else:
                vis = sh.exp(blocker_log_sum(pts, nrm, centres, radii, order), method=exp_method,
                             channels=False)  # Eq. 6
                direct = np.einsum("bk,bkc->bc", vis, environment_transfer(nrm, env, order))  # Eq. 8
            if has_ground:  # the environment the ground hides, seen through the same visibility
                hidden = (hidden_transfer(ground_projection, env, order) if ground_projection is not None
                          else ground_blocked_transfer(pts, nrm, env, ground, order=order, threads=threads))
                direct = direct - np.einsum("bk,bkc->bc", vis, hidden)
            radiance[sample_valid] = direct / np.pi
        if extra_irradiance is not None:
            extra = np.asarray(extra_irradiance, dtype=np.float64)
            if extra.shape != (S, m, 3):
                raise ValueError(f"extra_irradiance must have shape {(S, m, 3)} (lights, samples, RGB), "
                                 f"got {extra.shape}")
            radiance += np.where(sample_valid[..., None], extra, 0.0) / np.pi
        if sample_weight is not None:
            weight = np.asarray(sample_weight, dtype=np.float64)
            if weight.shape[-2:] != (S, m):
                raise ValueError(f"sample_weight must have shape (..., {S}, {m}) (lights, samples), got {weight.shape}")
            light = np.matmul(cell_sums.T, weight[..., None] * radiance)  # (..., S, k*k, 3)
            return sh.product(light, np.asarray(albedo_sh, dtype=np.float64), k, channels=True)
        light = np.matmul(cell_sums.T, radiance)  # Eq. 10: (S, k*k, 3) (numpy's einsum took 40 times as long)
    return sh.product(light, np.asarray(albedo_sh, dtype=np.float64), k, channels=True)  # Eq. 11


def second_pass(points, normals, centres, radii, sl_object, intersect, sl_rotation, emission, env_sh, *,
                blocking: str = "object", exp_method: str = "hyb", indirect: bool = True,
                average: str = "cosine", method: str = "fused", order: int | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """Direct and indirect irradiance at receivers (Eqs. 8, 12-24).

    Parameters
    ----------
    points, normals : (B, 3) float
    centres, radii, sl_object, intersect
        As :func:`accumulate_blockers`.
    sl_rotation : (S, 3, 3) float
        World-from-light rotation of each light (its object's rotation).
    emission : (S, m*m, 3) float
        ``L^c`` of each light in its own frame (:func:`first_pass`), of SH order ``m >= n``.
    env_sh : (N*N, 3) float
        Environment radiance of any order ``N >= n`` (``3n - 2``: exact transfer).
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
    order : int, optional
        SH order ``n`` of the visibility (the direct light and ``V~``); default the emission's. A higher
        emission order ``m`` sharpens the lights' radiance (their average radiance, Eq. 18 or the cosine form)
        at no cost to the exponentials (the paper: one order for both).

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
    env = np.asarray(env_sh, dtype=np.float64)
    m = math.isqrt(np.asarray(emission).shape[-2])
    order = m if order is None else int(order)
    if not 1 <= order <= m:
        raise ValueError(f"order must be between 1 and the emission's SH order {m}, got {order}")
    B, S = p.shape[0], np.asarray(centres).reshape(-1, 3).shape[0]
    if B == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    if method not in ("numba", "reference", "fused"):
        raise ValueError(f"method must be 'fused', 'numba' or 'reference', got {method!r}")
    if average not in ("cosine", "paper"):
        raise ValueError(f"average must be 'cosine' or 'paper', got {average!r}")
    if method == "fused" and exp_method in ("hyb", "ol"):  # the kernel normalises the normals
        return _second_pass_fused_call(p, n, centres, radii, sl_object, intersect, sl_rotation, emission, env,
                                       blocking, exp_method, indirect, average == "cosine", order)[:2]
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
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
    (``"cosine"``). ``order`` is the visibility's; the emission may have a higher one (its own shape).
    """
    rows_b, rows_s = np.nonzero(theta >= 0)
    if rows_b.size == 0:
        return rows_b, rows_s, np.zeros((0, 3))
    m = math.isqrt(np.asarray(emission).shape[1])  # the emission's order (>= order)
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
        w = sh.zh_rotate(w_theta_zh(th, m), local)
        l_avg = np.einsum("tk,tkc->tc", w, em[rows_s])
    else:
        # E_n = s n.(Lu . K) - (n.b) L . K in the light's frame, over pi s^2 (n . a)
        k = sh.zh_rotate(irradiance_kernel_zh(th, m + 1), local)
        lu = emission_times_direction(em)
        n_loc = np.einsum("tji,tj->ti", rot[rows_s], n[rows_b])
        s_t = np.sin(np.minimum(th, THETA_MAX_K))
        e_n = (s_t[:, None] * np.einsum("tj,tjkc,tk->tc", n_loc, lu[rows_s], k)
               - np.einsum("tj,tj->t", n_loc, local)[:, None] * np.einsum("tkc,tk->tc", em[rows_s], k[:, :m * m]))
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


def emission_times_direction(emission) -> np.ndarray:
    """SH of ``L(u) u_j`` for each light and coordinate ``j`` (x, y, z): ``(S, 3, (n+1)**2, C)``, exact.

    Parameters
    ----------
    emission : (S, n*n, C) float
        Light SH in the light's own frame.
    """
    em = np.asarray(emission, dtype=np.float64)
    x = _coordinate_products(math.isqrt(em.shape[1]))
    # one matrix product per light, rows (j, q): 25 times faster than the same sums as an einsum
    return np.matmul(x.reshape(-1, x.shape[2]), em).reshape(em.shape[0], 3, x.shape[1], em.shape[2])


# --------------------------------------------------------------------------- fused second pass (the fast tier)


def _emission_dirs(em) -> np.ndarray:
    """``(S, (m+1)**2, 9)`` :func:`emission_times_direction` of ``em (S, m*m, 3)``, columns ``(j, c)``, as the fused
    pass reads it. The last result is kept, keyed by the emission's bytes: a frame passes the same emission to
    every receiving object's call."""
    key = (em.shape, em.tobytes())
    if _EMISSION_DIRS[0] is None or _EMISSION_DIRS[0][0] != key:
        n_sph = em.shape[0]
        dirs = np.ascontiguousarray(emission_times_direction(em).transpose(0, 2, 1, 3).reshape(n_sph, -1, 9))
        _EMISSION_DIRS[0] = (key, dirs)
    return _EMISSION_DIRS[0][1].copy()


_EMISSION_DIRS: list = [None]


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
#: Most squarings of a HYB exponential (a bound: ``|f^| <= threshold 2^1100`` for every finite ``|f^|``).
_MAX_SQUARINGS = 1100
#: Halvings of a HYB exponential decided by selects (:func:`_exp_hyb_columns`); more take a loop.
_SELECT_HALVINGS = 12


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


# Structured inputs of the fused kernels (numba takes namedtuples of arrays and scalars as one argument).

#: The spherical lights as emitters and blockers (world space): ``centres (S, 3)``, ``radii (S,)``,
#: ``light_object (S,)`` int, ``object_centres (O, 3)``, the candidate front lists of :func:`_front_lists`
#: (``front_ptr (S+1,)``, ``front_idx``), ``rotation (S, 3, 3)`` world-from-light, ``emission (S, n*n, 3)``
#: ``L^c`` in the light's frame and ``emission_dir (S, (n+1)**2, 9)`` the SH of ``L^c(u) u_j``
#: (:func:`emission_times_direction`, columns ``(j, c)``), ``single (O,)`` bool: the object has one light (a light
#: of such an object is alone in it).
_Lights = collections.namedtuple("_Lights", ["centres", "radii", "light_object", "object_centres", "front_ptr",
                                             "front_idx", "rotation", "emission", "emission_dir", "single"])
#: Tables read per receiver: ``blocker_log`` (:func:`blocker_log_table`) and its knots ``blocker_knots``
#: (:func:`_blocker_log_knots`), ``transfer ((2n-1)**2, 3 n*n)`` the environment transfer matrix
#: (:func:`transfer_matrix`, columns ``(c, k)``), the clamped-cosine ZH of orders ``2n - 1`` (``cosine_hi``) and
#: ``n`` (``cosine``), and the ZH tables of ``w_theta`` (Eq. 18) and of the irradiance kernel (the
#: cosine-weighted average).
_Tables = collections.namedtuple("_Tables", ["blocker_log", "blocker_knots", "transfer", "cosine_hi", "cosine",
                                             "w_theta", "irradiance_kernel"])
#: The OL / HYB exponential, as :func:`prtlab.sh.exp`: the OL table (``r_max``, ``ol_a``, ``ol_b``), the HYB
#: threshold and the symmetric Gaunt pairs of a square (``sq_i, sq_j, sq_k, sq_v``, :func:`_symmetric_gaunt`).
_ExpTables = collections.namedtuple("_ExpTables", ["r_max", "ol_a", "ol_b", "threshold", "sq_i", "sq_j", "sq_k",
                                                   "sq_v"])
#: What the pass computes: SH order (of the visibility), per-object blocking (else per sphere), the indirect light,
#: HYB (else OL), the cosine-weighted average radiance (else the paper's Eq. 18), the receivers per block, ``object_chain``
#: (per object, HYB): the exponentials of the objects' prefix sums are formed once per lane and read by the lights
#: alone in their object (see :func:`_chain_exponentials`), and the SH order of the emission (at least ``order``).
_Mode = collections.namedtuple("_Mode", ["order", "per_object", "indirect", "hyb", "cosine", "n_lanes",
                                         "object_chain", "emission_order"])
#: Scratch of a HYB exponential of ``M`` columns (:func:`_exp_hyb_columns`): ``value, square, out
#: (n*n, M)`` (``value``: at least ``SQUARE_COLUMNS`` columns), ``columns (10, M)`` (per column ``|f^|^2``, the
#: scale ``2^-k``, OL's ``a sqrt(4 pi)`` and ``b``, then the halved norm, its table knot and the table's ``a`` and
#: ``b`` at the knot and the next), ``n_squarings (M,)`` and ``perm
#: (M + _MAX_SQUARINGS + 2,)`` int.
_HybScratch = collections.namedtuple("_HybScratch", ["value", "square", "columns", "n_squarings", "perm",
                                                     "out"])
#: Scratch of one parallel task, the lanes ``L`` last: ``recv (6, L)`` receiver points and normals,
#: ``blockers`` (:class:`BlockerLanes`), ``lane`` (:class:`LaneScratch`), ``normal_basis ((2n-1)**2, L)`` the
#: SH basis at the normals, ``transfer (3 n*n, L)``, ``cosine (n*n, L)`` the rotated clamped cosine ``rho_n``;
#: per object ``object_dist (O, L)``, ``object_order (O,)``, ``object_log, object_prefix (O, n*n, L)``,
#: ``running (n*n,)``, ``object_rank (O, L)`` int (position in the lane's order), ``chain (O, n*n, L)`` the prefix
#: sums by rank and ``chain_exp (O + 1, n*n, L)`` their HYB exponentials (``chain_exp[O]``: of all the logs);
#: ``front (n*n, L)`` and ``pair_log (n*n, 2L)`` (front, front + own) of the current light,
#: ``sums (4, L)`` per-lane sums, ``visibility (S, L)`` the ``V~`` of every light, ``light_dir (3, L)`` the
#: direction light -> receiver in the light's frame, ``cos_na, open_visibility (L,)``, ``kernel (1, (n+1)**2,
#: L)`` the rotated average-radiance ZH kernel, ``radiance_dir (9, L)`` and ``radiance (3, L)`` its products with
#: the emission; ``direct, indirect (3, L)`` the block's results; ``exp_direct`` and ``exp_light`` the HYB scratch
#: of ``L`` and ``2L`` columns; ``transfer_rows ((2n-1)**2, L)`` and ``transfer_index ((2n-1)**2,)`` int the
#: scaled basis rows of the clamped cosine that do not vanish and their coefficients; ``transfer_normals (3, L)``
#: the normals ``normal_basis`` and ``transfer`` were made for (NaN before the task's first block).
_BlockScratch = collections.namedtuple("_BlockScratch", [
    "recv", "blockers", "lane", "normal_basis", "transfer", "cosine", "object_dist", "object_order",
    "object_log", "object_prefix", "running", "front", "pair_log", "sums", "visibility", "light_dir", "cos_na",
    "open_visibility", "kernel", "radiance_dir", "radiance", "direct", "indirect", "exp_direct", "exp_light",
    "object_rank", "chain", "chain_exp", "transfer_rows", "transfer_index", "transfer_normals"])


def _fused_inputs(centres, radii, sl_object, intersect, sl_rotation, emission, env, blocking, exp_method,
                  indirect, cosine, order):
    """The structured inputs ``(lights, tables, exp_tables, mode)`` of :func:`_second_pass_fused`. The last few
    are kept, keyed by the bytes of every input: a frame makes the same call for each receiving object, and
    packing them (the transfer matrix, the lights' arrays, the tables) took about 0.4 ms a call. The kernel only
    reads them."""
    arrays = [np.asarray(x) for x in (centres, radii, sl_object, intersect, sl_rotation, emission, env)]
    key = (tuple((x.dtype.str, x.shape, x.tobytes()) for x in arrays), blocking, exp_method, bool(indirect),
           bool(cosine), int(order))
    kept = _FUSED_INPUTS.get(key)
    if kept is not None:
        return kept
    m = math.isqrt(np.asarray(emission).shape[-2])
    c, r, obj, inter, obj_centres = _light_arrays(centres, radii, sl_object, intersect)
    n_sph, hi = c.shape[0], 2 * order - 1
    transfer = np.ascontiguousarray(transfer_matrix(env, order).reshape(hi * hi, order * order, 3)
                                    .transpose(0, 2, 1).reshape(hi * hi, 3 * order * order))
    # writeable C copies: one compiled signature whatever the caller passes
    rot = np.array(np.broadcast_to(np.asarray(sl_rotation, dtype=np.float64), (n_sph, 3, 3)), order="C")
    em = np.array(np.asarray(emission, dtype=np.float64).reshape(n_sph, m * m, 3), order="C")
    if cosine and indirect and n_sph:
        em_dir = _emission_dirs(em)
    else:
        em_dir = np.zeros((n_sph, (m + 1) ** 2, 9))
    front_ptr, front_idx = _front_lists(obj, inter, blocking == "object")
    n_obj = obj_centres.shape[0]
    single = np.bincount(obj, minlength=n_obj) == 1
    lights = _Lights(np.array(c), np.array(r), np.array(obj), obj_centres, front_ptr, front_idx, rot, em, em_dir,
                     single)
    tables = _Tables(blocker_log_table(order), _blocker_log_knots(), transfer,
                     np.ascontiguousarray(sh.clamped_cosine_zh(hi)), np.ascontiguousarray(sh.clamped_cosine_zh(order)),
                     np.ascontiguousarray(_w_theta_table(m)),
                     np.ascontiguousarray(_irradiance_kernel_table(m + 1)))
    r_max, tab_a, tab_b = _ol_table(order)
    exp_tables = _ExpTables(float(r_max), tab_a, tab_b, float(_HYB_THRESHOLD), *_symmetric_gaunt(order))
    mode = _Mode(int(order), bool(blocking == "object"), bool(indirect and n_sph > 0), bool(exp_method == "hyb"),
                 bool(cosine), int(_LANES), bool(blocking == "object" and exp_method == "hyb" and
                                                 2 * int(single.sum()) > n_obj + 1), int(m))
    packed = (lights, tables, exp_tables, mode)
    for old in list(_FUSED_INPUTS)[: max(0, len(_FUSED_INPUTS) - _FUSED_KEPT + 1)]:
        del _FUSED_INPUTS[old]
    _FUSED_INPUTS[key] = packed
    return packed


#: The last packed inputs of :func:`_fused_inputs` by key, at most ``_FUSED_KEPT``: a frame asks for a set for its
#: first pass, one for its second pass's receiving objects and, with a ground, one for the ground's texture.
_FUSED_INPUTS: dict = {}
_FUSED_KEPT = 4


def _second_pass_fused_call(p, n, centres, radii, sl_object, intersect, sl_rotation, emission, env, blocking,
                            exp_method, indirect, cosine, order, visibility: bool = False):
    """Packs the inputs of :func:`_second_pass_fused` and runs it: ``(direct, indirect, vis)``, ``(B, 3)``
    each and ``vis (B, n*n)`` the direct light's visibility ``exp*(sum of the logs)`` with ``visibility`` (HYB
    only), else ``(0, n*n)``; ``n``: the normals as given (the kernel normalises them); ``order``: the
    visibility's SH order (the emission's may be higher)."""
    if visibility and exp_method != "hyb":
        raise ValueError(f"the visibility is formed with exp_method='hyb' only, got {exp_method!r}")
    lights, tables, exp_tables, mode = _fused_inputs(centres, radii, sl_object, intersect, sl_rotation, emission,
                                                     env, blocking, exp_method, indirect, cosine, order)
    direct = np.empty((p.shape[0], 3))
    ind = np.empty((p.shape[0], 3))
    vis = np.empty((p.shape[0] if visibility else 0, order * order))
    # writeable C arrays (one compiled signature), not copied when they are already: the kernel only reads them
    p, n = (x if x.flags.c_contiguous and x.flags.writeable else np.array(x, order="C") for x in (p, n))
    n_blocks = -(-p.shape[0] // _LANES)
    threads = min(task_threads(), n_blocks)
    if p.shape[0] < _FUSED_SERIAL_BELOW and threads > 1:
        # a receiving object of a few blocks: runs of whole blocks as tasks, each on one thread (a block's
        # receivers and results are the same whichever run it is in)
        step = _LANES * -(-n_blocks // threads)
        run_tasks([functools.partial(_second_pass_fused, p[s:s + step], n[s:s + step], lights, tables, exp_tables,
                                     mode, direct[s:s + step], ind[s:s + step], vis[s:s + step], 1)
                   for s in range(0, p.shape[0], step)])
        return direct, ind, vis
    with one_thread_below(p.shape[0], _FUSED_SERIAL_BELOW):  # a receiving object of a few blocks
        _second_pass_fused(p, n, lights, tables, exp_tables, mode, direct, ind, vis, numba.get_num_threads())
    return direct, ind, vis


@numba.njit(cache=True, parallel=True, error_model="numpy", nogil=True)
def _second_pass_fused(points, normals, lights, tables, exp_tables, mode, direct_out, indirect_out, visibility_out,
                       threads):
    """Second pass (Eqs. 8, 14, 18, 21-24) over blocks of ``mode.n_lanes`` receivers, the receivers of a block
    as the SIMD lanes of the inner loops: blocker logs, direct light, then per light the front sums,
    exponentials, average visibility and average radiance. Same quantities, to rounding, as the composed tier
    (``method="numba"``). ``normals`` need not be unit: each is divided by its norm as ``second_pass``'s
    numpy tiers do. ``n_lanes`` is a run-time value, not a compile-time constant: LLVM fully unrolls constant
    16-trip loops into scalar code instead of vectorising them.

    ``threads`` tasks (numba's thread count), each with its scratch, task ``t`` taking the blocks ``t, t + T, t +
    2T, ...``: the threads' shares of the receivers interleave, so a run of costlier receivers (the objects' after
    the ground's) is split between them. The results do not depend on ``threads``.

    Structure (measured, see the commits that split it): the per-block steps take the namedtuples and unpack
    them into locals once per block (a namedtuple passed to a compiled call is flattened into hundreds of
    arguments, and each unpacked array costs two atomic reference-count updates); they are inlined, except
    :func:`_add_cosine_averages` (inlined, the one large function it made ran that step 19 % slower). The
    per-light steps inside them take arrays."""
    n_recv = points.shape[0]
    n_lanes = mode.n_lanes
    n_blocks = (n_recv + n_lanes - 1) // n_lanes
    n_tasks = max(1, min(threads, n_blocks))
    for task in numba.prange(n_tasks):
        scratch = _block_scratch(lights.centres.shape[0], lights.object_centres.shape[0], mode.order,
                                 mode.emission_order, n_lanes)
        for block in range(task, n_blocks, n_tasks):
            first = block * n_lanes
            _second_pass_block(points, normals, first, min(n_lanes, n_recv - first), lights, tables, exp_tables,
                               mode, scratch, direct_out, indirect_out, visibility_out)


@numba.njit(cache=True)
def _hyb_scratch(n2, m):
    """:data:`_HybScratch` for ``m`` columns of ``n2`` coefficients (``value``: at least ``SQUARE_COLUMNS``
    columns, the row stride of the generated squares)."""
    return _HybScratch(np.empty((n2, max(m, SQUARE_COLUMNS))), np.empty((n2, m)), np.empty((10, m)),
                       np.empty(m, dtype=np.int64), np.empty(m + _MAX_SQUARINGS + 2, dtype=np.int64), np.empty((n2, m)))


@numba.njit(cache=True)
def _block_scratch(n_sph, n_obj, order, emission_order, n_lanes):
    """:data:`_BlockScratch` of one task (the lane's ZH buffers and the kernel sized for the larger order)."""
    n2, hi = order * order, 2 * order - 1
    top = max(order, emission_order) + 1
    n1 = top * top
    blockers = BlockerLanes(np.empty((n_sph, n2, n_lanes)), np.empty((n2, n_lanes)), np.empty((n_sph, n_lanes)),
                            np.empty((n_sph, n_lanes)), np.empty((n_sph, n_lanes)), np.empty((n_sph, n_lanes)),
                            np.empty((n_sph, 3, n_lanes)))
    lane = LaneScratch(np.empty((top, n_lanes)), np.empty((n1, n_lanes)), np.empty((7, n_lanes)))
    obj_log, obj_prefix = np.empty((n_obj, n2, n_lanes)), np.empty((n_obj, n2, n_lanes))
    vis = np.empty((n_sph, n_lanes))
    return _BlockScratch(
        np.empty((6, n_lanes)), blockers, lane,  # recv, blockers, lane
        np.empty((hi * hi, n_lanes)), np.empty((3 * n2, n_lanes)), np.empty((n2, n_lanes)),  # normal_basis .. cosine
        np.empty((n_obj, n_lanes)), np.empty(n_obj, dtype=np.int64), obj_log, obj_prefix,  # object_*
        np.empty(n2), np.empty((n2, n_lanes)), np.empty((n2, 2 * n_lanes)),  # running, front, pair_log
        np.empty((4, n_lanes)), vis, np.empty((3, n_lanes)),  # sums, visibility, light_dir
        np.empty(n_lanes), np.empty(n_lanes), np.empty((1, n1, n_lanes)),  # cos_na, open_visibility, kernel
        np.empty((9, n_lanes)), np.empty((3, n_lanes)), np.empty((3, n_lanes)), np.empty((3, n_lanes)),
        _hyb_scratch(n2, n_lanes), _hyb_scratch(n2, 2 * n_lanes),
        np.empty((n_obj, n_lanes), dtype=np.int64), np.empty((n_obj, n2, n_lanes)),  # object_rank, chain
        np.empty((n_obj + 1, n2, n_lanes)),  # chain_exp
        np.empty((hi * hi, n_lanes)), np.empty(hi * hi, dtype=np.int64),  # transfer_rows, transfer_index
        np.full((3, n_lanes), np.nan))  # transfer_normals


@numba.njit(cache=True, error_model="numpy", inline="always")
def _unit_normal(nx, ny, nz):
    """``n / |n|`` as ``n / np.linalg.norm(n, axis=1, keepdims=True)`` gives it, bit for bit: numpy sums the
    squares in order, ``(x^2 + y^2) + z^2`` (checked by ``tests/spherelights/test_shadows_speed_paths.py``)."""
    norm = math.sqrt((nx * nx + ny * ny) + nz * nz)
    return nx / norm, ny / norm, nz / norm


@numba.njit(cache=True, error_model="numpy", inline="always")
def _second_pass_block(points, normals, first, n_valid, lights, tables, exp_tables, mode, scratch, direct_out,
                       indirect_out, visibility_out):
    """The second pass of the receivers ``first .. first + n_valid - 1`` (one block; a partial block repeats
    its last receiver in the remaining lanes); the normals divided by their norms as they are read. With HYB and
    rows in ``visibility_out (B, n*n)``, the direct light's visibility ``exp*(sum of the logs)`` goes there too."""
    recv, direct, indirect = scratch.recv, scratch.direct, scratch.indirect
    for q in range(recv.shape[1]):
        b = first + min(q, n_valid - 1)
        for t in range(3):
            recv[t, q] = points[b, t]
        recv[3, q], recv[4, q], recv[5, q] = _unit_normal(normals[b, 0], normals[b, 1], normals[b, 2])
    _blocker_lanes(recv, lights.centres, lights.radii, tables, mode.order, scratch.blockers, scratch.lane,
                   mode.indirect)  # shadows only: the logs' sum alone
    _direct_lanes(tables, exp_tables, mode.hyb, mode.order, scratch)
    if mode.hyb and visibility_out.shape[0]:
        vis = scratch.exp_direct.out
        for q in range(n_valid):
            for k in range(visibility_out.shape[1]):
                visibility_out[first + q, k] = vis[k, q]
    if mode.indirect:
        _indirect_lanes(lights, tables, exp_tables, mode, scratch)
    for q in range(n_valid):
        for c in range(3):
            direct_out[first + q, c] = direct[c, q]
            indirect_out[first + q, c] = indirect[c, q] if mode.indirect else 0.0


@numba.njit(cache=True, error_model="numpy", inline="always")
def _environment_transfer_lanes(cosine_hi, transfer, order, scratch):
    """``T_n = cos_{2n-1}(n) @ M`` per lane into ``scratch.transfer`` (rows ``(c, k)``): the exact projection of
    ``L cos`` (see :func:`environment_transfer`; the clamped cosine's odd bands > 1 vanish). Leaves the SH basis
    at the normals in ``scratch.normal_basis``. Kept when every lane's normal is the one they were made for (a
    task's blocks of a flat ground: the same normals, so the same values)."""
    basis, trans, rows, index = scratch.normal_basis, scratch.transfer, scratch.transfer_rows, scratch.transfer_index
    recv, kept = scratch.recv, scratch.transfer_normals
    hi = 2 * order - 1
    n_lanes, n_out = trans.shape[1], trans.shape[0]
    same = True
    for q in range(n_lanes):
        same &= recv[3, q] == kept[0, q] and recv[4, q] == kept[1, q] and recv[5, q] == kept[2, q]
    if same:
        return
    for t in range(3):
        for q in range(n_lanes):
            kept[t, q] = recv[3 + t, q]
    _basis_lanes(scratch.recv, 3, hi, basis, scratch.lane.tmp)
    n_rows = 0  # the rows of the clamped cosine that do not vanish, scaled: rows[j] = f_l Y_k(n), k = index[j]
    for l in range(hi):
        if cosine_hi[l] == 0.0:
            continue
        f = _ZH_SCALE[l] * cosine_hi[l]
        for k in range(l * l, (l + 1) * (l + 1)):
            for q in range(n_lanes):
                rows[n_rows, q] = f * basis[k, q]
            index[n_rows] = k
            n_rows += 1
    for t in range(n_out):
        for q in range(n_lanes):
            trans[t, q] = 0.0
    # four rows per pass over ``trans`` (one load and store of an output row per four products)
    j = 0
    while j + 4 <= n_rows:
        k0, k1, k2, k3 = index[j], index[j + 1], index[j + 2], index[j + 3]
        for t in range(n_out):
            m0, m1, m2, m3 = transfer[k0, t], transfer[k1, t], transfer[k2, t], transfer[k3, t]
            for q in range(n_lanes):
                trans[t, q] += (rows[j, q] * m0 + rows[j + 1, q] * m1 + rows[j + 2, q] * m2
                                + rows[j + 3, q] * m3)
        j += 4
    for jj in range(j, n_rows):
        k = index[jj]
        for t in range(n_out):
            m = transfer[k, t]
            for q in range(n_lanes):
                trans[t, q] += rows[jj, q] * m


@numba.njit(cache=True, error_model="numpy", inline="always")
def _direct_lanes(tables, exp_tables, hyb, order, scratch):
    """Direct irradiance ``E = T_n . exp*(sum of the blocker logs)`` per lane (Eq. 8) into ``scratch.direct``."""
    _environment_transfer_lanes(tables.cosine_hi, tables.transfer, order, scratch)
    n2 = order * order
    total, trans, direct, sums = scratch.blockers.total_log, scratch.transfer, scratch.direct, scratch.sums
    n_lanes = total.shape[1]
    for c in range(3):
        for q in range(n_lanes):
            direct[c, q] = 0.0
    if hyb:
        _exp_hyb_columns(total, exp_tables, scratch.exp_direct)
        vis = scratch.exp_direct.out
        for c in range(3):
            for k in range(n2):
                for q in range(n_lanes):
                    direct[c, q] += trans[c * n2 + k, q] * vis[k, q]
        return
    # OL: exp*(f) . T = e^(f_0 / sqrt(4 pi)) (a sqrt(4 pi) T_0 + b f^ . T^), a and b functions of |f^|
    for q in range(n_lanes):
        sums[1, q] = 0.0
    for k in range(1, n2):
        for q in range(n_lanes):
            sums[1, q] += total[k, q] * total[k, q]
    for c in range(3):
        for k in range(1, n2):
            for q in range(n_lanes):
                direct[c, q] += trans[c * n2 + k, q] * total[k, q]
    sqrt4pi = math.sqrt(4.0 * math.pi)
    r_max, ol_a, ol_b = exp_tables.r_max, exp_tables.ol_a, exp_tables.ol_b
    for q in range(n_lanes):
        a, b = _ol_coefficients(math.sqrt(sums[1, q]), r_max, ol_a, ol_b)
        dc = math.exp(total[0, q] / sqrt4pi)
        for c in range(3):
            direct[c, q] = dc * (a * sqrt4pi * trans[c * n2, q] + b * direct[c, q])


@numba.njit(cache=True, error_model="numpy", inline="always")
def _indirect_lanes(lights, tables, exp_tables, mode, scratch):
    """Indirect irradiance ``sum_i L~_i V~_i`` per lane (Eq. 14) into ``scratch.indirect``: the average
    visibility of every light (front sums and exponentials, Eqs. 23-24), then its average radiance (Eq. 18 or
    the cosine-weighted average)."""
    n2 = mode.order * mode.order
    ind = scratch.indirect
    for c in range(3):
        for q in range(ind.shape[1]):
            ind[c, q] = 0.0
    _rotated_cosine(tables.cosine, mode.order, scratch)
    if mode.per_object:
        _object_prefix_logs(lights, n2, mode.object_chain, scratch)
    if mode.hyb:
        if mode.object_chain:
            _chain_exponentials(exp_tables, n2, scratch)
        _average_visibility_hyb(lights, exp_tables, mode.per_object, mode.object_chain, n2, scratch)
    else:
        _average_visibility_ol(lights, exp_tables, mode.per_object, n2, scratch)
    if mode.cosine:
        _add_cosine_averages(lights, tables, mode.order, mode.emission_order, scratch)
    else:
        _add_paper_averages(lights, tables, mode.emission_order, scratch)


@numba.njit(cache=True, error_model="numpy", inline="always")
def _rotated_cosine(cosine, order, scratch):
    """The clamped cosine ``rho_n`` rotated to each lane's normal, ``scratch.cosine``, from ``normal_basis``."""
    basis, rho = scratch.normal_basis, scratch.cosine
    for l in range(order):
        f = _ZH_SCALE[l] * cosine[l]
        for k in range(l * l, (l + 1) * (l + 1)):
            for q in range(rho.shape[1]):
                rho[k, q] = f * basis[k, q]


@numba.njit(cache=True, error_model="numpy", inline="always")
def _object_prefix_logs(lights, n2, object_chain, scratch):
    """Per-object blocking (Sec. 7.2): ``scratch.object_prefix[o, :, q]`` the sum of the logs of every light
    of the objects closer to lane ``q`` than ``o`` (object-centre distance; ties by index, a stable order as
    the other tiers); with ``object_chain`` also ``scratch.chain[t]``, the same sums by rank ``t``
    (``object_rank``), and ``prefix`` only of the objects of several lights (a light alone in its object reads the
    chain)."""
    recv, log = scratch.recv, scratch.blockers.log
    dist2, obj_log, prefix = scratch.object_dist, scratch.object_log, scratch.object_prefix
    by_dist, running, rank, chain = scratch.object_order, scratch.running, scratch.object_rank, scratch.chain
    centres, light_object, single = lights.object_centres, lights.light_object, lights.single
    n_obj, n_lanes = dist2.shape
    for o in range(n_obj):
        cx, cy, cz = centres[o, 0], centres[o, 1], centres[o, 2]
        for q in range(n_lanes):
            ex = cx - recv[0, q]
            ey = cy - recv[1, q]
            ez = cz - recv[2, q]
            dist2[o, q] = ex * ex + ey * ey + ez * ez
        for k in range(n2):
            for q in range(n_lanes):
                obj_log[o, k, q] = 0.0
    for s in range(light_object.shape[0]):
        o = light_object[s]
        for k in range(n2):
            for q in range(n_lanes):
                obj_log[o, k, q] += log[s, k, q]
    for q in range(n_lanes):
        for o in range(n_obj):
            by_dist[o] = o
        for o in range(1, n_obj):  # insertion sort by (distance, index)
            t = by_dist[o]
            j = o - 1
            while j >= 0 and dist2[by_dist[j], q] > dist2[t, q]:
                by_dist[j + 1] = by_dist[j]
                j -= 1
            by_dist[j + 1] = t
        for k in range(n2):
            running[k] = 0.0
        for t in range(n_obj):
            o = by_dist[t]
            rank[o, q] = t
            if object_chain:
                for k in range(n2):
                    chain[t, k, q] = running[k]
            if not (object_chain and single[o]):
                for k in range(n2):
                    prefix[o, k, q] = running[k]
            for k in range(n2):
                running[k] += obj_log[o, k, q]


@numba.njit(cache=True, error_model="numpy", inline="always")
def _any_live(theta, i):
    """Whether light ``i`` is seen (not culled) from any lane."""
    for q in range(theta.shape[1]):
        if theta[i, q] >= 0.0:
            return True
    return False


@numba.njit(cache=True, error_model="numpy", inline="always")
def _front_log(i, per_object, light_object, front_ptr, front_idx, prefix, log, dist, front):
    """``front[k, q]``: the sum of the logs in front of light ``i`` at lane ``q`` (Eq. 23): per object the
    closer objects' ``prefix``, plus the lights of ``i``'s front list (``front_ptr``, ``front_idx``) closer to
    the lane than ``i`` (centre distance ``dist``)."""
    n2, n_lanes = front.shape
    if per_object:
        oi = light_object[i]
        for k in range(n2):
            for q in range(n_lanes):
                front[k, q] = prefix[oi, k, q]
    else:
        for k in range(n2):
            for q in range(n_lanes):
                front[k, q] = 0.0
    for e in range(front_ptr[i], front_ptr[i + 1]):
        j = front_idx[e]
        for k in range(n2):
            for q in range(n_lanes):
                front[k, q] += log[j, k, q] if dist[j, q] < dist[i, q] else 0.0


@numba.njit(cache=True, error_model="numpy", inline="always")
def _average_visibility_hyb(lights, exp_tables, per_object, object_chain, n2, scratch):
    """``scratch.visibility[i, q]``: ``V~_i = (exp*(front) - exp*(front + G_i)) . rho_n`` (Eqs. 23-24) of every
    light at every lane, the two exponentials HYB (0 where the light is culled). With ``object_chain``, a light
    alone in its object reads them from ``scratch.chain_exp`` at its object's rank and the next (its front is the
    prefix of its object and its front + own the next prefix, the same sums)."""
    light_object, front_ptr, front_idx = lights.light_object, lights.front_ptr, lights.front_idx
    rank, chain_exp, single = scratch.object_rank, scratch.chain_exp, lights.single
    log, dist, theta = scratch.blockers.log, scratch.blockers.dist, scratch.blockers.theta
    front, prefix, pair, hyb = scratch.front, scratch.object_prefix, scratch.pair_log, scratch.exp_light
    rho, vis, e = scratch.cosine, scratch.visibility, scratch.exp_light.out
    n_lanes = front.shape[1]
    for i in range(log.shape[0]):
        for q in range(n_lanes):
            vis[i, q] = 0.0
        if not _any_live(theta, i):
            continue
        if object_chain and single[light_object[i]]:
            oi = light_object[i]
            for k in range(n2):
                for q in range(n_lanes):
                    t = rank[oi, q]
                    vis[i, q] += (chain_exp[t, k, q] - chain_exp[t + 1, k, q]) * rho[k, q]
            for q in range(n_lanes):
                vis[i, q] = vis[i, q] if theta[i, q] >= 0.0 else 0.0
            continue
        _front_log(i, per_object, light_object, front_ptr, front_idx, prefix, log, dist, front)
        for k in range(n2):
            for q in range(n_lanes):
                live = theta[i, q] >= 0.0
                pair[k, q] = front[k, q] if live else 0.0
                pair[k, n_lanes + q] = front[k, q] + log[i, k, q] if live else 0.0
        _exp_hyb_columns(pair, exp_tables, hyb)
        for k in range(n2):
            for q in range(n_lanes):
                vis[i, q] += (e[k, q] - e[k, n_lanes + q]) * rho[k, q]
        for q in range(n_lanes):
            vis[i, q] = vis[i, q] if theta[i, q] >= 0.0 else 0.0


@numba.njit(cache=True, error_model="numpy", inline="always")
def _chain_exponentials(exp_tables, n2, scratch):
    """``scratch.chain_exp[t] = exp*(chain[t])`` (HYB). Rank 0 has nothing in front, ``chain[0] = 0``: its
    exponential is written as the HYB exponential of a zero column makes it (OL's ``a(0) sqrt(4 pi)``, then zeros
    times ``b(0)``). The last, ``chain_exp[O]``, is the exponential of the sum of every log, which the direct light
    has formed (:func:`_direct_lanes`, from the logs summed in the lights' order; the chain's order would give the
    same sum to rounding): it is read from ``exp_direct``, which must still hold it. The ranks between, two per
    exponential of ``2L`` columns, an odd number of them leaving the last alone (``L`` columns, in
    ``exp_direct``'s scratch after the direct light's is copied)."""
    chain, chain_exp, pair, hyb = scratch.chain, scratch.chain_exp, scratch.pair_log, scratch.exp_light
    e, direct = hyb.out, scratch.exp_direct.out
    n_lanes = pair.shape[1] // 2
    n_obj = chain.shape[0]
    a, b = _ol_coefficients(0.0, exp_tables.r_max, exp_tables.ol_a, exp_tables.ol_b)
    for q in range(n_lanes):
        chain_exp[0, 0, q] = a * math.sqrt(4.0 * math.pi)
    for k in range(1, n2):
        for q in range(n_lanes):
            chain_exp[0, k, q] = b * 0.0
    for k in range(n2):
        for q in range(n_lanes):
            chain_exp[n_obj, k, q] = direct[k, q]
    for t in range(1, n_obj - 1, 2):
        for k in range(n2):
            for q in range(n_lanes):
                pair[k, q] = chain[t, k, q]
                pair[k, n_lanes + q] = chain[t + 1, k, q]
        _exp_hyb_columns(pair, exp_tables, hyb)
        for k in range(n2):
            for q in range(n_lanes):
                chain_exp[t, k, q] = e[k, q]
                chain_exp[t + 1, k, q] = e[k, n_lanes + q]
    if n_obj % 2 == 0 and n_obj > 0:
        last = n_obj - 1
        _exp_hyb_columns(chain[last], exp_tables, scratch.exp_direct)
        for k in range(n2):
            for q in range(n_lanes):
                chain_exp[last, k, q] = direct[k, q]


@numba.njit(cache=True, error_model="numpy", inline="always")
def _average_visibility_ol(lights, exp_tables, per_object, n2, scratch):
    """:func:`_average_visibility_hyb` with OL exponentials. OL is linear in ``f^`` given ``|f^|``: ``exp*(f) .
    rho = e^(f_0 / sqrt(4 pi)) (a sqrt(4 pi) rho_0 + b f^ . rho^)``, so only norms and dot products are
    formed."""
    light_object, front_ptr, front_idx = lights.light_object, lights.front_ptr, lights.front_idx
    log, dist, theta = scratch.blockers.log, scratch.blockers.dist, scratch.blockers.theta
    front, prefix, rho = scratch.front, scratch.object_prefix, scratch.cosine
    sums, vis = scratch.sums, scratch.visibility
    r_max, ol_a, ol_b = exp_tables.r_max, exp_tables.ol_a, exp_tables.ol_b
    n_lanes = front.shape[1]
    sqrt4pi = math.sqrt(4.0 * math.pi)
    for i in range(log.shape[0]):
        if not _any_live(theta, i):
            for q in range(n_lanes):
                vis[i, q] = 0.0
            continue
        _front_log(i, per_object, light_object, front_ptr, front_idx, prefix, log, dist, front)
        for t in range(4):  # rows: |f^|^2, |o^|^2, f^ . rho^, o^ . rho^ (o = f + G_i)
            for q in range(n_lanes):
                sums[t, q] = 0.0
        for k in range(1, n2):
            for q in range(n_lanes):
                f = front[k, q]
                o = f + log[i, k, q]
                cr = rho[k, q]
                sums[0, q] += f * f
                sums[1, q] += o * o
                sums[2, q] += f * cr
                sums[3, q] += o * cr
        for q in range(n_lanes):
            if theta[i, q] < 0.0:
                vis[i, q] = 0.0
                continue
            af, bf = _ol_coefficients(math.sqrt(sums[0, q]), r_max, ol_a, ol_b)
            ao, bo = _ol_coefficients(math.sqrt(sums[1, q]), r_max, ol_a, ol_b)
            f0 = front[0, q]
            o0 = f0 + log[i, 0, q]
            c0 = sqrt4pi * rho[0, q]
            vis[i, q] = (math.exp(f0 / sqrt4pi) * (af * c0 + bf * sums[2, q])
                         - math.exp(o0 / sqrt4pi) * (ao * c0 + bo * sums[3, q]))


@numba.njit(cache=True, error_model="numpy", inline="always")
def _light_direction(rotation, i, axis, out):
    """``out[:3, q]``: the direction light ``i`` -> receiver (``-axis[i, :, q]``) in the light's own frame
    (Sec. 7.1)."""
    r00, r01, r02 = rotation[i, 0, 0], rotation[i, 0, 1], rotation[i, 0, 2]
    r10, r11, r12 = rotation[i, 1, 0], rotation[i, 1, 1], rotation[i, 1, 2]
    r20, r21, r22 = rotation[i, 2, 0], rotation[i, 2, 1], rotation[i, 2, 2]
    for q in range(out.shape[1]):
        ax, ay, az = axis[i, 0, q], axis[i, 1, q], axis[i, 2, q]
        out[0, q] = -(r00 * ax + r10 * ay + r20 * az)
        out[1, q] = -(r01 * ax + r11 * ay + r21 * az)
        out[2, q] = -(r02 * ax + r12 * ay + r22 * az)


@numba.njit(cache=True, error_model="numpy", inline="always")
def _rotated_kernel(theta, i, table, theta_max, n_bands, dirs, zh, basis, tmp, kernel):
    """``kernel[0]``: a ZH table (knots ``j theta_max / K``, ``j = 0..K``) linearly interpolated at
    ``theta[i, q]`` clamped to ``[0, theta_max]`` and rotated to ``dirs[:3, q]`` (:func:`_rotated_zh_lanes`)."""
    n_knots = table.shape[0] - 1
    for q in range(zh.shape[1]):
        u = min(max(theta[i, q], 0.0), theta_max) * (n_knots / theta_max)
        j = min(int(math.floor(u)), n_knots - 1)
        w = u - j
        for l in range(n_bands):
            zh[l, q] = (1.0 - w) * table[j, l] + w * table[j + 1, l]
    _rotated_zh_lanes(dirs, 0, zh, n_bands, basis, tmp, kernel, 0)


@numba.njit(cache=True, error_model="numpy", inline="always")
def _project_lanes(kernel, coeffs, i, n_coeffs, n_cols, out):
    """``out[t, q] = sum_k kernel[0, k, q] coeffs[i, k, t]`` over the first ``n_coeffs`` coefficients, ``t <
    n_cols`` (a constant at the call site: the loop over ``t`` is unrolled)."""
    n_lanes = out.shape[1]
    for t in range(n_cols):
        for q in range(n_lanes):
            out[t, q] = 0.0
    # four coefficients per pass over ``out``: one load and store of the output row per four products (the
    # load and store per product bounded this loop)
    k = 0
    while k + 4 <= n_coeffs:
        for t in range(n_cols):
            m0, m1, m2, m3 = coeffs[i, k, t], coeffs[i, k + 1, t], coeffs[i, k + 2, t], coeffs[i, k + 3, t]
            for q in range(n_lanes):
                out[t, q] += (kernel[0, k, q] * m0 + kernel[0, k + 1, q] * m1 + kernel[0, k + 2, q] * m2
                              + kernel[0, k + 3, q] * m3)
        k += 4
    for kk in range(k, n_coeffs):
        for t in range(n_cols):
            m = coeffs[i, kk, t]
            for q in range(n_lanes):
                out[t, q] += kernel[0, kk, q] * m


@numba.njit(cache=True, error_model="numpy", inline="always")
def _add_paper_averages(lights, tables, order, scratch):
    """``scratch.indirect += sum_i L~_i V~_i`` with ``L~_i = w'_theta . L^c_i`` (Eq. 18); ``order``: the
    emission's."""
    rotation, emission, w_table = lights.rotation, lights.emission, tables.w_theta
    theta, axis, vis, ind = scratch.blockers.theta, scratch.blockers.axis, scratch.visibility, scratch.indirect
    light_dir, kernel, rad = scratch.light_dir, scratch.kernel, scratch.radiance
    zh, basis, tmp = scratch.lane.zh, scratch.lane.basis, scratch.lane.tmp
    for i in range(theta.shape[0]):
        if not _any_live(theta, i):
            continue
        _light_direction(rotation, i, axis, light_dir)
        _rotated_kernel(theta, i, w_table, 0.5 * math.pi, order, light_dir, zh, basis, tmp, kernel)
        _project_lanes(kernel, emission, i, order * order, 3, rad)
        for c in range(3):
            for q in range(ind.shape[1]):
                ind[c, q] += rad[c, q] * vis[i, q] if theta[i, q] >= 0.0 else 0.0


@numba.njit(cache=True, error_model="numpy")
def _add_cosine_averages(lights, tables, order, emission_order, scratch):
    """``scratch.indirect +=`` the sum over the lights of the cosine-weighted irradiance times the visible
    fraction, ``E_n clip(V~ / V~', 0, 1)``, with ``E_n = s n.(Lu . K) - (n.b) L . K`` in the light's frame (see
    :func:`irradiance_kernel_zh` and :func:`light_terms`; ``K`` of order ``emission_order + 1``) and ``V~'`` the
    unoccluded visibility (of order ``order``, as ``V~``)."""
    rot, emission, emission_dir = lights.rotation, lights.emission, lights.emission_dir
    b = scratch.blockers
    theta, sin_t, cos_t, axis = b.theta, b.sin_theta, b.cos_theta, b.axis
    recv, vis, ind, ld, kernel = scratch.recv, scratch.visibility, scratch.indirect, scratch.light_dir, scratch.kernel
    lum_dir, lum, cos_na, v_open = scratch.radiance_dir, scratch.radiance, scratch.cos_na, scratch.open_visibility
    zh, basis, tmp = scratch.lane.zh, scratch.lane.basis, scratch.lane.tmp
    k_table, cos_zh = tables.irradiance_kernel, tables.cosine
    sin_k_max = math.sin(THETA_MAX_K)
    for i in range(theta.shape[0]):
        if not _any_live(theta, i):
            continue
        _light_direction(rot, i, axis, ld)
        _rotated_kernel(theta, i, k_table, THETA_MAX_K, emission_order + 1, ld, zh, basis, tmp, kernel)
        _project_lanes(kernel, emission_dir, i, (emission_order + 1) * (emission_order + 1), 9, lum_dir)
        _project_lanes(kernel, emission, i, emission_order * emission_order, 3, lum)
        for q in range(ind.shape[1]):
            cos_na[q] = recv[3, q] * axis[i, 0, q] + recv[4, q] * axis[i, 1, q] + recv[5, q] * axis[i, 2, q]
        _cap_visibility_lanes(cos_t, i, cos_na, cos_zh, order, tmp, v_open)
        r00, r01, r02 = rot[i, 0, 0], rot[i, 0, 1], rot[i, 0, 2]
        r10, r11, r12 = rot[i, 1, 0], rot[i, 1, 1], rot[i, 1, 2]
        r20, r21, r22 = rot[i, 2, 0], rot[i, 2, 1], rot[i, 2, 2]
        for q in range(ind.shape[1]):
            nx, ny, nz = recv[3, q], recv[4, q], recv[5, q]
            mx = r00 * nx + r10 * ny + r20 * nz  # the normal in the light's frame
            my = r01 * nx + r11 * ny + r21 * nz
            mz = r02 * nx + r12 * ny + r22 * nz
            s_i = sin_t[i, q] if theta[i, q] <= THETA_MAX_K else sin_k_max
            n_dot_b = mx * ld[0, q] + my * ld[1, q] + mz * ld[2, q]
            proj = math.pi * s_i * s_i * cos_na[q]
            ok = theta[i, q] >= 0.0 and proj > 0.0 and v_open[q] > 0.0
            frac = min(max(vis[i, q] / v_open[q], 0.0), 1.0)
            for c in range(3):
                e_n = (s_i * (mx * lum_dir[c, q] + my * lum_dir[3 + c, q] + mz * lum_dir[6 + c, q])
                       - n_dot_b * lum[c, q])
                ind[c, q] += e_n * frac if ok else 0.0


@numba.njit(cache=True, error_model="numpy", inline="always")
def _ol_knot(r, r_max, n_tab):
    """The knot of OL's table (``n_tab`` knots uniform in ``sqrt(r)`` up to ``r_max``) at or below ``|f^| = r``, as
    a float, the last but one at most."""
    return min(math.floor(math.sqrt(r / r_max) * (n_tab - 1)), float(n_tab - 2))


@numba.njit(cache=True, error_model="numpy", inline="always")
def _ol_fraction(r, j, r_max, n_tab):
    """Where ``r`` lies between the knots ``j`` and ``j + 1`` of OL's table (0 to 1)."""
    r0 = r_max * (j / (n_tab - 1)) ** 2
    r1 = r_max * ((j + 1.0) / (n_tab - 1)) ** 2
    return (r - r0) / (r1 - r0)


@numba.njit(cache=True, error_model="numpy")
def _ol_coefficients(r, r_max, tab_a, tab_b):
    """``(a, b)`` of the optimal-linear exponential at ``|f^| = r`` (as ``prtlab.sh``'s ``_ol_one``)."""
    n_tab = tab_a.shape[0]
    if r >= r_max:
        return tab_a[n_tab - 1], tab_b[n_tab - 1]
    j = _ol_knot(r, r_max, n_tab)
    s = _ol_fraction(r, j, r_max, n_tab)
    i = int(j)
    return (1.0 - s) * tab_a[i] + s * tab_a[i + 1], (1.0 - s) * tab_b[i] + s * tab_b[i + 1]


@numba.njit(cache=True, error_model="numpy")
def _exp_hyb_columns(x, exp_tables, scratch):
    """HYB ``exp*`` of the columns of ``x (n2, M)`` into ``scratch.out`` (as ``prtlab.sh``'s ``_exp_hyb``: ``k``
    halvings to ``|f^| <= threshold``, OL, ``k`` squarings, the DC factor). The columns are ordered by ``k``
    (descending), so squaring ``t`` runs over the prefix of columns that still need it; a square uses the
    symmetric Gaunt pairs of ``exp_tables``, through the generated straight-line squares of
    :mod:`._square_kernels` where ``scratch.value`` has their row stride and the order has one. ``scratch``: a
    :data:`_HybScratch` of ``M`` columns."""
    n2, m = x.shape
    col, ks, perm = scratch.columns, scratch.n_squarings, scratch.perm
    v, w, out = scratch.value, scratch.square, scratch.out
    sqrt4pi = math.sqrt(4.0 * math.pi)
    threshold, r_max, ol_a, ol_b = exp_tables.threshold, exp_tables.r_max, exp_tables.ol_a, exp_tables.ol_b
    for p in range(m):
        col[0, p] = 0.0
    for i in range(1, n2):
        for p in range(m):
            col[0, p] += x[i, p] * x[i, p]
    # k: the fewest halvings with |f^| / 2^k <= threshold, i.e. |f^| <= threshold 2^k (both sides exact: powers of
    # two), the k of prtlab.sh's ceil(log2(|f^| / threshold)) and its guard; col[1]: the scale 2^-k. The first
    # _SELECT_HALVINGS comparisons as selects (a loop over the columns without branches: k varies from column to
    # column, and a while loop per column mispredicted its exit); a column beyond them goes on in a loop.
    k_max = 0
    beyond = False
    for p in range(m):
        r = math.sqrt(col[0, p])
        k = 0
        limit = threshold
        scale = 1.0
        for _ in range(_SELECT_HALVINGS):
            over = r > limit
            k += 1 if over else 0
            scale *= 0.5 if over else 1.0
            limit *= 2.0
        beyond |= r > limit
        ks[p] = k
        col[1, p] = scale
        k_max = max(k_max, k)
    if beyond:  # those columns go on halving from where the selects left them (powers of two: exact)
        for p in range(m):
            r = math.sqrt(col[0, p])
            limit = threshold * 2.0 ** _SELECT_HALVINGS
            while r > limit:
                limit *= 2.0
                col[1, p] *= 0.5
                ks[p] += 1
            k_max = max(k_max, ks[p])
    # columns by k descending, stable (a counting sort; perm's tail is its scratch)
    for kk in range(k_max + 2):
        perm[m + kk] = 0
    for p in range(m):
        perm[m + k_max - ks[p] + 1] += 1
    for kk in range(1, k_max + 2):
        perm[m + kk] += perm[m + kk - 1]
    for p in range(m):
        slot = m + k_max - ks[p]
        perm[perm[slot]] = p
        perm[slot] += 1
    # OL of the scaled columns h = 2^-k f^ (DC 0: its factor exp(0) = 1); |h|^2 = 2^-2k |f^|^2 exactly. Its
    # coefficients are _ol_coefficients' in loops over the columns: the square roots, the knot and the
    # interpolation vectorise, the table's reads between them do not. Then the columns are copied in the sorted
    # order.
    n_tab = ol_a.shape[0]
    for p in range(m):
        scale = col[1, p]
        r = math.sqrt(col[0, p] * (scale * scale))
        col[4, p] = r
        col[5, p] = _ol_knot(r, r_max, n_tab)
    for p in range(m):
        j = int(col[5, p])
        col[6, p], col[7, p], col[8, p], col[9, p] = ol_a[j], ol_a[j + 1], ol_b[j], ol_b[j + 1]
    for p in range(m):
        r = col[4, p]
        s = _ol_fraction(r, col[5, p], r_max, n_tab)
        far = r >= r_max
        col[2, p] = (ol_a[n_tab - 1] if far else (1.0 - s) * col[6, p] + s * col[7, p]) * sqrt4pi
        col[3, p] = ol_b[n_tab - 1] if far else (1.0 - s) * col[8, p] + s * col[9, p]
    for t in range(m):
        p = perm[t]
        scale, b = col[1, p], col[3, p]
        v[0, t] = col[2, p]
        for i in range(1, n2):
            v[i, t] = b * (x[i, p] * scale)
    n_act = m
    order = int(math.sqrt(n2) + 0.5)
    generated = v.shape[1] == SQUARE_COLUMNS and order <= SQUARE_ORDERS[-1]
    v_flat = v.reshape(-1)
    for step in range(k_max):
        while n_act > 0 and ks[perm[n_act - 1]] <= step:
            n_act -= 1
        if generated:
            square_columns(v_flat, order, n_act)
            continue
        _tile_product_prefix(v, v, exp_tables.sq_i, exp_tables.sq_j, exp_tables.sq_k, exp_tables.sq_v, w, n_act)
        for k in range(n2):
            for t in range(n_act):
                v[k, t] = w[k, t]
    for t in range(m):
        p = perm[t]
        dc = math.exp(x[0, p] / sqrt4pi)
        for i in range(n2):
            out[i, p] = dc * v[i, t]


@numba.njit(cache=True, error_model="numpy")
def _cap_visibility_lanes(cos_theta, i, cos_na, cos_zh, order, tmp, out):
    """:func:`_cap_visibility` of the lanes: ``out[q]`` for ``cos theta = cos_theta[i, q]`` and ``cos_na[q]``;
    ``tmp (5, L)`` scratch (rows: P_(l-1), P_l at cos theta, P_(l-1), P_l at cos_na, P_(l-1))."""
    n_lanes = out.shape[0]
    k0 = 2.0 * math.pi * math.sqrt(1.0 / (4.0 * math.pi))
    for q in range(n_lanes):
        tmp[0, q] = 1.0
        tmp[1, q] = cos_theta[i, q]
        tmp[2, q] = 1.0
        tmp[3, q] = cos_na[q]
        tmp[4, q] = 1.0
        out[q] = k0 * (1.0 - cos_theta[i, q]) * cos_zh[0]
    for l in range(1, order):
        kl = 2.0 * math.pi * math.sqrt((2 * l + 1) / (4.0 * math.pi))
        czl = cos_zh[l]
        for q in range(n_lanes):
            pc = tmp[1, q]
            pc_next = ((2 * l + 1) * cos_theta[i, q] * pc - l * tmp[0, q]) / (l + 1)
            pa = tmp[3, q]
            out[q] += kl * (tmp[4, q] - pc_next) / (2 * l + 1) * czl * pa
            tmp[4, q] = pc
            tmp[0, q] = pc
            tmp[1, q] = pc_next
            tmp[3, q] = ((2 * l + 1) * cos_na[q] * pa - l * tmp[2, q]) / (l + 1)
            tmp[2, q] = pa

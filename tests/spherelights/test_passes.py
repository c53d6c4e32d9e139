"""Tests of prtlab.spherelights._passes (first and second pass)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from prtlab import sh
from prtlab.geometry import builtin_mesh, geodesic_directions
from prtlab.spherelights import (
    accumulate_blockers,
    first_pass,
    second_pass,
    surface_albedo_sh,
    surface_samples,
    voronoi_cell_sums,
    w_theta_zh,
)
from tests.conftest import MC_SIGMAS, random_directions
from tests.spherelights.test_shadows import _env_sh

ORDER = 4


@pytest.mark.parametrize("blocking", ["object", "sphere"])
def test_accumulation_kernel_matches_reference(blocking, rng):
    p = rng.normal(size=(25, 3))
    n = random_directions(rng, 25)
    c = rng.normal(size=(7, 3)) * 2.0
    r = rng.uniform(0.2, 0.8, 7)
    obj = np.array([0, 0, 1, 1, 1, 2, 0])
    inter = np.zeros((7, 7), dtype=bool)
    inter[0, 1] = inter[1, 0] = inter[2, 3] = inter[3, 2] = True
    a = accumulate_blockers(p, n, c, r, obj, inter, ORDER, blocking=blocking)
    b = accumulate_blockers(p, n, c, r, obj, inter, ORDER, blocking=blocking, method="reference")
    for x, y in zip(a, b):
        np.testing.assert_allclose(x, y, atol=1e-12)


def test_front_sums_partition_the_blockers(rng):
    """Per-object blocking: the farthest light of the farthest object sees every other light in front,
    except the ones it intersects."""
    p = np.zeros((1, 3))
    n = np.array([[0.0, 1.0, 0.0]])
    c = np.array([[0.0, 2.0, 0.0], [0.0, 4.0, 0.0], [0.0, 6.0, 0.0]])
    r = np.array([0.5, 0.5, 0.5])
    obj = np.array([0, 1, 1])
    inter = np.zeros((3, 3), dtype=bool)
    gs, gf, th, ax = accumulate_blockers(p, n, c, r, obj, inter, ORDER, blocking="object")
    np.testing.assert_allclose(gf[0, 2], gs[0, 0] + gs[0, 1], atol=1e-14)
    np.testing.assert_allclose(gf[0, 0], 0.0)
    inter[1, 2] = inter[2, 1] = True
    gs, gf, th, ax = accumulate_blockers(p, n, c, r, obj, inter, ORDER, blocking="sphere")
    np.testing.assert_allclose(gf[0, 2], gs[0, 0], atol=1e-14)


def _one_sphere_light(centre, radius, albedo, env, exp_method="exact"):
    mesh = builtin_mesh("icosphere", subdivisions=4)
    mesh.apply_scale(radius)
    mesh.apply_translation(centre)
    dirs = geodesic_directions(92)
    c, r = np.asarray([centre], dtype=float), np.array([radius])
    pts, nrm, valid = surface_samples(mesh, c, r, dirs)
    alb = surface_albedo_sh(mesh, c, r, albedo, ORDER)
    emission = first_pass(pts, nrm, valid, c, r, env, voronoi_cell_sums(ORDER), alb, exp_method=exp_method)
    return c, r, emission


def test_first_pass_of_a_lone_sphere_is_its_diffuse_reflection():
    """Unoccluded sphere: the emission is albedo/pi times the irradiance at normal w, which is band-limited
    (order 4) for a band-limited environment; the only errors are the Voronoi nearest-neighbour
    interpolation of 92 values (O(cell size x gradient)) and the albedo-coverage product."""
    env = _env_sh()
    albedo = np.array([0.8, 0.5, 0.3])
    c, r, emission = _one_sphere_light([0.0, 1.0, 0.0], 0.5, albedo, env)
    conv = np.repeat(np.pi * np.array([1.0, 2.0 / 3.0, 0.25, 0.0]), 2 * np.arange(ORDER) + 1)
    truth = albedo / np.pi * conv[:, None] * env
    # Voronoi interpolation error: |L - L_nn| <= max|grad L| * (max cell radius); band-limited L of
    # order 4 has |grad L| <= sum_l sqrt(l(l+1)) |band l| ... bound the whole vector by the L2 norm:
    dirs, w = sh.quadrature(1, degree=40)
    L = sh.basis(dirs, ORDER) @ truth
    cells = geodesic_directions(92)
    nn = np.argmax(dirs @ cells.T, axis=1)
    # the direct L2 distance between L and its nearest-neighbour resampling on the cells
    vals = sh.basis(cells, ORDER) @ truth
    err_nn = np.sqrt((w[:, None] * (L - vals[nn]) ** 2).sum(0))
    err = np.linalg.norm(emission[0] - truth, axis=0)
    # Bessel: the SH projection of (L_nn - L) has norm <= its L2 norm; plus the stratified-projection
    # error of Y_j (tested < 5e-3 per coefficient on the constant) times the largest cell value
    assert np.all(err <= err_nn * 1.05 + 16 * 5e-3 * np.abs(vals).max(0)), (err, err_nn)


def _mc_indirect(p, n, centre, radius, truth_sh, n_samples, rng):
    u1, u2 = rng.random(n_samples), rng.random(n_samples)
    rr, ph = np.sqrt(u1), 2 * np.pi * u2
    local = np.stack([rr * np.cos(ph), rr * np.sin(ph), np.sqrt(1 - u1)], -1)
    t = np.cross(n, [1.0, 0.0, 0.0])
    t /= np.linalg.norm(t)
    dirs = local @ np.stack([t, np.cross(n, t), n])
    oc = p - centre
    bq = dirs @ oc
    disc = bq * bq - (oc @ oc - radius**2)
    hit = disc > 0
    tq = -bq - np.sqrt(np.maximum(disc, 0))
    q = p + tq[:, None] * dirs
    nq = (q - centre) / radius
    f = np.pi * hit[:, None] * (sh.basis(nq, ORDER) @ truth_sh)
    return f.mean(0), f.std(0, ddof=1) / np.sqrt(n_samples)


def test_one_sphere_indirect_against_monte_carlo(rng):
    """One diffuse sphere lighting a plane (the paper's optimal case), against exact-up-to-noise MC, with the
    paper's average radiance (Eqs. 15-18).

    Derived bound per receiver (``E = L~ V~`` ours, ``E* = Lbar* V*`` the truth):
    ``|E - E*| <= (|w'| |L^c - L*| + (max_cap L* - min_cap L*)) |V~| + max_cap L* |V~ - V*|`` with
    ``|V~ - V*| <= |v - P_n(1 - B)| |rho_n| + |(I - P_n)(1 - B)|_2 |(I - P_n) rho|_2`` (Cauchy-Schwarz).
    """
    env = _env_sh()
    albedo = np.array([0.8, 0.5, 0.3])
    centre, radius = np.array([0.0, 1.0, 0.0]), 0.5
    c, r, emission = _one_sphere_light(centre, radius, albedo, env)
    conv = np.repeat(np.pi * np.array([1.0, 2.0 / 3.0, 0.25, 0.0]), 2 * np.arange(ORDER) + 1)
    truth = albedo / np.pi * conv[:, None] * env
    xs = np.array([0.0, 0.5, 1.0, 2.0])
    pts = np.stack([xs, np.zeros_like(xs), np.zeros_like(xs)], -1)
    nrm = np.broadcast_to([0.0, 1.0, 0.0], pts.shape)
    _, ind = second_pass(pts, nrm, c, r, [0], np.zeros((1, 1), bool), np.eye(3)[None], emission, env,
                         exp_method="exact", average="paper")
    cos_n = sh.zh_rotate(sh.clamped_cosine_zh(ORDER), [0.0, 1.0, 0.0])
    # |(I - P_n) rho|_2 for the clamped cosine: |rho|^2 = 2 pi / 3
    rho_tail = np.sqrt(2 * np.pi / 3 - sh.clamped_cosine_zh(ORDER) @ sh.clamped_cosine_zh(ORDER))
    for k, p in enumerate(pts):
        ref, se = _mc_indirect(p, nrm[k], centre, radius, truth, 400_000, rng)
        d = centre - p
        dist = np.linalg.norm(d)
        theta = np.arcsin(radius / dist)
        axis = d / dist
        one_minus_b = -sh.zh_rotate(sh.blocker_zh(theta, ORDER), axis)
        one_minus_b[0] += np.sqrt(4 * np.pi)
        v_ours = sh.exp(np.zeros(16)) - sh.exp(sh.zh_rotate(sh.blocker_log_zh(theta, ORDER), axis), method="exact")
        v_tilde = v_ours @ cos_n
        cap = 2 * np.pi * (1 - np.cos(theta))
        b_tail = np.sqrt(max(cap - one_minus_b @ one_minus_b, 0.0))
        dv = np.linalg.norm(v_ours - one_minus_b) * np.linalg.norm(cos_n) + b_tail * rho_tail
        # true emission over the cap of the sphere visible from p (cos alpha > sin theta about -axis)
        sdirs = random_directions(np.random.default_rng(0), 20000)
        vis = sdirs @ (-axis) > np.sin(theta)
        lv = sh.basis(sdirs[vis], ORDER) @ truth
        spread = lv.max(0) - lv.min(0)
        w = sh.zh_rotate(w_theta_zh(theta, ORDER), -axis)
        dl = np.linalg.norm(w) * np.linalg.norm(emission[0] - truth, axis=0)
        bound = (dl + spread) * abs(v_tilde) + lv.max(0) * dv
        assert np.all(np.abs(ind[k] - ref) <= bound + MC_SIGMAS * se), (k, ind[k], ref, bound, se)


def test_errors():
    with pytest.raises(ValueError, match="blocking must be"):
        accumulate_blockers(np.zeros((1, 3)), np.ones((1, 3)), [[0, 1, 0]], [1.0], [0], np.zeros((1, 1), bool), 4,
                            blocking="pixel")
    with pytest.raises(ValueError, match="method must be"):
        accumulate_blockers(np.zeros((1, 3)), np.ones((1, 3)), [[0, 1, 0]], [1.0], [0], np.zeros((1, 1), bool), 4,
                            method="gpu")
    with pytest.raises(ValueError, match="must agree in S"):
        accumulate_blockers(np.zeros((1, 3)), np.ones((1, 3)), [[0, 1, 0]], [1.0, 2.0], [0], np.zeros((1, 1), bool), 4)


@pytest.mark.parametrize("blocking,average", [("object", "cosine"), ("sphere", "cosine"), ("object", "paper")])
def test_fused_second_pass_matches_composed_tier(blocking, average, rng):
    p = rng.uniform(-2, 2, size=(60, 3))
    n = random_directions(rng, 60)
    c = rng.normal(size=(6, 3)) * 1.5
    r = rng.uniform(0.2, 0.6, 6)
    obj = np.array([0, 0, 0, 1, 2, 2])
    inter = np.zeros((6, 6), dtype=bool)
    inter[0, 1] = inter[1, 0] = True
    rot = np.stack([np.eye(3)] * 3 + [np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])] * 3)
    em = rng.normal(size=(6, 16, 3)) * 0.1
    em[:, 0] += 1.0
    env = _env_sh()
    for exp_method in ("ol", "hyb"):
        args = (p, n, c, r, obj, inter, rot, em, env)
        d1, i1 = second_pass(*args, blocking=blocking, exp_method=exp_method, method="fused", average=average)
        d2, i2 = second_pass(*args, blocking=blocking, exp_method=exp_method, method="numba", average=average)
        np.testing.assert_allclose(d1, d2, atol=1e-11)
        np.testing.assert_allclose(i1, i2, atol=1e-11)


@given(seed=st.integers(0, 2**31), n_recv=st.integers(0, 24), n_sph=st.integers(1, 7),
       blocking=st.sampled_from(["object", "sphere"]), exp_method=st.sampled_from(["ol", "hyb"]),
       average=st.sampled_from(["cosine", "paper"]))
def test_fused_second_pass_matches_composed_tier_property(seed, n_recv, n_sph, blocking, exp_method, average):
    rng = np.random.default_rng(seed)
    p = rng.uniform(-2, 2, size=(n_recv, 3))
    n = random_directions(rng, n_recv)
    c = rng.normal(size=(n_sph, 3)) * 1.5
    r = rng.uniform(0.1, 0.8, n_sph)
    obj = np.unique(rng.integers(0, 3, n_sph), return_inverse=True)[1]  # objects 0..O-1, none empty
    inter = (rng.random((n_sph, n_sph)) < 0.3) & (obj[:, None] == obj[None])
    inter = inter | inter.T
    np.fill_diagonal(inter, False)
    rot = np.stack([np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(n_sph)])
    em = rng.normal(size=(n_sph, 16, 3)) * 0.1
    em[:, 0] += 1.0
    args = (p, n, c, r, obj, inter, rot, em, _env_sh())
    d1, i1 = second_pass(*args, blocking=blocking, exp_method=exp_method, method="fused", average=average)
    d2, i2 = second_pass(*args, blocking=blocking, exp_method=exp_method, method="numba", average=average)
    assert d1.shape == d2.shape == i1.shape == i2.shape == (n_recv, 3)
    np.testing.assert_allclose(d1, d2, atol=1e-11)
    np.testing.assert_allclose(i1, i2, atol=1e-11)


def _five_lights(rng):
    """Five spherical lights in three objects (two, one, two), none intersecting, turned at random, with an order-4
    emission: ``(centres, radii, sl_object, intersect, rotations, emission)``."""
    c = rng.normal(size=(5, 3)) * 1.5
    r = rng.uniform(0.2, 0.6, 5)
    obj = np.array([0, 0, 1, 2, 2])
    inter = np.zeros((5, 5), dtype=bool)
    rot = np.stack([np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(5)])
    em = rng.normal(size=(5, 16, 3)) * 0.1
    em[:, 0] += 1.0
    return c, r, obj, inter, rot, em


@pytest.mark.parametrize("order", [2, 4, 7])
def test_fused_hyb_columns_match_the_hyb_reference_tier(order, rng):
    """The fused pass's HYB exponential of a block's columns (``_exp_hyb_columns``) against ``sh.exp``'s numpy
    tier, columns of 0 to 14 halvings (beyond the halvings decided by selects, ``_SELECT_HALVINGS``, a column
    takes the loop), in shuffled order, a DC term of either sign; order 7 has no generated square."""
    from prtlab.spherelights._passes import (_SELECT_HALVINGS, _ExpTables, _exp_hyb_columns, _hyb_scratch,
                                             _HYB_THRESHOLD, _ol_table, _symmetric_gaunt)

    n2, m = order * order, 64
    k = rng.permutation(np.arange(m) % (_SELECT_HALVINGS + 3))
    norm = _HYB_THRESHOLD * 2.0 ** (k - rng.uniform(0.0, 1.0, m))  # k halvings bring it under the threshold
    norm[k == 0] *= rng.uniform(0.0, 1.0, int((k == 0).sum()))
    x = rng.normal(size=(n2, m))
    x[1:] *= norm / np.linalg.norm(x[1:], axis=0)
    x[0] = rng.uniform(-3.0, 3.0, m) - 2e-3 * norm  # keeps exp*(x) finite where |f^| is large
    keep = norm < 60.0  # exp*(f) at larger norms is far outside float64's range: compared only where finite
    r_max, tab_a, tab_b = _ol_table(order)
    tables = _ExpTables(float(r_max), tab_a, tab_b, float(_HYB_THRESHOLD), *_symmetric_gaunt(order))
    scratch = _hyb_scratch(n2, m)
    _exp_hyb_columns(np.ascontiguousarray(x), tables, scratch)
    ref = sh.exp(np.ascontiguousarray(x[:, keep].T), method="hyb-reference", channels=False).T
    np.testing.assert_array_equal(scratch.n_squarings, k)
    # rounding: each squaring doubles the relative error and adds its sums' (n2^2 products at most)
    bound = 2.0 ** (k[keep] + 1) * n2**2 * np.finfo(float).eps * np.abs(ref).max(axis=0)
    assert np.all(np.abs(scratch.out[:, keep] - ref) <= bound)
    assert (k[keep] > 3).any() and (k[~keep] > _SELECT_HALVINGS).any()


@pytest.mark.parametrize("exp_method", ["ol", "hyb"])
def test_fused_second_pass_on_runs_of_one_normal(exp_method, rng):
    """Receivers in runs of one normal, as a flat ground gives (the fused tier keeps a block's environment
    transfer for the next block when every lane's normal is the same): blocks of one normal, a block where one lane
    differs, an unnormalised copy of the normal, a block of another normal, against the composed tier."""
    from prtlab.spherelights._passes import _LANES

    runs = [np.tile([0.0, 1.0, 0.0], (3 * _LANES, 1)), random_directions(rng, _LANES),
            np.tile([0.0, 1.0, 0.0], (2 * _LANES, 1)), np.tile([0.0, 2.0, 0.0], (_LANES, 1)),
            np.tile([0.6, 0.8, 0.0], (2 * _LANES + 5, 1))]
    runs[2][_LANES + 7] = [0.0, 0.8, 0.6]
    n = np.concatenate(runs)
    p = rng.uniform(-2, 2, size=(n.shape[0], 3))
    c, r, obj, inter, rot, em = _five_lights(rng)
    args = (p, n, c, r, obj, inter, rot, em, _env_sh())
    for indirect in (False, True):
        d1, i1 = second_pass(*args, blocking="object", exp_method=exp_method, method="fused", indirect=indirect)
        d2, i2 = second_pass(*args, blocking="object", exp_method=exp_method, method="numba", indirect=indirect)
        np.testing.assert_allclose(d1, d2, atol=1e-11)
        np.testing.assert_allclose(i1, i2, atol=1e-11)
        assert np.ptp(d1[:, 0]) > 0.1


@given(seed=st.integers(0, 2**31), order=st.integers(1, 6), extra=st.integers(0, 2), indirect=st.booleans(),
       blocking=st.sampled_from(["object", "sphere"]), exp_method=st.sampled_from(["ol", "hyb"]),
       average=st.sampled_from(["cosine", "paper"]))
@settings(max_examples=40, deadline=None)
def test_fused_second_pass_matches_composed_tier_every_order(seed, order, extra, indirect, blocking, exp_method,
                                                             average):
    """The fused tier against the composed one at orders 1-6 (closed-form and recurrence bases, bands above the
    order-4 closed forms), an emission of the same or a higher order (``extra`` bands more), shadows only and with
    indirect light, receivers in partial blocks (> 32 lanes)."""
    rng = np.random.default_rng(seed)
    n_recv, n_sph = 40, 5
    p = rng.uniform(-2, 2, size=(n_recv, 3))
    n = random_directions(rng, n_recv)
    c = rng.normal(size=(n_sph, 3)) * 1.5
    r = rng.uniform(0.1, 0.8, n_sph)
    obj = np.array([0, 0, 1, 2, 2])
    inter = np.zeros((n_sph, n_sph), dtype=bool)
    inter[0, 1] = inter[1, 0] = True
    rot = np.stack([np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(n_sph)])
    m = order + extra
    em = rng.normal(size=(n_sph, m * m, 3)) * 0.1
    em[:, 0] += 1.0
    env = np.zeros(((3 * order - 2) ** 2, 3))  # the exact-transfer order of the environment
    env[:16] = _env_sh()[: env.shape[0]]
    env[0] = [3.0, 2.5, 2.0]
    args = (p, n, c, r, obj, inter, rot, em, env)
    kw = dict(blocking=blocking, exp_method=exp_method, average=average, indirect=indirect, order=order)
    d1, i1 = second_pass(*args, method="fused", **kw)
    d2, i2 = second_pass(*args, method="numba", **kw)
    np.testing.assert_allclose(d1, d2, atol=1e-11)
    np.testing.assert_allclose(i1, i2, atol=1e-11)
    if not indirect:
        assert np.all(i1 == 0)


@pytest.mark.parametrize("average", ["cosine", "paper"])
@pytest.mark.parametrize("method", ["fused", "numba"])
def test_an_emission_padded_with_zeros_changes_nothing(average, method, rng):
    """An order-6 emission whose bands 4-5 are 0 gives the order-4 emission's light (the visibility at order 4):
    the higher-order kernel only meets the emission's own bands."""
    p = rng.uniform(-2, 2, size=(50, 3))
    n = random_directions(rng, 50)
    c, r, obj, inter, rot, em = _five_lights(rng)
    padded = np.concatenate([em, np.zeros((5, 20, 3))], axis=1)
    env = _env_sh()
    kw = dict(average=average, method=method)
    d4, i4 = second_pass(p, n, c, r, obj, inter, rot, em, env, **kw)
    d6, i6 = second_pass(p, n, c, r, obj, inter, rot, padded, env, order=4, **kw)
    np.testing.assert_array_equal(d4, d6)
    np.testing.assert_allclose(i6, i4, rtol=1e-12, atol=1e-12 * np.abs(i4).max())
    with pytest.raises(ValueError, match="order must be between 1 and the emission's"):
        second_pass(p, n, c, r, obj, inter, rot, em, env, order=5)


def _cosine_directions(n, count, rng):
    """(count, 3) cosine-distributed directions about the unit normal ``n``."""
    u1, u2 = rng.random(count), rng.random(count)
    rr, ph = np.sqrt(u1), 2 * np.pi * u2
    local = np.stack([rr * np.cos(ph), rr * np.sin(ph), np.sqrt(1 - u1)], -1)
    t = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    t /= np.linalg.norm(t)
    return local @ np.stack([t, np.cross(n, t), n])


def _first_hit_is(p, dirs, centres, radii, k):
    """Rays from p hitting sphere ``k`` before every other sphere."""
    def dist(c, r):
        oc = p - c
        bq = dirs @ oc
        disc = bq * bq - (oc @ oc - r * r)
        t = -bq - np.sqrt(np.maximum(disc, 0.0))
        return np.where((disc > 0) & (t > 0), t, np.inf)

    ts = np.stack([dist(c, r) for c, r in zip(centres, radii)])
    return np.isfinite(ts[k]) & (np.argmin(ts, axis=0) == k)


@pytest.mark.parametrize("blocking", ["object", "sphere"])
def test_light_behind_another_against_monte_carlo(blocking, rng):
    """A lit far sphere seen past a dark near one (Eqs. 21-24, Sec. 7.2) from ground receivers, against MC of
    the same quantity (the irradiance carried by rays whose first hit is the far sphere).

    The far light emits a constant ``L0`` (exact at order 4, so only visibility is approximated) and the near
    light nothing. Ours: ``E = E_n clip(V~ / V~')`` (``average="cosine"``), ``E_n`` the unoccluded irradiance
    of the far light, ``V~ = (exp G_near - exp(G_near + G_far)) . rho_n``, ``V~' = P_n(cap) . rho_n``. With
    the truth ``E* = L0 V*``, ``V* = int v* rho`` (``v*`` the indicator of far-but-not-near directions),
    ``V*' = pi s^2 cos`` (both caps above the horizon), ``e1 = V~ - V*``, ``e2 = V~' - V*'``:
    ``|E - E*| <= E_n (|e1| + |e2|) / V~' + |E_n - L0 V*'|`` (clip is 1-Lipschitz onto [0, 1], which holds
    ``V*/V*'``), and by Cauchy-Schwarz (the documented order-4 visibility bound of
    ``test_one_sphere_indirect_against_monte_carlo``)
    ``|e1| <= |v - P_n v*| |rho_n| + |(I - P_n) v*|_2 |(I - P_n) rho|_2``, ``|e2| <= |(I - P_n) cap|_2
    |(I - P_n) rho|_2``. ``P_n v*`` and ``|v*|^2`` by a degree-600 product quadrature (its error on the
    indicator is O(1e-3) sr, inside the MC term).

    Measured (order 4, HYB): the bound is of the size of the light itself; where the near sphere hides the far
    one completely (x = -0.8, truth 0) ours keeps 75 % of the unoccluded light (0.064 of 0.086): an order-4
    product of two blockers cannot resolve one cap inside another.
    """
    near_c, near_r = np.array([0.0, 0.9, 0.0]), 0.35
    far_c, far_r = np.array([1.0, 1.8, 0.0]), 0.5
    c, r = np.stack([near_c, far_c]), np.array([near_r, far_r])
    xs = np.array([-2.0, -0.8, -0.3, 0.6])
    pts = np.stack([xs, np.zeros_like(xs), np.zeros_like(xs)], -1)
    up = np.array([0.0, 1.0, 0.0])
    nrm = np.broadcast_to(up, pts.shape)
    L0 = np.array([1.0, 0.7, 0.4])
    em = np.zeros((2, ORDER * ORDER, 3))
    em[1, 0] = L0 * np.sqrt(4 * np.pi)
    inter = np.zeros((2, 2), dtype=bool)
    rot = np.stack([np.eye(3)] * 2)
    _, ind = second_pass(pts, nrm, c, r, [0, 1], inter, rot, em, _env_sh(), blocking=blocking)
    _, e_n = second_pass(pts, nrm, c[1:], r[1:], [0], inter[:1, :1], rot[:1], em[1:], _env_sh())
    gs, gf, th, ax = accumulate_blockers(pts, nrm, c, r, [0, 1], inter, ORDER, blocking=blocking)
    partial = 0
    for k, p in enumerate(pts):
        ref, se, bound, open_true, frac = _behind_check(p, up, c, r, 1, gf[k, 1], gs[k, 1], e_n[k], L0, rng)
        partial += 0.1 < frac < 0.9
        assert np.all(np.abs(ind[k] - ref) <= bound + MC_SIGMAS * se), (k, ind[k], ref, bound, se)
        assert np.all(ind[k] < e_n[k])  # every receiver here has the far light partly hidden: it darkens
    assert partial >= 2  # the near sphere hides part of the far one from some receivers


def _behind_check(p, n, centres, radii, k, g_front, g_light, e_n, L0, rng, n_mc=200_000):
    """MC and derived bound for the light ``k`` of constant radiance ``L0`` seen past the other spheres from
    ``(p, n)`` (see :func:`test_light_behind_another_against_monte_carlo`): ``(ref, se, bound, V*' L0,
    visible fraction)``. ``g_front, g_light``: our blocker logs (Eq. 23); ``e_n``: our unoccluded irradiance."""
    v = sh.exp(g_front) - sh.exp(g_front + g_light)
    cos_n = sh.zh_rotate(sh.clamped_cosine_zh(ORDER), n)
    rho_tail = np.sqrt(2 * np.pi / 3 - sh.clamped_cosine_zh(ORDER) @ sh.clamped_cosine_zh(ORDER))
    d = centres[k] - p
    dist = np.linalg.norm(d)
    s = radii[k] / dist
    v_open_true = np.pi * s * s * (d @ n) / dist
    cap_sh = -sh.zh_rotate(sh.blocker_zh(np.arcsin(s), ORDER), d / dist)
    cap_sh[0] += np.sqrt(4 * np.pi)
    v_open = cap_sh @ cos_n
    e2 = np.sqrt(max(2 * np.pi * (1 - np.sqrt(1 - s * s)) - cap_sh @ cap_sh, 0.0)) * rho_tail
    qd, qw = sh.quadrature(1, degree=600)
    ind_q = _first_hit_is(p, qd, centres, radii, k).astype(float)
    proj = (qw * ind_q) @ sh.basis(qd, ORDER)
    e1 = np.linalg.norm(v - proj) * np.linalg.norm(cos_n) + np.sqrt(max(qw @ ind_q - proj @ proj, 0)) * rho_tail
    bound = e_n * (e1 + e2) / v_open + np.abs(e_n - L0 * v_open_true)
    f = np.pi * _first_hit_is(p, _cosine_directions(n, n_mc, rng), centres, radii, k)[:, None] * L0
    ref, se = f.mean(0), f.std(0, ddof=1) / np.sqrt(n_mc)
    return ref, se, bound, L0 * v_open_true, ref[0] / (L0[0] * v_open_true)


def test_first_pass_extra_irradiance():
    """Irradiance from other sources (local lights) adds ``E / pi`` to every valid sample's radiance; a wrong
    shape raises."""
    env = np.zeros((16, 3))
    c, r, zero = _one_sphere_light([0.0, 1.0, 0.0], 0.5, np.array([0.8, 0.5, 0.3]), env)
    assert np.all(zero == 0)
    mesh = builtin_mesh("icosphere", subdivisions=4)
    mesh.apply_scale(0.5)
    mesh.apply_translation([0.0, 1.0, 0.0])
    pts, nrm, valid = surface_samples(mesh, c, r, geodesic_directions(92))
    alb = surface_albedo_sh(mesh, c, r, np.array([0.8, 0.5, 0.3]), ORDER)
    extra = np.full(valid.shape + (3,), np.pi)  # E = pi: radiance 1 before the albedo
    em = first_pass(pts, nrm, valid, c, r, env, voronoi_cell_sums(ORDER), alb, extra_irradiance=extra)
    const = first_pass(pts, nrm, valid, c, r, _const_env(), voronoi_cell_sums(ORDER), alb)
    np.testing.assert_allclose(em, const, atol=1e-12)
    with pytest.raises(ValueError, match="extra_irradiance must have shape"):
        first_pass(pts, nrm, valid, c, r, env, voronoi_cell_sums(ORDER), alb, extra_irradiance=extra[:, :5])


def test_first_pass_emission_of_a_higher_order():
    """``first_pass(order=n)`` with the cell sums and albedo of order ``k > n``: the samples' radiance (visibility of
    order ``n``) projected to order ``k``; with a uniform albedo its first ``n * n`` coefficients are the order-``n``
    emission's."""
    mesh = builtin_mesh("icosphere", subdivisions=3)
    mesh.apply_scale(0.5)
    c, r = np.array([[0.0, 1.0, 0.0], [0.9, 1.2, 0.0]]), np.array([0.5, 0.4])
    pts, nrm, valid = surface_samples(mesh, c[:1], r[:1], geodesic_directions(92))
    env = np.zeros((100, 3))  # an order-10 sky, brighter above
    env[0], env[2] = [3.0, 2.5, 2.0], [1.0, 0.8, 0.6]

    def uniform(order):
        alb = np.zeros((1, order * order, 3))
        alb[0, 0] = np.array([0.8, 0.5, 0.3]) * np.sqrt(4 * np.pi)
        return alb

    em4 = first_pass(pts, nrm, valid, c, r, env, voronoi_cell_sums(4), uniform(4))
    em6 = first_pass(pts, nrm, valid, c, r, env, voronoi_cell_sums(6), uniform(6), order=4)
    assert em6.shape == (1, 36, 3)
    np.testing.assert_allclose(em6[:, :16], em4, rtol=1e-12, atol=1e-13)
    assert np.abs(em6[:, 16:]).max() > 1e-3 * np.abs(em4).max()  # the neighbour's shadow has higher bands


def _const_env():
    """The order-4 constant environment whose unoccluded irradiance is pi (radiance 1)."""
    env = np.zeros((16, 3))
    env[0] = np.sqrt(4 * np.pi)
    return env


@pytest.mark.parametrize("order", [1, 2, 3, 4, 5, 6])
def test_generated_squares_match_the_gaunt_product(order, rng):
    """The straight-line squares of ``_square_kernels`` are ``sh.product(v, v)`` truncated to the order (the
    generic Gaunt tier) on the columns they are given, and leave the other columns alone."""
    from prtlab.spherelights._square_kernels import SQUARE_COLUMNS, square_columns

    n2, width = order * order, 37
    v = rng.normal(size=(n2, SQUARE_COLUMNS))
    expect = sh.product(v[:, :width].T, v[:, :width].T, order=order, channels=False).T
    got = v.copy()
    square_columns(got.reshape(-1), order, width)
    np.testing.assert_allclose(got[:, :width], expect, rtol=1e-13, atol=1e-13 * np.abs(expect).max())
    np.testing.assert_array_equal(got[:, width:], v[:, width:])


def test_square_kernels_are_generated():
    """``_square_kernels.py`` is the output of its generator (regenerate it after changing either): the same
    text, with its Gaunt literals equal to the generator's to a few ulp (the Gaunt table comes from a quadrature
    whose last bit depends on the install's BLAS)."""
    import re
    from pathlib import Path

    from prtlab.spherelights import _square_kernels
    from prtlab.spherelights._square_source import square_kernel_source

    literal = re.compile(r"-?\d+\.\d+(?:e-?\d+)?")
    committed, generated = Path(_square_kernels.__file__).read_text(), square_kernel_source()
    assert literal.split(committed) == literal.split(generated)
    a = np.array(literal.findall(committed), dtype=float)
    b = np.array(literal.findall(generated), dtype=float)
    assert a.size == b.size > 1000
    np.testing.assert_allclose(a, b, rtol=8 * np.finfo(float).eps, atol=0)


@pytest.mark.parametrize("obj", [[0, 0, 0, 1, 2, 3, 4], [0, 0, 1, 2, 3]])
@pytest.mark.parametrize("average", ["cosine", "paper"])
def test_fused_second_pass_object_chain_matches_composed_tier(obj, average, rng):
    """Per object, HYB, most objects of one light: the fused tier reads those lights' exponentials from the
    objects' prefix chain (``_Mode.object_chain``; an even and an odd number of ranks) and agrees with the
    composed tier."""
    from prtlab.spherelights._passes import _LANES

    obj = np.array(obj)
    n_sph, n_recv = len(obj), 2 * _LANES + 7
    p = rng.uniform(-2, 2, size=(n_recv, 3))
    n = random_directions(rng, n_recv)
    c = rng.normal(size=(n_sph, 3)) * 1.5
    r = rng.uniform(0.2, 0.6, n_sph)
    inter = np.zeros((n_sph, n_sph), dtype=bool)
    inter[0, 1] = inter[1, 0] = True
    rot = np.stack([np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(n_sph)])
    em = rng.normal(size=(n_sph, 16, 3)) * 0.1
    em[:, 0] += 1.0
    args = (p, n, c, r, obj, inter, rot, em, _env_sh())
    d1, i1 = second_pass(*args, blocking="object", exp_method="hyb", method="fused", average=average)
    d2, i2 = second_pass(*args, blocking="object", exp_method="hyb", method="numba", average=average)
    np.testing.assert_allclose(d1, d2, atol=1e-11)
    np.testing.assert_allclose(i1, i2, atol=1e-11)
    assert np.abs(i1).max() > 0.1


@pytest.mark.parametrize("exp_method, ground", [("hyb", False), ("ol", False), ("hyb", True), ("ol", True)])
def test_fused_first_pass_matches_composed_tier(exp_method, ground, rng):
    """The samples' direct light by the second pass's fused kernel (``method="fused"``, the default) agrees with the
    composed tier (``blocker_log_sum``, ``sh.exp``, ``environment_transfer``) to rounding, with and without a
    ground hiding part of the environment (OL with a ground takes the composed tier); lights near each other shade
    each other's samples; an unknown method raises."""
    n_sph = 5
    c = rng.uniform(-1.0, 1.0, size=(n_sph, 3))
    r = rng.uniform(0.3, 0.6, n_sph)
    dirs = geodesic_directions(92)
    pts = c[:, None] + r[:, None, None] * dirs[None]
    nrm = np.broadcast_to(dirs, pts.shape) * rng.uniform(0.5, 2.0, size=(n_sph, 92, 1))  # any length
    valid = rng.random((n_sph, 92)) > 0.1
    alb = rng.uniform(0.2, 0.8, size=(n_sph, ORDER * ORDER, 3))
    rect = np.array([[-1.5, 0.0, 0.0, 3.0, 0.0, 0.0, 3.0]]) if ground else None
    args = (pts, nrm, valid, c, r, _env_sh(), voronoi_cell_sums(ORDER), alb)
    fused = first_pass(*args, exp_method=exp_method, ground=rect)
    composed = first_pass(*args, exp_method=exp_method, ground=rect, method="numba")
    np.testing.assert_allclose(fused, composed, rtol=0, atol=1e-12 * np.abs(composed).max())
    alone = first_pass(pts[:1], nrm[:1], valid[:1], c[:1], r[:1], *args[5:7], alb[:1], exp_method=exp_method,
                       ground=rect)
    assert np.abs(fused[0] - alone[0]).max() > 1e-3 * np.abs(alone[0]).max()  # the other lights block
    with pytest.raises(ValueError, match="method must be"):
        first_pass(*args, method="reference")


def test_first_pass_sample_weight():
    """Weights of the samples' radiance: ones are the paper's emission; a leading axis gives one emission per set of
    weights, each that of its own call; constant weights scale the emission; a wrong shape raises."""
    mesh = builtin_mesh("icosphere", subdivisions=3)
    mesh.apply_scale(0.5)
    mesh.apply_translation([0.0, 1.0, 0.0])
    c, r = np.array([[0.0, 1.0, 0.0]]), np.array([0.5])
    pts, nrm, valid = surface_samples(mesh, c, r, geodesic_directions(92))
    alb = surface_albedo_sh(mesh, c, r, np.array([0.8, 0.5, 0.3]), ORDER)
    args = (pts, nrm, valid, c, r, _const_env(), voronoi_cell_sums(ORDER), alb)
    paper = first_pass(*args)
    np.testing.assert_allclose(first_pass(*args, sample_weight=np.ones((1, 92))), paper, atol=1e-14)
    w = np.linspace(0.0, 1.0, 92)[None]
    both = first_pass(*args, sample_weight=np.stack([np.full((1, 92), 0.5), w]))
    assert both.shape == (2,) + paper.shape
    np.testing.assert_allclose(both[0], 0.5 * paper, atol=1e-14)
    np.testing.assert_allclose(both[1], first_pass(*args, sample_weight=w), atol=1e-14)
    with pytest.raises(ValueError, match="sample_weight must have shape"):
        first_pass(*args, sample_weight=np.ones(92))

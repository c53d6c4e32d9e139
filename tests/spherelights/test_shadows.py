"""Tests of prtlab.spherelights._shadows (Ren et al. 2006 soft shadows from spherical blockers)."""

import numpy as np
import pytest

from prtlab import sh
from prtlab.spherelights import adjust_blockers, blocker_log_sum, direct_irradiance, environment_transfer
from tests.conftest import MC_SIGMAS, random_directions

ORDER = 4


def _env_sh(order=ORDER):
    """A positive band-limited environment (order 4): its SH projection is exact."""
    env = np.zeros((order * order, 3))
    env[0] = [3.0, 2.5, 2.0]
    env[1] = [0.4, 0.5, 0.6]     # ~ y: brighter sky
    env[3] = [0.3, 0.1, -0.2]
    env[6] = [0.2, 0.2, 0.2]
    env[10] = [0.1, -0.1, 0.05]
    return env


def _env_eval(env, dirs):
    return sh.basis(dirs, ORDER) @ env


def _hemisphere_rule(normal, n_theta=200, n_phi=400):
    """Gauss-Legendre in cos(theta) x uniform phi over the hemisphere of ``normal``: (dirs, weights)."""
    z, wz = np.polynomial.legendre.leggauss(n_theta)
    z, wz = 0.5 * (z + 1.0), 0.5 * wz
    phi = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi
    st = np.sqrt(1 - z * z)
    local = np.stack([st[:, None] * np.cos(phi), st[:, None] * np.sin(phi), np.broadcast_to(z[:, None], (n_theta, n_phi))], -1)
    w = (wz[:, None] * np.full(n_phi, 2 * np.pi / n_phi)).reshape(-1)
    t = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    t /= np.linalg.norm(t)
    b = np.cross(normal, t)
    return local.reshape(-1, 3) @ np.stack([t, b, normal]), w


def _sphere_hit(origins, dirs, c, r):
    oc = origins - c
    bq = np.einsum("...k,...k->...", oc, dirs)
    cq = np.einsum("...k,...k->...", oc, oc) - r * r
    disc = bq * bq - cq
    t = -bq - np.sqrt(np.maximum(disc, 0.0))
    return (disc > 0) & (t > 0)


def _mc_irradiance(p, n, centres, radii, env, n_samples, rng):
    """Cosine-weighted MC of int V L cos with analytic spheres: (E (3,), standard error (3,))."""
    u1, u2 = rng.random(n_samples), rng.random(n_samples)
    rr, ph = np.sqrt(u1), 2 * np.pi * u2
    local = np.stack([rr * np.cos(ph), rr * np.sin(ph), np.sqrt(1 - u1)], -1)
    t = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    t /= np.linalg.norm(t)
    dirs = local @ np.stack([t, np.cross(n, t), n])
    vis = np.ones(n_samples, dtype=bool)
    for c, r in zip(centres, radii):
        vis &= ~_sphere_hit(p, dirs, c, r)
    f = np.pi * vis[:, None] * _env_eval(env, dirs)
    return f.mean(axis=0), f.std(axis=0, ddof=1) / np.sqrt(n_samples)


# ----------------------------------------------------------------- known answers and tiers


def test_unoccluded_irradiance_is_the_exact_projection():
    env = _env_sh()
    n = np.array([[0.0, 1.0, 0.0], [0.6, 0.8, 0.0]])
    e = direct_irradiance(np.zeros((2, 3)), n, np.zeros((0, 3)), np.zeros(0), env, exp_method="exact")
    for k in range(2):
        d, w = _hemisphere_rule(n[k])
        ref = (w * (_env_eval(env, d) * (d @ n[k])[:, None]).T).sum(axis=1)
        np.testing.assert_allclose(e[k], ref, rtol=1e-9)


def test_transfer_is_exact_projection(rng):
    env = _env_sh()
    n = np.array([0.0, 0.0, 1.0])
    t = environment_transfer(n, env)
    d, w = sh.quadrature(1, degree=80)
    f = _env_eval(env, d) * np.maximum(d @ n, 0)[:, None]
    # independent projection on a fine rule: error from the kink at the horizon only
    proj = sh.basis(d, ORDER).T @ (w[:, None] * f)
    np.testing.assert_allclose(t, proj, atol=2e-3)


def test_kernel_matches_reference_tier(rng):
    p = rng.normal(size=(40, 3))
    n = random_directions(rng, 40)
    c = rng.normal(size=(6, 3)) * 2.0
    r = rng.uniform(0.1, 1.0, 6)
    for order in (1, 4, 6):
        a = blocker_log_sum(p, n, c, r, order)
        b = blocker_log_sum(p, n, c, r, order, method="reference")
        np.testing.assert_allclose(a, b, atol=1e-12)


def test_adjustment_rules():
    p = np.zeros(3)
    n = np.array([0.0, 1.0, 0.0])
    c = np.array([[0.5, 2.0, 0.0], [0.5, -2.0, 0.0], [1.0, 0.2, 0.0]])  # none contains p
    r = np.array([1.0, 1.0, 0.5])
    ca, ra = adjust_blockers(p, n, c, r)
    np.testing.assert_allclose(ca[0], c[0]); assert ra[0] == 1.0       # above: kept
    assert ra[1] == 0.0                                                   # below: culled
    assert ra[2] == pytest.approx(0.35)                                   # (h + r) / 2
    assert ca[2, 1] == pytest.approx(0.35) and ca[2, 1] + ra[2] == pytest.approx(0.7)  # tangent, same top
    # the receiver is never inside an adjusted sphere (hypothesis-like random sweep)
    rng = np.random.default_rng(1)
    cc = rng.normal(size=(500, 3))
    rr = rng.uniform(0.01, 2.0, 500)
    ca, ra = adjust_blockers(p, n, cc, rr)
    assert np.all(np.linalg.norm(ca, axis=1) >= ra * (1 - 1e-12))
    # continuity at h = +-r (spheres not containing p)
    ca, ra = adjust_blockers(p, n, [[1.3, 1.0 - 1e-9, 0.0], [1.3, -1.0 + 1e-9, 0.0]], [1.0, 1.0])
    assert abs(ra[0] - 1.0) < 1e-8 and ra[1] < 1e-8
    # a sphere containing the receiver is culled
    ca, ra = adjust_blockers(p, n, [[0.1, 0.2, 0.0]], [0.5])
    assert ra[0] == 0.0


def test_empty_and_shapes():
    env = _env_sh()
    assert direct_irradiance(np.zeros((0, 3)), np.zeros((0, 3)), [[0, 1, 0]], [0.5], env).shape == (0, 3)
    assert blocker_log_sum(np.zeros((2, 5, 3)), np.ones((2, 5, 3)), [[0, 1, 0]], [0.5], 4).shape == (2, 5, 16)


def test_errors():
    env = _env_sh()
    with pytest.raises(ValueError, match="points must be a"):
        blocker_log_sum(np.zeros(2), np.ones(2), [[0, 1, 0]], [1.0], 4)
    with pytest.raises(ValueError, match="NaN or inf"):
        blocker_log_sum([[np.nan, 0, 0]], [[0, 1, 0]], [[0, 1, 0]], [1.0], 4)
    with pytest.raises(ValueError, match="same shape"):
        blocker_log_sum(np.zeros((2, 3)), np.ones((3, 3)), [[0, 1, 0]], [1.0], 4)
    with pytest.raises(ValueError, match="zero vectors"):
        blocker_log_sum(np.zeros((1, 3)), np.zeros((1, 3)), [[0, 1, 0]], [1.0], 4)
    with pytest.raises(ValueError, match=r"radii must have shape \(1,\)"):
        blocker_log_sum(np.zeros((1, 3)), np.ones((1, 3)), [[0, 1, 0]], [1.0, 2.0], 4)
    with pytest.raises(ValueError, match="non-negative"):
        blocker_log_sum(np.zeros((1, 3)), np.ones((1, 3)), [[0, 1, 0]], [-1.0], 4)
    with pytest.raises(ValueError, match="order must be an int in 1..8"):
        blocker_log_sum(np.zeros((1, 3)), np.ones((1, 3)), [[0, 1, 0]], [1.0], 9)
    with pytest.raises(ValueError, match="method must be"):
        blocker_log_sum(np.zeros((1, 3)), np.ones((1, 3)), [[0, 1, 0]], [1.0], 4, method="gpu")
    with pytest.raises(ValueError, match="exp_method must be"):
        direct_irradiance(np.zeros((1, 3)), np.ones((1, 3)), [[0, 1, 0]], [1.0], env, exp_method="taylor")
    with pytest.raises(ValueError, match="env_sh must be an"):
        direct_irradiance(np.zeros((1, 3)), np.ones((1, 3)), [[0, 1, 0]], [1.0], env[:15])
    with pytest.raises(TypeError, match="radii must be a real array"):
        blocker_log_sum(np.zeros((1, 3)), np.ones((1, 3)), [[0, 1, 0]], ["a"], 4)


# ----------------------------------------------------------------- against Monte Carlo (the paper's optimal case)


@pytest.mark.parametrize("exp_method", ["exact", "hyb", "ol"])
def test_one_sphere_over_a_plane_against_monte_carlo(exp_method, rng):
    """One analytic sphere over a plane: the reference is exact up to MC noise.

    Derived bound: with ``V_n = P_n V`` (rotated ``blocker_zh``) and ``T = P_n(L cos)``,
    ``E - E_true = (e - V_n) . T - int (I - P_n)V (I - P_n)(L cos)``, so
    ``|E - E_true| <= |e - V_n| |T| + |(I-P_n)V|_2 |(I-P_n)(L cos)|_2`` (Cauchy-Schwarz);
    ``|e - V_n|`` is the exponentiation (and table) error, computed here per receiver.
    """
    env = _env_sh()
    centre, radius = np.array([0.0, 1.0, 0.0]), 0.5
    n = np.array([0.0, 1.0, 0.0])
    xs = np.array([0.0, 0.4, 0.8, 1.5])
    pts = np.stack([xs, np.zeros_like(xs), np.zeros_like(xs)], -1)
    e = direct_irradiance(pts, np.broadcast_to(n, pts.shape), centre[None], [radius], env, exp_method=exp_method)
    g = blocker_log_sum(pts, np.broadcast_to(n, pts.shape), centre[None], [radius], ORDER)
    vis = sh.exp(g, method=exp_method)
    for k, p in enumerate(pts):
        ref, se = _mc_irradiance(p, n, [centre], [radius], env, 200_000, rng)
        d = centre - p
        theta = np.arcsin(radius / np.linalg.norm(d))
        vn = sh.zh_rotate(sh.blocker_zh(theta, ORDER), d / np.linalg.norm(d))
        t = environment_transfer(n, env)
        exp_err = np.linalg.norm(vis[k] - vn) * np.linalg.norm(t, axis=0)
        v_tail = np.sqrt(max(4 * np.pi - 2 * np.pi * (1 - np.cos(theta)) - vn @ vn, 0.0))
        dirs, w = _hemisphere_rule(n)
        lc = _env_eval(env, dirs) * (dirs @ n)[:, None]
        lc_tail = np.sqrt(np.maximum((w[:, None] * lc * lc).sum(0) - (t * t).sum(0), 0.0))
        bound = exp_err + v_tail * lc_tail
        assert np.all(np.abs(e[k] - ref) <= bound + MC_SIGMAS * se), (k, e[k], ref, bound, se)



def _union_of_caps_projection(axes, thetas, order, outside, n_gauss=48, h=1e-5):
    """``int_R y_k(w) dw`` for the union ``R`` of spherical caps ``(axes (S, 3) unit, thetas (S,))``, exactly
    (to ~1e-10), by Green's identity on the sphere: a boundary integral over the arcs of the cap circles that lie
    outside every other cap, by Gauss-Legendre between the analytic circle-circle crossings (smooth integrands).

    For ``l >= 1`` (``Delta y = -l(l+1) y``): ``int_R y = -1/(l(l+1)) oint_dR d_nu y ds``, ``d_nu`` the outward
    (polar-angle) derivative, central differences of step ``h`` (error ~ h^2 l^3). For ``l = 0``, with ``f(w) =
    ln(1 - w . b)`` (``Delta f = -1`` away from ``b``) and ``b = outside`` a direction in no cap:
    ``area(R) = oint_dR (nu . b) / (1 - w . b) ds`` (one cap about ``-b``: ``2 pi (1 - cos theta)``).
    """
    axes, thetas = np.asarray(axes, dtype=float), np.asarray(thetas, dtype=float)
    b = np.asarray(outside, dtype=float)
    band = np.repeat(np.arange(order), 2 * np.arange(order) + 1)[1:]
    x, wx = np.polynomial.legendre.leggauss(n_gauss)
    out = np.zeros(order * order)
    for i, (a, th) in enumerate(zip(axes, thetas)):
        e1 = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(a, e1)
        others = [j for j in range(len(axes)) if j != i]

        def circle(t, ph):
            return np.cos(t) * a + np.sin(t) * (np.cos(ph)[:, None] * e1 + np.sin(ph)[:, None] * e2)

        cuts = [0.0, 2 * np.pi]
        for j in others:  # circle i crosses circle j where A cos(phi) + B sin(phi) = C
            aa, bb = np.sin(th) * (e1 @ axes[j]), np.sin(th) * (e2 @ axes[j])
            cc = np.cos(thetas[j]) - np.cos(th) * (a @ axes[j])
            rho = np.hypot(aa, bb)
            if abs(cc) < rho:
                p0, dp = np.arctan2(bb, aa), np.arccos(cc / rho)
                cuts += [(p0 - dp) % (2 * np.pi), (p0 + dp) % (2 * np.pi)]
        cuts = np.sort(cuts)
        for lo, hi in zip(cuts[:-1], cuts[1:]):
            mid = circle(th, np.array([0.5 * (lo + hi)]))[0]
            if hi - lo < 1e-15 or any(mid @ axes[j] > np.cos(thetas[j]) for j in others):
                continue  # this arc lies inside another cap: not on the boundary of the union
            ph = 0.5 * (hi - lo) * x + 0.5 * (hi + lo)
            ds = 0.5 * (hi - lo) * wx * np.sin(th)
            w = circle(th, ph)
            nu = -np.sin(th) * a + np.cos(th) * (np.cos(ph)[:, None] * e1 + np.sin(ph)[:, None] * e2)
            dy = (sh.basis(circle(th + h, ph), order) - sh.basis(circle(th - h, ph), order)) / (2 * h)
            out[1:] -= (ds @ dy[:, 1:]) / (band * (band + 1))
            out[0] += (ds @ ((nu @ b) / (1.0 - w @ b))) / np.sqrt(4 * np.pi)
    return out


def test_union_of_caps_projection_known_answers():
    """The exact cap-union projection used by the three-sphere bound: one cap is ``sqrt(4 pi) e_0 - P_n(blocker)``
    (``blocker_zh`` rotated), a cap inside another adds nothing, and two disjoint caps add; an overlapping pair is
    less than the sum by the lens: its constant coefficient is the union's area ``2 pi (2 - cos r1 - cos r2) - A``
    over ``sqrt(4 pi)``, ``A`` the closed-form area of the lens of two caps at angular distance ``d``, and it
    does not depend on the point ``outside`` of Green's identity. Every coefficient agrees with a product rule
    of degree 1600 within the rule's error on an indicator: at most the area of the cells its boundary
    crosses, ``L (dt + dp)`` (``L = 2 pi (sin r1 + sin r2)`` bounds the boundary's length, ``dt``, ``dp`` the
    rule's largest node spacings), times ``max |Y| <= sqrt((2 l + 1) / 4 pi)``."""
    a = np.array([0.3, 0.9, 0.1]) / np.linalg.norm([0.3, 0.9, 0.1])
    b = np.array([-0.5, 0.8, -0.3]) / np.linalg.norm([-0.5, 0.8, -0.3])
    down = np.array([0.0, -1.0, 0.0])

    def one(axis, theta):
        return np.sqrt(4 * np.pi) * (np.arange(ORDER * ORDER) == 0) - sh.zh_rotate(sh.blocker_zh(theta, ORDER), axis)

    np.testing.assert_allclose(_union_of_caps_projection([a], [0.4], ORDER, down), one(a, 0.4), atol=1e-9)
    np.testing.assert_allclose(_union_of_caps_projection([a, a], [0.4, 0.1], ORDER, down), one(a, 0.4), atol=1e-9)
    assert np.arccos(a @ b) > 0.4 + 0.3
    np.testing.assert_allclose(_union_of_caps_projection([a, b], [0.4, 0.3], ORDER, down),
                               one(a, 0.4) + one(b, 0.3), atol=1e-9)
    c = np.array([0.6, 0.9, -0.2]) / np.linalg.norm([0.6, 0.9, -0.2])
    assert np.arccos(a @ c) < 0.4 + 0.3
    got = _union_of_caps_projection([a, c], [0.4, 0.3], ORDER, down)
    assert got[0] < (one(a, 0.4) + one(c, 0.3))[0] - 1e-3
    side = np.array([0.0, -0.6, 0.8])
    assert _union_of_caps_projection([a, c], [0.4, 0.3], ORDER, side)[0] == pytest.approx(got[0], abs=1e-10)
    r1, r2, dist = 0.4, 0.3, np.arccos(a @ c)
    lens = 2 * (np.pi - np.arccos((np.cos(dist) - np.cos(r1) * np.cos(r2)) / (np.sin(r1) * np.sin(r2)))
                - np.cos(r1) * np.arccos((np.cos(r2) - np.cos(dist) * np.cos(r1)) / (np.sin(dist) * np.sin(r1)))
                - np.cos(r2) * np.arccos((np.cos(r1) - np.cos(dist) * np.cos(r2)) / (np.sin(dist) * np.sin(r2))))
    assert got[0] == pytest.approx((2 * np.pi * (2 - np.cos(r1) - np.cos(r2)) - lens) / np.sqrt(4 * np.pi), abs=1e-12)
    degree = 1600
    d, w = sh.quadrature(1, degree=degree)
    brute = sh.basis(d, ORDER).T @ (w * ((d @ a > np.cos(r1)) | (d @ c > np.cos(r2))))
    theta = np.sort(np.arccos(np.clip(np.unique(np.round(d[:, 2], 12)), -1, 1)))
    spacing = np.max(np.diff(np.concatenate([[0.0], theta, [np.pi]]))) + 2 * np.pi / (degree + 1)
    bound = 2 * np.pi * (np.sin(r1) + np.sin(r2)) * spacing * np.sqrt((2 * (ORDER - 1) + 1) / (4 * np.pi))
    assert np.max(np.abs(got - brute)) <= bound


@pytest.mark.parametrize("exp_method", ["exact", "hyb", "ol"])
def test_three_spheres_over_a_plane_against_monte_carlo(exp_method, rng):
    """Three disjoint analytic spheres (radii 0.45, 0.6, 0.3) over a plane, 12 receivers (6 of which see two
    blockers' cones overlap): against MC of ``int V L cos`` with ``V`` the visibility of the union (exact up to
    noise; 200k cosine-weighted samples per receiver).

    Derived bound, as the one-sphere test: with ``V_n = P_n V`` and ``T = P_n(L cos)``,
    ``|E - E_true| <= |e - V_n| |T| + |(I-P_n)V|_2 |(I-P_n)(L cos)|_2``; here ``V = 1 - 1_R`` with ``R`` the union
    of the three cones' caps, so ``V_n = sqrt(4 pi) e_0 - P_n 1_R`` (:func:`_union_of_caps_projection`, exact)
    and ``|(I-P_n)V|^2 = 4 pi - area(R) - |V_n|^2``. ``|e - V_n|`` is the whole approximation of the method
    (the truncated products of the exponential, HYB/OL, the blocker-log table), computed per receiver; 4 MC
    standard errors on top. Measured (this seed): relative RMS ``|E - E_mc| / |E_mc|`` over receivers and RGB
    1.64 % exact, 1.64 % HYB, 1.77 % OL, with the MC's own relative standard error 0.13 %; the order-4
    projection itself (``V_n . T``) is at 0.54 %, so about 1.5 % comes from exponentiating the summed logs, even
    exactly. The largest ``|E - E_mc| / (bound + 4 se)`` is 0.36 (exact), 0.36 (HYB), 0.39 (OL): the
    Cauchy-Schwarz bound lets a 3 % radius error through, not a 10 % one or a missing sphere.
    """
    env = _env_sh()
    centres = np.array([[-0.9, 0.9, 0.2], [0.35, 1.1, -0.25], [1.2, 0.6, 0.45]])
    radii = np.array([0.45, 0.6, 0.3])
    for i in range(3):  # disjoint, entirely above the plane: no blocker is adjusted at these receivers
        assert centres[i, 1] > radii[i]
        for j in range(i):
            assert np.linalg.norm(centres[i] - centres[j]) > radii[i] + radii[j]
    n = np.array([0.0, 1.0, 0.0])
    xs, zs = np.meshgrid([-1.5, -0.9, -0.3, 0.35, 0.95, 1.6], [-0.4, 0.4])
    pts = np.stack([xs.ravel(), np.zeros(xs.size), zs.ravel()], -1)
    nrm = np.broadcast_to(n, pts.shape)
    e = direct_irradiance(pts, nrm, centres, radii, env, exp_method=exp_method)
    vis = sh.exp(blocker_log_sum(pts, nrm, centres, radii, ORDER), method=exp_method)
    t = environment_transfer(n, env)
    dirs, w = _hemisphere_rule(n)
    lc = _env_eval(env, dirs) * (dirs @ n)[:, None]
    lc_tail = np.sqrt(np.maximum((w[:, None] * lc * lc).sum(0) - (t * t).sum(0), 0.0))
    overlapping = 0
    for k, p in enumerate(pts):
        ref, se = _mc_irradiance(p, n, centres, radii, env, 200_000, rng)
        d = centres - p
        dist = np.linalg.norm(d, axis=1)
        axes, theta = d / dist[:, None], np.arcsin(radii / dist)
        overlapping += any(np.arccos(axes[i] @ axes[j]) < theta[i] + theta[j] for i in range(3) for j in range(i))
        cap = _union_of_caps_projection(axes, theta, ORDER, -n)
        vn = -cap
        vn[0] += np.sqrt(4 * np.pi)
        exp_err = np.linalg.norm(vis[k] - vn) * np.linalg.norm(t, axis=0)
        v_tail = np.sqrt(max(4 * np.pi - np.sqrt(4 * np.pi) * cap[0] - vn @ vn, 0.0))
        bound = exp_err + v_tail * lc_tail
        assert np.all(np.abs(e[k] - ref) <= bound + MC_SIGMAS * se), (k, e[k], ref, bound, se)
    assert overlapping == 6  # the union, not only disjoint cones, is exercised


def test_environment_transfer_of_a_higher_order_environment_is_exact(rng):
    """With an environment of order 3n - 2 the transfer is the exact projection of L times the clamped cosine of
    order 2n - 1 (a product y_k Y_q sees bands <= 3n - 3 of L); with the environment cut to order n it is not."""
    n_env = 3 * ORDER - 2
    env = rng.normal(size=(n_env * n_env, 2)) / (1 + np.arange(n_env * n_env))[:, None]
    nrm = random_directions(rng, 5)
    t = environment_transfer(nrm, env, ORDER)
    dirs, w = sh.quadrature(1, degree=3 * n_env)
    hi = 2 * ORDER - 1
    cos = sh.zh_rotate(sh.clamped_cosine_zh(hi), nrm) @ sh.basis(dirs, hi).T  # (5, Q)
    ref = np.einsum("q,qk,qc,bq->bkc", w, sh.basis(dirs, ORDER), sh.basis(dirs, n_env) @ env, cos)
    np.testing.assert_allclose(t, ref, atol=1e-10)
    cut = environment_transfer(nrm, env[: ORDER * ORDER])
    assert np.abs(cut - ref).max() > 1e-3
    with pytest.raises(ValueError, match="cannot give a transfer of order"):
        environment_transfer(nrm, env[:4], ORDER)


def test_transfer_matrix_kept_is_the_computed_one(rng):
    """``transfer_matrix`` keeps the last environments' matrices: each call equals the sum of Gaunt products computed
    afresh, bit for bit, for environments of another order, channels, dtype or one signed zero apart, and a caller
    writing into its array changes no later call's."""
    from prtlab.sh._gaunt import _gaunt_block
    from prtlab.spherelights._shadows import transfer_matrix

    def fresh(env, order):
        n_env = int(round(np.sqrt(env.shape[0])))
        hi = 2 * order - 1
        gi, gj, gk, gv = _gaunt_block(hi, n_env, order)
        a = np.zeros((hi * hi, order * order, env.shape[1]))
        np.add.at(a, (gi, gk), gv[:, None] * env[gj])
        return a.reshape(hi * hi, -1)

    env = rng.normal(size=(25, 3))
    zero = env.copy()
    zero[3] = [0.0, -0.0, 0.0]
    signed = zero.copy()
    signed[3, 1] = 0.0
    cases = [(env, 4), (env, 3), (env[:16], 4), (env[:, :1], 4), (env.astype(np.float32), 4), (zero, 4),
             (signed, 4), (env, 4)]
    for e, order in cases * 2:
        ours = transfer_matrix(e, order)
        expect = fresh(e, order)
        assert ours.dtype == expect.dtype and ours.shape == expect.shape
        assert np.array_equal(ours.view(np.uint64), expect.view(np.uint64))
        assert ours.flags.writeable and ours.flags.c_contiguous
        ours[:] = np.nan  # the kept matrix is not the caller's
    assert not np.isnan(transfer_matrix(env, 4)).any()


def test_one_thread_below_restores_the_thread_counts():
    """Below the threshold the block runs with numba and every BLAS library on one thread; the counts before are
    restored after it, also when it raises; at or above the threshold nothing changes."""
    import numba
    from threadpoolctl import threadpool_info

    from prtlab.spherelights._shadows import one_thread_below

    def blas():
        return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]

    numba_before, blas_before = numba.get_num_threads(), blas()
    with one_thread_below(1, 2):
        assert numba.get_num_threads() == 1 and all(n == 1 for n in blas())
    assert (numba.get_num_threads(), blas()) == (numba_before, blas_before)
    with pytest.raises(RuntimeError), one_thread_below(1, 2):
        raise RuntimeError("inside")
    assert (numba.get_num_threads(), blas()) == (numba_before, blas_before)
    with one_thread_below(2, 2):
        assert (numba.get_num_threads(), blas()) == (numba_before, blas_before)

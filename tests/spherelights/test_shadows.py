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

"""Tests of prtlab/sh/_explog.py: SH exponential / logarithm, spherical-blocker ZH tables."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import prtlab.sh._explog as explog
from prtlab.sh import blocker_log_zh, blocker_zh, exp, log, product, product_exact, quadrature, zh_rotate
from prtlab.sh._eval import basis_reference
from tests.conftest import FLOAT_TOLERANCE, random_directions

TOL = FLOAT_TOLERANCE[np.float64]
SQRT4PI = np.sqrt(4 * np.pi)
ALL_METHODS = ["hyb", "ol", "exact", "hyb-reference", "ol-reference"]
Z = np.array([0.0, 0.0, 1.0])


def _one(order):
    e = np.zeros(order * order)
    e[0] = SQRT4PI
    return e


def _rms_error(approx, exact):
    """RMS over the sphere of the function error (orthonormal basis)."""
    return np.linalg.norm(approx - exact, axis=-1) / SQRT4PI


# ----------------------------------------------------------------------------- blocker ZH: known answers


def test_blocker_zh_matches_piecewise_gauss_legendre():
    order = 6
    for theta in np.radians([3.0, 25.0, 60.0, 90.0]):
        c = np.cos(theta)
        z, w = np.polynomial.legendre.leggauss(20)  # exact for the polynomial on [-1, c]
        zz = -1 + (z + 1) * (c + 1) / 2
        yz = explog._legendre(zz, order - 1) * explog._zh_norm(order)
        expected = 2 * np.pi * (w * (c + 1) / 2) @ yz
        np.testing.assert_allclose(blocker_zh(theta, order), expected, atol=1e-13)


def test_blocker_zh_limits_and_shapes():
    np.testing.assert_allclose(blocker_zh(0.0, 4), [SQRT4PI, 0, 0, 0], atol=TOL)
    half = blocker_zh(np.pi / 2, 3)  # the lower hemisphere: DC sqrt(4 pi) / 2, no l = 2 term
    np.testing.assert_allclose(half[[0, 2]], [SQRT4PI / 2, 0.0], atol=TOL)
    assert half[1] < 0
    assert blocker_zh(np.zeros((2, 3)), 5).shape == (2, 3, 5)
    assert blocker_zh(np.zeros(0), 5).shape == (0, 5)


# ----------------------------------------------------------------------------- blocker logs


@pytest.mark.parametrize("order", [1, 2, 4, 6])
def test_blocker_log_is_the_inverse_of_the_zonal_exp(order):
    theta = np.radians([1.0, 5.0, 20.0, 45.0, 60.0, 80.0, 90.0])
    g = blocker_log_zh(theta, order, method="solve")
    b = blocker_zh(theta, order)
    resid = np.linalg.norm(explog._zonal_exp(g, order) - b, axis=-1) / np.linalg.norm(b, axis=-1)
    assert np.all(resid[theta <= np.radians(20)] < 1e-12)
    assert np.all(resid[theta <= np.radians(60)] < 1e-10)
    assert np.all(resid < 1e-6)  # ill-conditioned near pi/2; documented


def test_blocker_log_exact_sh_tier_agrees_with_zonal_tier(rng):
    order = 4
    theta = np.radians([10.0, 35.0, 60.0])
    axes = random_directions(rng, 3)
    g = blocker_log_zh(theta, order, method="solve")
    sh_exp = exp(zh_rotate(g, axes), method="exact")
    np.testing.assert_allclose(sh_exp, zh_rotate(blocker_zh(theta, order), axes), atol=1e-10)


def test_blocker_log_table_matches_solve():
    order = 4
    radii = np.arange(explog._N_RADII + 1) * (np.pi / 2 / explog._N_RADII)
    mid = 0.5 * (radii[1:] + radii[:-1])
    solved = blocker_log_zh(mid, order, method="solve")
    table = blocker_log_zh(mid, order)
    err = np.linalg.norm(table - solved, axis=-1)
    assert np.all(err <= 1e-4 * np.linalg.norm(solved, axis=-1) + 1e-12)
    # knots reproduce the solve exactly; theta = 0 is the zero vector
    np.testing.assert_allclose(blocker_log_zh(radii[[0, 7, 256]], order),
                               blocker_log_zh(radii[[0, 7, 256]], order, method="solve"), atol=1e-9)
    np.testing.assert_array_equal(blocker_log_zh(0.0, order), np.zeros(order))


def test_blocker_log_shapes():
    assert blocker_log_zh(0.3, 4).shape == (4,)
    assert blocker_log_zh(np.full((2, 5), 0.3), 3).shape == (2, 5, 3)
    assert blocker_log_zh(np.zeros((0,)), 3).shape == (0, 3)
    assert blocker_log_zh(np.zeros((0,)), 3, method="solve").shape == (0, 3)
    # small blockers have small logs that grow with the radius
    norms = np.linalg.norm(blocker_log_zh(np.radians([5, 20, 40, 60]), 4), axis=-1)
    assert np.all(np.diff(norms) > 0)


def test_small_blocker_log_is_minus_its_cap():
    """log(1 - c) = -c - c*c/2 - ...: for the order-4 ZH ``c`` of a 5-degree cap (closed form
    ``c_l = 2 pi sqrt((2l+1)/(4 pi)) (P_{l-1} - P_{l+1})(cos a) / (2l+1)``), each truncated product
    ``c^{*k}`` has L2 norm at most ``s^{k-1} |c|`` with ``s = sum_l |c_l| sqrt((2l+1)/(4 pi)) >= sup |c|``,
    so ``|log + c| <= |c| (-log(1 - s) / s - 1)``, plus the table's interpolation error (1e-4 relative)."""
    from numpy.polynomial.legendre import legval

    order, x = 4, np.cos(np.radians(5.0))
    p = [legval(x, [0.0] * k + [1.0]) for k in range(order + 1)]
    ell = np.arange(order)
    integral = np.array([1 - x] + [(p[l - 1] - p[l + 1]) / (2 * l + 1) for l in range(1, order)])
    cap = 2 * np.pi * np.sqrt((2 * ell + 1) / (4 * np.pi)) * integral
    s = np.sum(np.abs(cap) * np.sqrt((2 * ell + 1) / (4 * np.pi)))
    got = blocker_log_zh(np.radians(5.0), order)
    bound = np.linalg.norm(cap) * (-np.log1p(-s) / s - 1) + 1e-4 * np.linalg.norm(got)
    assert np.linalg.norm(got + cap) <= bound, (np.linalg.norm(got + cap), bound)


# ----------------------------------------------------------------------------- exp: known answers and identities


@pytest.mark.parametrize("method", ALL_METHODS)
@pytest.mark.parametrize("order", [1, 2, 4])
def test_exp_of_zero_is_one(method, order):
    np.testing.assert_allclose(exp(np.zeros(order * order), method=method), _one(order), atol=TOL)


@pytest.mark.parametrize("method", ALL_METHODS)
def test_order_one_is_the_scalar_exponential(method):
    f = np.array([[-2.0], [0.0], [1.5]])
    np.testing.assert_allclose(exp(f, method=method, channels=False), SQRT4PI * np.exp(f / SQRT4PI), rtol=1e-14)


@given(order=st.integers(1, 5), seed=st.integers(0, 2**31), dc=st.floats(-5, 5))
def test_dc_isolation_every_tier(order, seed, dc):
    rng = np.random.default_rng(seed)
    f = rng.normal(size=(3, order * order)) * rng.uniform(0.01, 2.0)
    shifted = f.copy()
    shifted[:, 0] += dc * SQRT4PI
    for method in ALL_METHODS:
        np.testing.assert_allclose(exp(shifted, method=method), np.exp(dc) * exp(f, method=method),
                                   rtol=1e-12, atol=1e-12)


@settings(max_examples=12)
@given(order=st.integers(1, 4), seed=st.integers(0, 2**31))
def test_exact_tier_matches_taylor_series_of_products(order, seed):
    """exp* = sum f^k / k!, products at working order 10, truncated at the end.

    With |f| <= 0.2 the parts lost by truncating at band 10 come back to bands
    < order only after >= 7 factors of f in all (size ~ |f|^7 / 7!).
    """
    rng = np.random.default_rng(seed)
    f = rng.normal(size=order * order)
    f *= rng.uniform(0.01, 0.2) / np.linalg.norm(f)
    work = 10
    fw = np.zeros(work * work)
    fw[: order * order] = f
    term = _one(work)
    total = term.copy()
    for k in range(1, 20):
        term = product(term, fw) / k
        total += term
    np.testing.assert_allclose(exp(f, method="exact"), total[: order * order], atol=1e-11)


def test_exact_tier_is_converged_on_blocker_sums(rng):
    f = explog._blocker_sums(rng, 100, 4)
    y = basis_reference(*[quadrature(1, degree=2 * explog._exact_degree(4))[0]], 4)
    _, w = quadrature(1, degree=2 * explog._exact_degree(4))
    vals = f @ y.T
    fine = (np.exp(vals) * w) @ y
    np.testing.assert_allclose(exp(f, method="exact"), fine, atol=1e-11)


@given(order=st.integers(1, 5), seed=st.integers(0, 2**31), scale=st.floats(0.001, 40.0))
def test_ol_and_hyb_kernels_match_numpy_reference(order, seed, scale):
    rng = np.random.default_rng(seed)
    f = rng.normal(size=(9, order * order, 2))
    f *= scale / np.linalg.norm(f, axis=1, keepdims=True)
    for method in ("ol", "hyb"):
        np.testing.assert_allclose(exp(f, method=method), exp(f, method=method + "-reference"),
                                   rtol=1e-12, atol=1e-12)


def test_hyb_equals_ol_below_its_threshold(rng):
    f = rng.normal(size=(20, 16))
    f[:, 1:] *= 0.9 * explog._HYB_THRESHOLD / np.linalg.norm(f[:, 1:], axis=1, keepdims=True)
    np.testing.assert_allclose(exp(f, method="hyb"), exp(f, method="ol"), rtol=1e-14, atol=1e-14)


def test_ol_is_nearly_exact_at_order_2(rng):
    # exp of a band-1 function is zonal about its gradient: exactly a 1 + b fh at order 2
    f = explog._blocker_sums(rng, 300, 2)
    r = np.linalg.norm(f[:, 1:], axis=1)
    inside = r < explog._ol_table(2)[0]
    err = _rms_error(exp(f, method="ol"), exp(f, method="exact"))
    assert np.all(err[inside] < 1e-3)


def test_ol_is_no_worse_than_the_first_order_member_of_its_family():
    """OL fits ``a(r) 1 + b(r) fh`` to ``exp*(fh)`` by least squares per norm ``r`` over sums of blocker logs
    (DC removed, each also halved 1..8 times: ``_compute_ol_table``). ``a = b = 1`` (the first-order Taylor
    polynomial) is a member of that family, so on fresh sums drawn the same way OL's mean squared error is at
    most the Taylor polynomial's: the paired difference is held at >= -4 standard errors."""
    rng = np.random.default_rng(20060730 + 1)  # not the training seed
    f = explog._blocker_sums(rng, 600, 4)
    f[:, 0] = 0.0
    fh = (2.0 ** -np.arange(explog._N_HALVINGS + 1)[:, None, None] * f[None]).reshape(-1, 16)
    truth = explog._exp_exact_rows(fh)
    taylor = fh.copy()
    taylor[:, 0] = SQRT4PI
    d = np.sum((taylor - truth) ** 2, axis=1) - np.sum((exp(fh, method="ol") - truth) ** 2, axis=1)
    assert d.mean() >= -4.0 * d.std(ddof=1) / np.sqrt(len(d)), (d.mean(), d.std(ddof=1) / np.sqrt(len(d)))


def test_hyb_is_more_accurate_than_ol_on_accumulated_blockers():
    """Sums of 1..20 blocker logs, radii 5..60 degrees, random directions, order 4 (what the papers accumulate):
    HYB's mean squared error below OL's (Ren et al. 2006's finding), paired, by 4 standard errors. The
    figures per blocker count and radius are the generated table ``sh.exp`` of docs/REPRODUCTION.md."""
    rng = np.random.default_rng(20060730 + 1)  # not the training seed
    f = explog._blocker_sums(rng, 600, 4)
    ex = exp(f, method="exact")
    d = _rms_error(exp(f, method="ol"), ex) ** 2 - _rms_error(exp(f, method="hyb"), ex) ** 2
    assert d.mean() > 4.0 * d.std(ddof=1) / np.sqrt(len(d)), (d.mean(), d.std(ddof=1) / np.sqrt(len(d)))


def test_hyb_beats_ol_for_large_blockers(rng):
    """Blockers of 30..60 degrees, where OL's fixed coefficients fit worst (Ren et al. 2006, Sec. 5): HYB's
    squared error below OL's, paired, by 4 standard errors (as the test above, on the large blockers alone)."""
    f = explog._blocker_sums(rng, 800, 4, radius_range_deg=(30.0, 60.0))
    ex = exp(f, method="exact")
    d = _rms_error(exp(f, method="ol"), ex) ** 2 - _rms_error(exp(f, method="hyb"), ex) ** 2
    assert d.mean() > 4.0 * d.std(ddof=1) / np.sqrt(len(d)), (d.mean(), d.std(ddof=1) / np.sqrt(len(d)))


# ----------------------------------------------------------------------------- log


def _positive_band_limited(rng, order):
    """A positive function of exactly ``order`` bands: a square plus a constant, or a dominant DC."""
    if order % 2 == 1:
        h = rng.normal(size=((order + 1) // 2) ** 2)
        f = product_exact(h, h)
        f[0] += rng.uniform(0.05, 1.0) * SQRT4PI
        return f
    f = rng.normal(size=order * order) * 0.3
    dirs, _ = quadrature(1, degree=4 * order + 8)
    low = (f @ basis_reference(dirs, order).T).min()
    f[0] += (abs(low) + rng.uniform(0.1, 1.0)) * SQRT4PI
    return f


@settings(max_examples=20)
@given(order=st.integers(1, 5), seed=st.integers(0, 2**31))
def test_exp_of_log_is_identity(order, seed):
    rng = np.random.default_rng(seed)
    f = np.stack([_positive_band_limited(rng, order) for _ in range(3)])
    g = log(f)
    np.testing.assert_allclose(exp(g, method="exact"), f, atol=1e-11 * np.abs(f).max())


@settings(max_examples=20)
@given(order=st.integers(1, 5), seed=st.integers(0, 2**31))
def test_log_of_exp_is_identity(order, seed):
    rng = np.random.default_rng(seed)
    g = rng.normal(size=(4, order * order)) * rng.uniform(0.01, 1.5)
    np.testing.assert_allclose(log(exp(g, method="exact")), g, atol=1e-9)


def test_log_of_a_blocker_is_the_tabulated_log(rng):
    theta = np.radians([10.0, 30.0, 50.0])
    axes = random_directions(rng, 3)
    full = log(zh_rotate(blocker_zh(theta, 4), axes))
    np.testing.assert_allclose(full, zh_rotate(blocker_log_zh(theta, 4, method="solve"), axes), atol=1e-8)


# ----------------------------------------------------------------------------- layout, empty, errors


@pytest.mark.parametrize("method", ALL_METHODS)
def test_colour_and_empty_batches(method, rng):
    f = rng.normal(size=(2, 9, 3)) * 0.4
    e = exp(f, method=method)
    assert e.shape == (2, 9, 3)
    np.testing.assert_allclose(e[..., 1], exp(f[..., 1], method=method), rtol=1e-14, atol=1e-14)
    assert exp(np.zeros((0, 16)), method=method).shape == (0, 16)
    assert exp(np.zeros((4, 0, 4, 3)), method=method).shape == (4, 0, 4, 3)


def test_log_colour_and_empty(rng):
    f = np.stack([_positive_band_limited(rng, 3) for _ in range(3)], axis=-1)
    g = log(f)
    assert g.shape == (9, 3)
    np.testing.assert_allclose(g[:, 2], log(f[:, 2]), atol=1e-12)
    assert log(np.zeros((0, 9))).shape == (0, 9)


def test_errors():
    with pytest.raises(ValueError, match="method must be one of 'hyb', 'ol', 'exact'"):
        exp(np.zeros(4), method="taylor")
    with pytest.raises(ValueError, match="f contains NaN or inf"):
        exp(np.array([0.0, np.nan, 0.0, 0.0]))
    with pytest.raises(ValueError, match="f contains NaN or inf"):
        log(np.array([1.0, np.inf, 0.0, 0.0]))
    with pytest.raises(ValueError, match=r"f must have shape \(\.\.\., n\*n\)"):
        exp(np.zeros((4, 5, 3)))
    with pytest.raises(ValueError, match="DC coefficient\\) must be > 0"):
        log(np.array([0.0, 0.1, 0.0, 0.0]))
    with pytest.raises(ValueError, match="log did not converge for 1 of 2 vectors"):
        log(np.array([[1.0, 0.0, 0.0, 0.0], [1.0, 10.0, 0.0, 0.0]]), max_iter=30)
    with pytest.raises(ValueError, match="tol must be a positive float"):
        log(np.ones(4), tol=0)
    with pytest.raises(ValueError, match="max_iter must be an int >= 1"):
        log(np.ones(4), max_iter=0)
    with pytest.raises(ValueError, match=r"angular_radius must lie in \[0, pi/2\]"):
        blocker_log_zh(2.0, 4)
    with pytest.raises(ValueError, match=r"angular_radius must lie in \[0, pi/2\]"):
        blocker_zh(-0.1, 4)
    with pytest.raises(ValueError, match="angular_radius contains NaN"):
        blocker_log_zh(np.nan, 4)
    with pytest.raises(TypeError, match="angular_radius must be a real array"):
        blocker_zh("wide", 4)
    with pytest.raises(ValueError, match="method must be one of 'table', 'solve'"):
        blocker_log_zh(0.2, 4, method="lookup")
    with pytest.raises(ValueError, match="order must be an int >= 1"):
        blocker_zh(0.2, 0)


# ----------------------------------------------------------------------------- stored tables


def test_stored_tables_are_current_and_used():
    stored = explog._stored_tables()
    assert stored, "prtlab/sh/_explog_tables.npz is missing or stale: run python -m prtlab.sh._explog"
    assert str(stored["params"]) == explog._table_params()
    r_max, a, b = explog._ol_table(4)
    np.testing.assert_array_equal(a, stored["ol_4"][0])
    assert a[0] == 1.0 and b[0] == 1.0


@pytest.mark.parametrize("orders", [(1, 2), pytest.param((3, 4, 5, 6, 7, 8), marks=pytest.mark.slow)])
def test_regeneration_reproduces_stored_tables(orders):
    stored = explog._stored_tables()
    fresh = explog._generate_tables(orders)
    for key, value in fresh.items():
        if key == "params":
            assert str(value) == str(stored[key])
        else:
            np.testing.assert_allclose(value, stored[key], rtol=1e-8, atol=1e-10, err_msg=key)

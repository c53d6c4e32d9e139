"""Tests of prtlab/wavelet/_approx.py: non-linear (k largest) approximation of Haar-coded cubemaps."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from prtlab.wavelet import coefficient_levels, energy_kept, haar2d, ihaar2d, keep_largest, support_solid_angles

cases = st.tuples(
    st.integers(0, 2**32 - 1),
    st.sampled_from([1, 2, 4, 8, 16]),
    st.sampled_from([(), (2,), (2, 3)]),
)


def random_coeffs(case):
    seed, r, batch = case
    rng = np.random.default_rng(seed)
    # a smooth-plus-spiky cubemap, as lighting is
    x = rng.random(batch + (6, r, r)) ** 8 * 100.0 + 1.0
    return haar2d(x)


# --------------------------------------------------------------------------- known answers


def test_keeps_exactly_the_largest(rng):
    c = haar2d(rng.normal(size=(6, 8, 8)))
    approx, fraction = keep_largest(c, 20)
    kept = approx != 0
    assert kept.sum() == 20
    assert np.abs(c[kept]).min() >= np.abs(c[~kept]).max()
    np.testing.assert_array_equal(approx[kept], c[kept])
    assert fraction == pytest.approx((approx**2).sum() / (c**2).sum(), rel=1e-14)


def test_k_zero_all_and_beyond(rng):
    c = haar2d(rng.normal(size=(2, 6, 4, 4)))
    n = 6 * 16
    approx, fraction = keep_largest(c, 0)
    assert np.all(approx == 0) and np.all(fraction == 0)
    for k in (n, n + 5):
        approx, fraction = keep_largest(c, k)
        np.testing.assert_array_equal(approx, c)
        np.testing.assert_array_equal(fraction, 1.0)
        np.testing.assert_array_equal(energy_kept(c, k), 1.0)


def test_zero_cubemap_keeps_all_its_energy():
    approx, fraction = keep_largest(np.zeros((6, 4, 4)), 3)
    assert fraction == 1.0 and np.all(approx == 0)
    assert energy_kept(np.zeros((6, 4, 4)), [0, 5]).tolist() == [1.0, 1.0]


def test_ties_keep_the_lowest_index():
    c = np.ones((6, 2, 2))
    approx, _ = keep_largest(c, 5)
    expected = np.zeros(24)
    expected[:5] = 1.0
    np.testing.assert_array_equal(approx.ravel(), expected)


def test_error_of_the_approximation_is_the_energy_dropped(rng):
    x = rng.random((6, 16, 16)) ** 4
    c = haar2d(x)
    approx, fraction = keep_largest(c, 50)
    err = ((ihaar2d(approx) - x) ** 2).sum()
    assert err == pytest.approx((1 - fraction) * (x**2).sum(), rel=1e-10)


def test_area_weighted_selection(rng):
    r = 8
    c = haar2d(rng.normal(size=(6, r, r)))
    area = support_solid_angles(r)
    approx, fraction = keep_largest(c, 30, weights=area)
    kept = approx != 0
    key = np.abs(c) * area
    assert kept.sum() == 30
    assert key[kept].min() >= key[~kept].max()
    assert fraction == pytest.approx(energy_kept(c, 30, weights=area), rel=1e-13)
    # with equal magnitudes, area weighting keeps the coarsest supports: the face scaling coefficients
    # and the level-0 wavelets (whole-face support)
    equal, _ = keep_largest(np.ones((6, r, r)), 24, weights=area)
    np.testing.assert_array_equal(equal != 0, np.broadcast_to(coefficient_levels(r) <= 0, (6, r, r)))
    # uniform weights change nothing
    np.testing.assert_array_equal(keep_largest(c, 30, weights=2.0)[0], keep_largest(c, 30)[0])


# --------------------------------------------------------------------------- properties


@given(cases, st.integers(0, 7000))
def test_energy_monotone_in_k_and_exact_at_n(case, k):
    c = random_coeffs(case)
    n = c.shape[-1] ** 2 * 6
    ks = np.arange(n + 1)
    curve = energy_kept(c, ks)
    assert curve.shape == c.shape[:-3] + (n + 1,)
    assert np.all(np.diff(curve, axis=-1) >= -1e-15)
    np.testing.assert_array_equal(curve[..., -1], 1.0)
    np.testing.assert_array_equal(curve[..., 0], 0.0)
    approx, fraction = keep_largest(c, k)
    np.testing.assert_allclose(fraction, curve[..., min(k, n)], rtol=1e-12)
    np.testing.assert_allclose(energy_kept(c, k), fraction, rtol=1e-12)
    assert np.all((approx != 0).sum(axis=(-3, -2, -1)) <= min(k, n))


@given(cases, st.integers(1, 200))
def test_best_k_term_approximation(case, k):
    """No other choice of k coefficients keeps more energy: the kept ones dominate the dropped ones."""
    c = random_coeffs(case).reshape(-1, 6 * case[1] ** 2)
    approx, _ = keep_largest(c.reshape(-1, 6, case[1], case[1]), k)
    approx = approx.reshape(c.shape)
    for row, kept_row in zip(c, approx):
        kept = kept_row != 0
        if kept.any() and (~kept).any():
            assert np.abs(row[kept]).min() >= np.abs(row[~kept]).max()


def test_empty_batches():
    approx, fraction = keep_largest(np.zeros((0, 6, 4, 4)), 3)
    assert approx.shape == (0, 6, 4, 4) and fraction.shape == (0,)
    assert energy_kept(np.zeros((0, 6, 4, 4)), [1, 2]).shape == (0, 2)


# --------------------------------------------------------------------------- errors


def test_errors():
    c = np.zeros((6, 4, 4))
    with pytest.raises(ValueError, match="k must be an int >= 0"):
        keep_largest(c, -1)
    with pytest.raises(TypeError, match="k must be an int"):
        keep_largest(c, 2.5)
    with pytest.raises(ValueError, match="k must be an int >= 0"):
        energy_kept(c, [3, -2])
    with pytest.raises(ValueError, match="weights must be non-negative"):
        keep_largest(c, 2, weights=-np.ones((6, 4, 4)))
    with pytest.raises(ValueError, match="weights must broadcast"):
        keep_largest(c, 2, weights=np.ones((6, 8, 8)))
    with pytest.raises(ValueError, match="weights contains NaN"):
        keep_largest(c, 2, weights=np.full((6, 4, 4), np.nan))
    with pytest.raises(ValueError, match="power of two"):
        keep_largest(np.zeros((6, 3, 3)), 2)

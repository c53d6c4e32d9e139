"""Tests of prtlab/shadowfields/_direct.py: visibility products and the direct pass."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from prtlab import brdf, sh
from prtlab.shadowfields import direct_pass, occluder_order, visibility_pass
from tests.conftest import FLOAT_TOLERANCE

ORDER = 3
N2 = ORDER * ORDER


def test_occluder_order_is_by_distance():
    np.testing.assert_array_equal(occluder_order([0, 0, 0], [[3, 0, 0], [1, 0, 0], [0, 2, 0]]), [1, 2, 0])


def test_visibility_pass_with_unoccluded_factors_is_the_self_visibility(rng):
    own = rng.normal(size=(5, N2))
    one = np.zeros((5, N2))
    one[:, 0] = np.sqrt(4 * np.pi)
    np.testing.assert_allclose(visibility_pass(own, [one, one]), own, atol=1e-12)
    np.testing.assert_allclose(visibility_pass(own, []), own)
    a, b = rng.normal(size=(2, 5, N2))
    np.testing.assert_allclose(visibility_pass(own, [a, b]), sh.product(sh.product(own, a, ORDER), b, ORDER))
    assert visibility_pass(np.zeros((0, N2)), [np.zeros((0, N2))]).shape == (0, N2)


def test_lambert_under_constant_light_unoccluded_is_albedo_times_light():
    sep = brdf.separable(brdf.lambert(np.array([0.2, 0.5, 0.8])), 1, resolution=(8, 16))
    n = np.array([[0.0, 1.0, 0.0], [0.6, 0.0, 0.8]])
    light = np.zeros((N2, 3))
    light[0] = np.sqrt(4 * np.pi) * np.array([1.0, 2.0, 3.0])
    vis = np.zeros((2, N2))
    vis[:, 0] = np.sqrt(4 * np.pi)
    out = direct_pass(light, vis, brdf.project_g_cos(sep, n, ORDER), np.ones((2, 1)), sep.colour)
    np.testing.assert_allclose(out, np.tile([0.2, 1.0, 2.4], (2, 1)), rtol=1e-9)


@given(seed=st.integers(0, 2**31 - 1), per_vertex=st.booleans())
def test_numba_tier_equals_triple_integral(seed, per_vertex):
    rng = np.random.default_rng(seed)
    V, K, C = 4, 2, 3
    light = rng.normal(size=(V, N2, C) if per_vertex else (N2, C))
    args = (light, rng.normal(size=(V, N2)), rng.normal(size=(V, K, N2)), rng.normal(size=(V, K)),
            rng.normal(size=(K, C)))
    np.testing.assert_allclose(direct_pass(*args), direct_pass(*args, method="reference"),
                               atol=FLOAT_TOLERANCE[np.float64] * 100)


def test_empty():
    assert direct_pass(np.zeros((N2, 3)), np.zeros((0, N2)), np.zeros((0, 1, N2)), np.zeros((0, 1)),
                       np.ones((1, 3))).shape == (0, 3)


def test_errors(rng):
    light, vis, g = np.zeros((N2, 3)), np.zeros((2, N2)), np.zeros((2, 1, N2))
    h, col = np.zeros((2, 1)), np.ones((1, 3))
    with pytest.raises(ValueError, match="visibility must be"):
        direct_pass(light, vis[0], g, h, col)
    with pytest.raises(ValueError, match="n\\*n coefficients"):
        direct_pass(light, np.zeros((2, 5)), g, h, col)
    with pytest.raises(ValueError, match="g_cos must be"):
        direct_pass(light, vis, g[:, :, :4], h, col)
    with pytest.raises(ValueError, match="h must be"):
        direct_pass(light, vis, g, h[:1], col)
    with pytest.raises(ValueError, match="colour must be"):
        direct_pass(light, vis, g, h, np.ones((2, 3)))
    with pytest.raises(ValueError, match="light must be"):
        direct_pass(np.zeros((4, 3)), vis, g, h, col)
    with pytest.raises(ValueError, match="light contains NaN"):
        direct_pass(light + np.nan, vis, g, h, col)
    with pytest.raises(ValueError, match="method must be"):
        direct_pass(light, vis, g, h, col, method="gpu")
    with pytest.raises(ValueError, match="self_visibility must be"):
        visibility_pass(np.zeros(N2), [])
    with pytest.raises(ValueError, match=r"occluder_visibility\[0\] must be"):
        visibility_pass(vis, [np.zeros((3, N2))])

"""Tests of prtlab/sh/_product.py (and its kernels): SH products, product matrices, triple integrals."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from prtlab.sh import product, product_exact, product_matrix, quadrature, triple_integral
from prtlab.sh._eval import basis_reference
from tests.conftest import FLOAT_TOLERANCE, random_directions

TOL = FLOAT_TOLERANCE[np.float64]


def _quad(degree):
    """Product rule exact for spherical polynomials of ``degree``."""
    return quadrature(1, degree=degree)
METHODS = ["sparse", "dense"]
orders = st.integers(1, 5)
seeds = st.integers(0, 2**31)


def _random(rng, order, batch=(), channels=None):
    shape = batch + (order * order,) + (() if channels is None else (channels,))
    return rng.normal(size=shape)


def _values(coeffs, dirs):
    """f(w) at dirs: coeffs (..., n*n) -> (..., N)."""
    n = int(round(np.sqrt(coeffs.shape[-1])))
    return coeffs @ basis_reference(dirs, n).T


def _project(values, dirs, weights, order):
    return (values * weights) @ basis_reference(dirs, order)


# ----------------------------------------------------------------------------- known answers


@pytest.mark.parametrize("method", METHODS)
def test_constant_one_is_the_identity(method, rng):
    one = np.zeros(16)
    one[0] = np.sqrt(4 * np.pi)
    f = _random(rng, 4, (3,))
    np.testing.assert_allclose(product(one, f, method=method), f, atol=TOL)
    np.testing.assert_allclose(product_matrix(one, method=method), np.eye(16), atol=TOL)


def test_z_times_z():
    # (c z) (c z) = c^2 z^2 = (1/(4 pi)) * 3 * (1/3 + 2/3 P_2(z)): DC = sqrt(4pi) / (4 pi), l=2 m=0 = 2/sqrt(5 pi) / 2
    z = np.zeros(4)
    z[2] = 1.0  # Y_10
    c = product(z, z, 3)
    expected = np.zeros(9)
    expected[0] = 1.0 / np.sqrt(4 * np.pi)
    expected[6] = 1.0 / np.sqrt(5 * np.pi)
    np.testing.assert_allclose(c, expected, atol=TOL)


# ----------------------------------------------------------------------------- identities (hypothesis, every tier)


@given(na=orders, nb=orders, seed=seeds)
def test_products_commute_and_tiers_agree(na, nb, seed):
    rng = np.random.default_rng(seed)
    a, b = _random(rng, na, (3,)), _random(rng, nb, (3,))
    nc = int(rng.integers(1, 7))
    ref = product(a, b, nc, method="dense")
    assert ref.shape == (3, nc * nc)
    for method in METHODS:
        np.testing.assert_allclose(product(a, b, nc, method=method), ref, atol=TOL)
        np.testing.assert_allclose(product(b, a, nc, method=method), ref, atol=TOL)


@given(na=orders, nb=orders, nc=orders, seed=seeds)
def test_product_is_projection_of_pointwise_product(na, nb, nc, seed):
    rng = np.random.default_rng(seed)
    a, b = _random(rng, na, (2,)), _random(rng, nb, (2,))
    dirs, w = _quad(na + nb + nc - 3)  # exact for Y_i Y_j Y_k
    expected = _project(_values(a, dirs) * _values(b, dirs), dirs, w, nc)
    for method in METHODS:
        np.testing.assert_allclose(product(a, b, nc, method=method), expected, atol=1e-12)


@given(na=orders, nb=orders, seed=seeds)
def test_exact_product_is_exact_pointwise(na, nb, seed):
    rng = np.random.default_rng(seed)
    a, b = _random(rng, na), _random(rng, nb)
    dirs = random_directions(rng, 11)
    for method in METHODS:
        c = product_exact(a, b, method=method)
        assert c.shape == ((na + nb - 1) ** 2,)
        np.testing.assert_allclose(_values(c, dirs), _values(a, dirs) * _values(b, dirs), atol=1e-12)


@given(nf=orders, n=orders, seed=seeds)
def test_product_matrix_applies_the_product(nf, n, seed):
    rng = np.random.default_rng(seed)
    f, g = _random(rng, nf, (4,)), _random(rng, n, (4,))
    for method in METHODS:
        m = product_matrix(f, n, method=method)
        assert m.shape == (4, n * n, n * n)
        np.testing.assert_allclose(m, np.swapaxes(m, -1, -2), atol=TOL)
        np.testing.assert_allclose(np.einsum("tkj,tj->tk", m, g), product(f, g, n, method=method), atol=TOL)


@given(na=orders, nb=orders, nc=orders, seed=seeds)
def test_triple_integral_symmetric_and_equals_quadrature(na, nb, nc, seed):
    rng = np.random.default_rng(seed)
    a, b, c = _random(rng, na, (2,)), _random(rng, nb, (2,)), _random(rng, nc, (2,))
    dirs, w = _quad(na + nb + nc - 3)
    expected = (_values(a, dirs) * _values(b, dirs) * _values(c, dirs)) @ w
    for method in METHODS:
        for x, y, z in [(a, b, c), (b, a, c), (c, b, a), (b, c, a)]:
            np.testing.assert_allclose(triple_integral(x, y, z, method=method), expected, atol=1e-11)


# ----------------------------------------------------------------------------- layout: colour, broadcasting, empty


@pytest.mark.parametrize("method", METHODS)
def test_colour_is_per_channel_and_mixes_with_grey(method, rng):
    a, b = _random(rng, 3, (5,), channels=3), _random(rng, 4, (5,), channels=3)
    grey = _random(rng, 2, (5,))
    c = product(a, b, method=method)
    assert c.shape == (5, 9, 3)
    for ch in range(3):
        np.testing.assert_allclose(c[..., ch], product(a[..., ch], b[..., ch], method=method), atol=TOL)
        np.testing.assert_allclose(product(grey, b, 4, method=method)[..., ch],
                                   product(grey, b[..., ch], 4, method=method), atol=TOL)
    t = triple_integral(a, grey, b, method=method)
    assert t.shape == (5, 3)
    # channels=True for a channel count that is itself a square
    a4, b4 = _random(rng, 2, (), channels=4), _random(rng, 2, (), channels=4)
    c4 = product(a4, b4, method=method, channels=True)
    assert c4.shape == (4, 4)
    np.testing.assert_allclose(c4[:, 1], product(a4[:, 1], b4[:, 1], method=method), atol=TOL)


@pytest.mark.parametrize("method", METHODS)
def test_broadcasting_batches(method, rng):
    a, b = _random(rng, 3, (4, 1)), _random(rng, 3, (5,))
    c = product(a, b, method=method)
    assert c.shape == (4, 5, 9)
    np.testing.assert_allclose(c[2, 3], product(a[2, 0], b[3], method=method), atol=TOL)


@pytest.mark.parametrize("method", METHODS)
def test_empty_batches(method):
    assert product(np.zeros((0, 16)), np.zeros((0, 9)), method=method).shape == (0, 16)
    assert product(np.zeros((2, 0, 4, 3)), np.zeros(4), 3, method=method).shape == (2, 0, 9, 3)
    assert product_exact(np.zeros((0, 4)), np.zeros((0, 4)), method=method).shape == (0, 9)
    assert product_matrix(np.zeros((0, 9)), method=method).shape == (0, 9, 9)
    assert triple_integral(np.zeros((0, 4)), np.zeros(4), np.zeros(1), method=method).shape == (0,)


def test_order_one_is_scalar_multiplication(rng):
    a, b = rng.normal(size=(6, 1)), rng.normal(size=(6, 1))
    np.testing.assert_allclose(product(a, b), a * b / np.sqrt(4 * np.pi), atol=TOL)


def test_integer_input_is_promoted():
    c = product(np.array([2, 0, 0, 0]), np.array([1, 1, 1, 1]))
    assert c.dtype == np.float64


# ----------------------------------------------------------------------------- errors


def test_errors(rng):
    good = _random(rng, 2)
    with pytest.raises(ValueError, match="method must be one of 'sparse', 'dense'"):
        product(good, good, method="fast")
    with pytest.raises(ValueError, match="method must be one of"):
        product_matrix(good, method="einsum")
    with pytest.raises(ValueError, match="method must be one of"):
        triple_integral(good, good, good, method=None)
    bad = good.copy()
    bad[1] = np.nan
    with pytest.raises(ValueError, match="b contains NaN or inf"):
        product(good, bad)
    with pytest.raises(ValueError, match="f contains NaN or inf"):
        product_matrix(bad)
    with pytest.raises(ValueError, match="c contains NaN or inf"):
        triple_integral(good, good, bad)
    with pytest.raises(ValueError, match=r"a must have shape \(\.\.\., n\*n\) or \(\.\.\., n\*n, C\)"):
        product(np.zeros((5, 3)), good)
    with pytest.raises(ValueError, match=r"a must have shape \(\.\.\., n\*n, C\) with n >= 1"):
        product(np.zeros(4), good, channels=True)
    with pytest.raises(ValueError, match=r"f must have shape \(\.\.\., n\*n\)"):
        product_matrix(np.zeros((4, 3)))
    with pytest.raises(TypeError, match="channels must be None, True or False"):
        product(good, good, channels="rgb")
    with pytest.raises(TypeError, match="a must be a real numeric array"):
        product(np.array(["x"] * 4), good)
    with pytest.raises(ValueError, match="order must be an int >= 1"):
        product(good, good, 0)
    with pytest.raises(ValueError, match="do not broadcast"):
        product(np.zeros((3, 4)), np.zeros((2, 4)))
    with pytest.raises(ValueError, match="different channel counts"):
        product(np.zeros((4, 3)), np.zeros((4, 2)))

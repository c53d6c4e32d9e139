"""Tests of prtlab/sh/_eval.py: basis (both tiers), evaluate, index helpers."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.special
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from prtlab.sh import basis, basis_reference, evaluate, index, n_coeffs, quadrature
from tests.conftest import FLOAT_TOLERANCE, random_directions

TOL = FLOAT_TOLERANCE[np.float64]
METHODS = ["numba", "reference"]

direction_arrays = arrays(
    np.float64, st.tuples(st.integers(1, 12), st.just(3)), elements=st.floats(-1.0, 1.0, width=64)
).filter(lambda d: np.all(np.linalg.norm(d, axis=1) > 1e-3))


# --------------------------------------------------------------------------- known answers


@pytest.mark.parametrize("method", METHODS)
def test_table_of_real_harmonics(method, rng):
    d = random_directions(rng, 50)
    x, y, z = d.T
    b = basis(d, 4, method=method)
    pi = math.pi
    expected = {
        0: np.full_like(x, 0.5 / math.sqrt(pi)),
        1: math.sqrt(3 / (4 * pi)) * y,
        2: math.sqrt(3 / (4 * pi)) * z,
        3: math.sqrt(3 / (4 * pi)) * x,
        4: 1.092548430592079 * x * y,  # the design's tabulated value
        5: 1.092548430592079 * y * z,
        6: 0.31539156525252 * (3 * z * z - 1),
        7: 1.092548430592079 * x * z,
        8: 0.546274215296039 * (x * x - y * y),
        9: 0.590043589926644 * y * (3 * x * x - y * y),
        12: 0.373176332590115 * z * (5 * z * z - 3),
        15: 0.590043589926644 * x * (x * x - 3 * y * y),
    }
    for i, val in expected.items():
        np.testing.assert_allclose(b[:, i], val, atol=1e-12)


@pytest.mark.parametrize("method", METHODS)
def test_poles(method):
    order = 12
    poles = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    b = basis(poles, order, method=method)
    for l in range(order):
        for m in range(-l, l + 1):
            expected = math.sqrt((2 * l + 1) / (4 * math.pi)) if m == 0 else 0.0
            assert b[0, index(l, m)] == pytest.approx(expected, abs=TOL)
            assert b[1, index(l, m)] == pytest.approx(expected * (-1) ** l, abs=TOL)


def test_index_and_n_coeffs():
    assert n_coeffs(4) == 16
    assert index(0, 0) == 0 and index(1, -1) == 1 and index(2, 2) == 8
    np.testing.assert_array_equal(index(np.array([3, 3]), np.array([-3, 3])), [9, 15])
    with pytest.raises(ValueError, match="-l <= m <= l"):
        index(1, 2)
    with pytest.raises(TypeError, match="l and m must be integers"):
        index(1.0, 0)


# --------------------------------------------------------------------------- outside references


def _scipy_real_sh(dirs, order):
    """The design's real basis from scipy's complex SH (Condon-Shortley phase removed)."""
    x, y, z = dirs.T
    theta = np.arccos(np.clip(z, -1, 1))
    phi = np.arctan2(y, x)
    out = np.empty((dirs.shape[0], order * order))
    for l in range(order):
        for m in range(0, l + 1):
            ylm = scipy.special.sph_harm_y(l, m, theta, phi)
            if m == 0:
                out[:, l * l + l] = ylm.real
            else:
                out[:, l * l + l + m] = math.sqrt(2) * (-1) ** m * ylm.real
                out[:, l * l + l - m] = math.sqrt(2) * (-1) ** m * ylm.imag
    return out


@pytest.mark.parametrize("method", METHODS)
def test_against_scipy(method, rng):
    d = random_directions(rng, 200)
    np.testing.assert_allclose(basis(d, 20, method=method), _scipy_real_sh(d, 20), atol=1e-11)


def test_against_sphericart(rng):
    sphericart = pytest.importorskip("sphericart")
    d = random_directions(rng, 500)
    # sphericart 2.x: SphericalHarmonics(l_max) is the normalised real SH, same order m = -l..l,
    # same signs (no Condon-Shortley phase): identical to the design's basis.
    ref = sphericart.SphericalHarmonics(15).compute(d)
    np.testing.assert_allclose(basis(d, 16), ref, atol=1e-12)


# --------------------------------------------------------------------------- identities (every tier)


@pytest.mark.parametrize("method", METHODS)
@given(order=st.integers(1, 12))
def test_orthonormality_by_quadrature(method, order):
    dirs, w = quadrature(order)
    y = basis(dirs, order, method=method)
    np.testing.assert_allclose((y * w[:, None]).T @ y, np.eye(order * order), atol=1e-12)


@given(dirs=direction_arrays, order=st.integers(1, 20), scale=st.floats(1e-3, 1e3))
def test_fast_tier_matches_reference(dirs, order, scale):
    np.testing.assert_allclose(basis(scale * dirs, order), basis_reference(dirs, order), atol=TOL)


@pytest.mark.parametrize("method", METHODS)
@given(dirs=direction_arrays)
def test_addition_theorem(method, dirs):
    # sum_m Y_lm(d)^2 = (2l+1) / (4 pi) for every unit d.
    order = 9
    y = basis(dirs, order, method=method)
    for l in range(order):
        np.testing.assert_allclose(
            (y[:, l * l : (l + 1) ** 2] ** 2).sum(axis=1), (2 * l + 1) / (4 * np.pi), rtol=1e-12
        )


# --------------------------------------------------------------------------- degenerate regimes and shapes


@pytest.mark.parametrize("method", METHODS)
def test_shapes_empty_and_order_one(method, rng):
    assert basis(np.zeros((0, 3)), 4, method=method).shape == (0, 16)
    assert basis(np.zeros((2, 0, 3)), 3, method=method).shape == (2, 0, 9)
    d = random_directions(rng, 6).reshape(2, 3, 3)
    assert basis(d, 5, method=method).shape == (2, 3, 25)
    assert basis(d[0, 0], 5, method=method).shape == (25,)
    np.testing.assert_allclose(basis(d, 1, method=method), 0.5 / np.sqrt(np.pi))


@pytest.mark.parametrize("method", METHODS)
def test_basis_errors(method):
    with pytest.raises(TypeError, match="order must be an int"):
        basis(np.zeros((1, 3)) + 1, 2.0, method=method)
    with pytest.raises(TypeError, match="order must be an int"):
        basis(np.zeros((1, 3)) + 1, True, method=method)
    with pytest.raises(ValueError, match="order must be an int >= 1"):
        basis(np.ones((1, 3)), 0, method=method)
    with pytest.raises(ValueError, match=r"dirs must be a \(\.\.\., 3\) array"):
        basis(np.ones((4, 2)), 2, method=method)
    with pytest.raises(ValueError, match="NaN or inf"):
        basis(np.array([[0.0, 0.0, 1.0], [np.nan, 0.0, 1.0]]), 2, method=method)
    with pytest.raises(ValueError, match="NaN or inf"):
        basis(np.array([[np.inf, 0.0, 1.0]]), 5, method=method)
    with pytest.raises(ValueError, match="zero vector"):
        basis(np.array([[0.0, 0.0, 0.0]]), 3, method=method)
    with pytest.raises(TypeError, match=r"dirs must be a real \(\.\.\., 3\) array"):
        basis(np.array([["a", "b", "c"]]), 3, method=method)
    with pytest.raises(ValueError, match="method must be one of"):
        basis(np.ones((1, 3)), 3, method="fast")


def test_evaluate_broadcasting(rng):
    order = 4
    c = rng.normal(size=order * order)
    d = random_directions(rng, 7)
    y = basis_reference(d, order)
    np.testing.assert_allclose(evaluate(c, d), y @ c, atol=TOL)
    # per-vertex coefficients at per-vertex directions
    cv = rng.normal(size=(7, order * order))
    np.testing.assert_allclose(evaluate(cv, d), np.einsum("vi,vi->v", cv, y), atol=TOL)
    # every function at every direction
    assert evaluate(cv[:3, None], d[None]).shape == (3, 7)
    # colour
    cc = rng.normal(size=(order * order, 3))
    np.testing.assert_allclose(evaluate(cc, d), y @ cc, atol=TOL)
    cvc = rng.normal(size=(7, order * order, 3))
    np.testing.assert_allclose(evaluate(cvc, d, method="reference"), np.einsum("vic,vi->vc", cvc, y), atol=TOL)
    # a colour count that is itself a perfect square needs channels=True
    c4 = rng.normal(size=(order * order, 4))
    assert evaluate(c4, d, channels=True).shape == (7, 4)
    assert evaluate(c, np.zeros((0, 3))).shape == (0,)
    assert evaluate(cc, np.zeros((0, 3))).shape == (0, 3)


def test_evaluate_errors(rng):
    d = random_directions(rng, 5)
    with pytest.raises(ValueError, match="not a perfect square|perfect square"):
        evaluate(np.ones(5), d)
    with pytest.raises(ValueError, match="perfect square"):
        evaluate(np.ones((5, 3)), d)
    with pytest.raises(ValueError, match="do not broadcast"):
        evaluate(np.ones((4, 9)), d)
    with pytest.raises(ValueError, match="coeffs contains NaN"):
        evaluate(np.full(9, np.nan), d)
    with pytest.raises(ValueError, match=r"dirs must be a \(\.\.\., 3\)"):
        evaluate(np.ones(9), np.ones((5, 2)))
    with pytest.raises(TypeError, match="coeffs must be a real array"):
        evaluate(np.ones(9, dtype=complex), d)
    with pytest.raises(ValueError, match="got a scalar"):
        evaluate(1.0, d)
    with pytest.raises(ValueError, match="channels=True"):
        evaluate(np.ones(9), d, channels=True)

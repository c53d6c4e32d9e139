"""Tests of prtlab.pca._weights: least-squares weights with the precomputed A^-1 (Iwasaki 2007, Sec. 5.2)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from prtlab.pca import WeightSolver, reconstruct, solve_weights
from tests.conftest import FLOAT_TOLERANCE

TOL = FLOAT_TOLERANCE[np.float64]


def _basis(rng, n=6, nv=40):
    return rng.normal(size=(n, nv))


# --------------------------------------------------------------------------- known answers


def test_exact_for_distributions_in_the_span(rng):
    basis = _basis(rng)
    w = rng.normal(size=(5, 3, 6))
    values = reconstruct(basis, w)
    np.testing.assert_allclose(solve_weights(basis, None, values), w, atol=1e-10)


def test_exact_in_span_with_sample_subset_and_colour(rng):
    basis = _basis(rng, 6, 60)
    samples = np.arange(0, 60, 3)
    w = rng.normal(size=(4, 6, 3))
    values = reconstruct(basis, w)  # (4, 60, 3)
    got = solve_weights(basis, samples, values[:, samples, :])
    np.testing.assert_allclose(got, w, atol=1e-10)


def test_residual_orthogonal_to_basis_and_optimal(rng):
    basis = _basis(rng)
    values = rng.normal(size=40)
    w = solve_weights(basis, None, values)
    residual = values - w @ basis
    np.testing.assert_allclose(basis @ residual, 0.0, atol=1e-10)  # normal equations (Eq. 7)
    best = np.sum(residual**2)
    for _ in range(20):  # any perturbation is worse
        assert np.sum((values - (w + 1e-3 * rng.normal(size=6)) @ basis) ** 2) > best
    np.testing.assert_allclose(w, np.linalg.lstsq(basis.T, values, rcond=None)[0], atol=1e-10)


def test_paper_example():
    assert np.allclose(solve_weights(np.array([[1.0, 1.0, 1.0], [0.0, 1.0, 2.0]]), None, [1.0, 3.0, 5.0]), [1, 2])


def test_conditioning_reported(rng):
    q, _ = np.linalg.qr(rng.normal(size=(40, 5)))
    s = WeightSolver.from_basis(q.T)
    assert s.condition_number == pytest.approx(1.0, abs=1e-10)
    scaled = q.T * np.array([1.0, 1.0, 1.0, 1.0, 1e-3])[:, None]
    assert WeightSolver.from_basis(scaled).condition_number == pytest.approx(1e6, rel=1e-8)
    np.testing.assert_allclose(s.a_matrix @ s.a_inverse, np.eye(5), atol=1e-10)


# --------------------------------------------------------------------------- tiers


@given(
    n=st.integers(1, 8),
    batch=st.sampled_from([(), (3,), (2, 2)]),
    colour=st.sampled_from([None, 1, 3]),
    seed=st.integers(0, 2**31),
)
def test_fast_matches_reference(n, batch, colour, seed):
    rng = np.random.default_rng(seed)
    basis = rng.normal(size=(n, 25))
    shape = batch + (25,) + (() if colour is None else (colour,))
    values = rng.normal(size=shape)
    fast = solve_weights(basis, None, values, method="fast")
    ref = solve_weights(basis, None, values, method="reference")
    assert fast.shape == batch + (n,) + (() if colour is None else (colour,))
    np.testing.assert_allclose(fast, ref, atol=1e-9, rtol=1e-9)


# --------------------------------------------------------------------------- degenerate regimes


def test_empty_batch(rng):
    basis = _basis(rng)
    assert solve_weights(basis, None, np.zeros((0, 40))).shape == (0, 6)
    assert solve_weights(basis, None, np.zeros((0, 40, 3))).shape == (0, 6, 3)
    assert reconstruct(basis, np.zeros((0, 6))).shape == (0, 40)


def test_single_basis_function_is_projection(rng):
    b = rng.normal(size=(1, 10))
    v = rng.normal(size=10)
    np.testing.assert_allclose(solve_weights(b, None, v), [b[0] @ v / (b[0] @ b[0])], rtol=1e-12)


def test_boolean_mask_samples(rng):
    basis = _basis(rng)
    mask = np.zeros(40, bool)
    mask[::2] = True
    v = rng.normal(size=20)
    np.testing.assert_allclose(solve_weights(basis, mask, v), solve_weights(basis, np.arange(0, 40, 2), v))


def test_colour_flag_disambiguates(rng):
    basis = rng.normal(size=(2, 3))
    v = rng.normal(size=(3, 3))
    a = solve_weights(basis, None, v, colour=True)
    b = solve_weights(basis, None, v, colour=False)
    np.testing.assert_allclose(a, solve_weights(basis, None, v.T).T)
    np.testing.assert_allclose(b, solve_weights(basis, None, v))  # inferred: last axis is the point axis
    assert a.shape == (2, 3) and b.shape == (3, 2)


# --------------------------------------------------------------------------- errors


def test_errors(rng):
    basis = _basis(rng)
    with pytest.raises(ValueError, match="NaN"):
        solve_weights(basis, None, np.full(40, np.nan))
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 40\)"):
        solve_weights(basis, None, np.zeros(39))
    with pytest.raises(ValueError, match="method must be one of"):
        solve_weights(basis, None, np.zeros(40), method="qr")
    with pytest.raises(ValueError, match="at least N sample"):
        solve_weights(basis, [0, 1, 2], np.zeros(3))
    with pytest.raises(ValueError, match="singular"):
        solve_weights(np.ones((2, 40)), None, np.zeros(40))
    with pytest.raises(ValueError, match=r"shape \(N, n_vertices\)"):
        solve_weights(np.zeros(4), None, np.zeros(4))
    with pytest.raises(TypeError, match="real"):
        solve_weights(np.array([["a"]]), None, np.zeros(1))
    with pytest.raises(ValueError, match="NaN or inf; refit"):
        solve_weights(np.full((1, 3), np.nan), None, np.zeros(3))
    with pytest.raises(ValueError, match="index vertices"):
        solve_weights(basis, np.arange(35, 45), np.zeros(10))
    with pytest.raises(ValueError, match="repeat"):
        solve_weights(basis, np.array([0, 0, 1, 2, 3, 4, 5]), np.zeros(7))
    with pytest.raises(TypeError, match="integer vertex indices"):
        solve_weights(basis, np.arange(10.0), np.zeros(10))
    with pytest.raises(ValueError, match="1-D"):
        solve_weights(basis, np.zeros((2, 5), int), np.zeros(10))
    with pytest.raises(ValueError, match="as a mask"):
        solve_weights(basis, np.ones(5, bool), np.zeros(5))
    with pytest.raises(TypeError, match="weights must be a real"):
        reconstruct(basis, np.array(["x"] * 6))

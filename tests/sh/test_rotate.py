"""Tests of prtlab/sh/_rotate.py: Ivanic-Ruedenberg blocks (numba) held to exact quadrature (reference)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from prtlab.sh import basis, evaluate, project_function, rotate, rotation_matrices, rotation_matrix
from tests.conftest import FLOAT_TOLERANCE, random_directions, random_rotation

TOL = FLOAT_TOLERANCE[np.float64]
METHODS = ["numba", "reference"]


def axis_angle(axis, angle):
    axis = np.asarray(axis, dtype=float)
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


unit_axes = st.tuples(*[st.floats(-1, 1)] * 3).filter(lambda a: np.linalg.norm(a) > 1e-2)
rotations = st.one_of(
    st.builds(axis_angle, unit_axes, st.floats(-np.pi, np.pi)),
    # near-identity rotations, deliberately
    st.builds(axis_angle, unit_axes, st.sampled_from([1e-9, -1e-9, 1e-6, 1e-12])),
    # rotations about the poles and half turns
    st.builds(axis_angle, st.sampled_from([(0, 0, 1), (0, 0, -1), (1, 0, 0), (0, 1, 0)]),
              st.sampled_from([0.0, np.pi / 2, np.pi, -np.pi / 3, 1e-9])),
)


def rotated_function_coeffs(c, R, order):
    """Reference: project w -> f(R^T w) exactly with product quadrature."""
    return project_function(lambda d: evaluate(c, d @ R, method="reference"), order, method="reference")


# --------------------------------------------------------------------------- known answers


def test_band_one_is_permuted_rotation(rng):
    R = random_rotation(rng)
    perm = [1, 2, 0]  # (y, z, x)
    np.testing.assert_allclose(rotation_matrices(R, 2)[1], R[np.ix_(perm, perm)], atol=1e-15)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("alpha", [0.7, -2.9, np.pi, 1e-9])
def test_rotation_about_the_pole_closed_form(method, alpha):
    # f(R^T w) with R about z by alpha shifts phi by -alpha: per (l, m > 0) pair
    # g_lm = cos(m a) c_lm - sin(m a) c_l-m,  g_l-m = sin(m a) c_lm + cos(m a) c_l-m.
    order = 7
    c = np.random.default_rng(5).normal(size=order * order)
    g = rotate(c, axis_angle((0, 0, 1), alpha), method=method)
    for l in range(order):
        assert g[l * l + l] == pytest.approx(c[l * l + l], abs=TOL)
        for m in range(1, l + 1):
            cp, cm = c[l * l + l + m], c[l * l + l - m]
            assert g[l * l + l + m] == pytest.approx(np.cos(m * alpha) * cp - np.sin(m * alpha) * cm, abs=TOL)
            assert g[l * l + l - m] == pytest.approx(np.sin(m * alpha) * cp + np.cos(m * alpha) * cm, abs=TOL)


def test_lobe_turns_with_R():
    rz = axis_angle((0, 0, 1), np.pi / 2)  # +x -> +y
    c = basis(np.array([1.0, 0.0, 0.0]), 6)
    np.testing.assert_allclose(rotate(c, rz), basis(np.array([0.0, 1.0, 0.0]), 6), atol=1e-13)


@pytest.mark.parametrize("method", METHODS)
def test_identity_and_order_one(method, rng):
    c = rng.normal(size=(3, 25))
    np.testing.assert_allclose(rotate(c, np.eye(3), method=method), c, atol=TOL)
    c1 = rng.normal(size=(5, 1, 3))  # order 1, colour
    np.testing.assert_allclose(rotate(c1, random_rotation(rng), method=method), c1, atol=TOL)
    for blk in rotation_matrices(np.eye(3), 8, method=method):
        np.testing.assert_allclose(blk, np.eye(blk.shape[0]), atol=TOL)


# --------------------------------------------------------------------------- against re-projection


@pytest.mark.parametrize("order", [1, 2, 5, 9])
def test_matches_reprojection(order, rng):
    for _ in range(3):
        R = random_rotation(rng)
        c = rng.normal(size=order * order)
        np.testing.assert_allclose(rotate(c, R), rotated_function_coeffs(c, R, order), atol=1e-12)


def test_evaluation_follows_rotation(rng):
    R = random_rotation(rng)
    c = rng.normal(size=(49, 3))
    w = random_directions(rng, 30)
    np.testing.assert_allclose(evaluate(rotate(c, R), w @ R.T), evaluate(c, w), atol=1e-12)


# --------------------------------------------------------------------------- identities, every tier


@pytest.mark.parametrize("method", METHODS)
@given(a=rotations, b=rotations)
def test_composition(method, a, b):
    order = 6
    for ma, mb, mab in zip(
        rotation_matrices(a, order, method=method),
        rotation_matrices(b, order, method=method),
        rotation_matrices(a @ b, order, method=method),
    ):
        np.testing.assert_allclose(ma @ mb, mab, atol=TOL)


@pytest.mark.parametrize("method", METHODS)
@given(R=rotations, seed=st.integers(0, 2**32 - 1))
def test_band_energy_and_orthogonality(method, R, seed):
    order = 7
    c = np.random.default_rng(seed).normal(size=(4, order * order))
    rc = rotate(c, R, method=method)
    for l in range(order):
        sl = slice(l * l, (l + 1) ** 2)
        np.testing.assert_allclose((rc[:, sl] ** 2).sum(1), (c[:, sl] ** 2).sum(1), rtol=1e-12, atol=1e-12)
    for blk in rotation_matrices(R, order, method=method):
        np.testing.assert_allclose(blk @ blk.T, np.eye(blk.shape[0]), atol=TOL)


@given(R=rotations)
def test_fast_blocks_match_reference(R):
    for fast, ref in zip(rotation_matrices(R, 8), rotation_matrices(R, 8, method="reference")):
        np.testing.assert_allclose(fast, ref, atol=TOL)


def test_near_identity_is_near_identity():
    R = axis_angle((0.3, -0.5, 0.8), 1e-9)
    for blk in rotation_matrices(R, 16):
        err = np.abs(blk - np.eye(blk.shape[0])).max()
        assert err < 16 * 1e-9  # |M_l - I| <= l * angle


def test_high_order_stays_orthogonal(rng):
    R = random_rotation(rng)
    for blk in rotation_matrices(R, 20):
        np.testing.assert_allclose(blk @ blk.T, np.eye(blk.shape[0]), atol=1e-11)


# --------------------------------------------------------------------------- batching and shapes


def test_batched_rotations_and_dense_matrix(rng):
    Rs = np.stack([random_rotation(rng) for _ in range(4)])
    c = rng.normal(size=(4, 16, 3))
    out = rotate(c, Rs)
    for k in range(4):
        np.testing.assert_allclose(out[k], rotation_matrix(Rs[k], 4) @ c[k], atol=TOL)
    # broadcasting one vector against many rotations
    one = rng.normal(size=16)
    np.testing.assert_allclose(rotate(one, Rs), np.einsum("kij,j->ki", rotation_matrix(Rs, 4), one), atol=TOL)
    assert rotation_matrix(Rs, 4).shape == (4, 16, 16)
    assert [b.shape for b in rotation_matrices(Rs, 3)] == [(4, 1, 1), (4, 3, 3), (4, 5, 5)]


def test_large_batch_matches_dense(rng):
    R = random_rotation(rng)
    c = rng.normal(size=(100_000, 16))
    np.testing.assert_allclose(rotate(c, R), c @ rotation_matrix(R, 4).T, atol=TOL)


def test_tiles_with_shared_and_mixed_rotations(rng):
    # The kernel works in tiles of 64 vectors: whole tiles sharing a rotation, and mixed tiles.
    a, b = random_rotation(rng), random_rotation(rng)
    Rs = np.stack([a] * 130 + [b] * 70 + [random_rotation(rng) for _ in range(3)])
    c = rng.normal(size=(Rs.shape[0], 25, 2))
    expected = np.einsum("kij,kjc->kic", rotation_matrix(Rs, 5), c)
    np.testing.assert_allclose(rotate(c, Rs), expected, atol=TOL)


def test_empty_batches(rng):
    R = random_rotation(rng)
    assert rotate(np.zeros((0, 9)), R).shape == (0, 9)
    assert rotate(np.zeros((0, 9, 3)), R).shape == (0, 9, 3)
    assert rotate(np.zeros(9), np.zeros((0, 3, 3))).shape == (0, 9)
    assert rotation_matrix(np.zeros((0, 3, 3)), 3).shape == (0, 9, 9)


def test_errors(rng):
    c = np.ones(9)
    with pytest.raises(ValueError, match="not orthonormal"):
        rotate(c, 1.1 * np.eye(3))
    with pytest.raises(ValueError, match="reflection"):
        rotate(c, np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match="NaN or inf"):
        rotate(c, np.full((3, 3), np.nan))
    with pytest.raises(ValueError, match=r"\(3, 3\) or \(\.\.\., 3, 3\)"):
        rotate(c, np.eye(4))
    with pytest.raises(TypeError, match="R must be a real"):
        rotate(c, np.eye(3, dtype=complex))
    with pytest.raises(ValueError, match="do not broadcast"):
        rotate(np.ones((5, 9)), np.stack([np.eye(3)] * 4))
    with pytest.raises(ValueError, match="perfect square"):
        rotate(np.ones(8), np.eye(3))
    with pytest.raises(ValueError, match="coeffs contains NaN"):
        rotate(np.full(4, np.nan), np.eye(3))
    with pytest.raises(ValueError, match="order must be an int >= 1"):
        rotation_matrices(np.eye(3), 0)
    with pytest.raises(ValueError, match="method must be one of"):
        rotate(c, np.eye(3), method="wigner")
    # within tolerance is accepted
    R = random_rotation(rng) + 1e-8
    rotate(c, R)


def test_kept_blocks_give_the_computed_rotation():
    """A rotation asked for again takes its kept blocks: the same results bit for bit as blocks computed afresh,
    for either method, whatever a caller did to the blocks ``rotation_matrices`` handed out."""
    from prtlab.sh import _rotate

    rng = np.random.default_rng(7)
    R = random_rotation(rng)
    c = rng.normal(size=(5, 25, 3))
    for method in ("numba", "reference"):
        _rotate._KEPT_BLOCKS.clear()
        first = rotate(c, R, method=method)
        assert (R.tobytes(), 5, method) in _rotate._KEPT_BLOCKS
        for block in rotation_matrices(R, 5, method=method):
            block[...] = 0.0  # the caller's copy
        again = rotate(c, R.T.T, method=method)  # the same values, another layout
        other = rotate(c, R.T, method=method)  # another rotation (kept too), then the first's again
        assert np.array_equal(rotate(c, R, method=method), first)
        _rotate._KEPT_BLOCKS.clear()
        assert np.array_equal(again, first) and np.array_equal(rotate(c, R, method=method), first)
        assert np.array_equal(other, rotate(c, R.T, method=method)) and not np.array_equal(other, first)
    with pytest.raises(ValueError):
        rotate(c, 2.0 * R)  # a matrix that is not a rotation is checked, never kept
    assert not any(k[0] == (2.0 * R).tobytes() for k in _rotate._KEPT_BLOCKS)

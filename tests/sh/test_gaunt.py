"""Tests of prtlab/sh/_gaunt.py: the real Gaunt tensor."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from prtlab.sh import gaunt_tensor
from prtlab.sh._eval import basis_reference
from prtlab.sh import quadrature
from prtlab.sh._gaunt import GauntTensor, _band_index, _selection_rules
from tests.conftest import FLOAT_TOLERANCE, random_directions

TOL = FLOAT_TOLERANCE[np.float64]


def _quad(degree):
    """Product rule exact for spherical polynomials of ``degree``."""
    return quadrature(1, degree=degree)

# ----------------------------------------------------------------------------- known answers


def test_dc_row_is_identity_over_sqrt_4pi():
    n2 = 25
    g = gaunt_tensor(5).dense()
    np.testing.assert_allclose(g[0], np.eye(n2) / np.sqrt(4 * np.pi), atol=TOL)


def test_order_two_entries():
    g = gaunt_tensor(2)
    assert g.nnz == 10  # G_000 and the 3 permutations of G_0jj for j = 1, 2, 3
    assert isinstance(g, GauntTensor) and g.order == 2
    assert repr(g) == "GauntTensor(order=2, nnz=10)"


def test_known_value_z_squared():
    # G_{10,10,20} = (3 / (4 pi)) sqrt(5 / (4 pi)) int z^2 (3 z^2 - 1) / 2 dw = 1 / sqrt(5 pi)
    g = gaunt_tensor(3).dense()
    assert g[2, 2, 6] == pytest.approx(1.0 / np.sqrt(5.0 * np.pi), abs=TOL)


# ----------------------------------------------------------------------------- outside reference: sympy


def test_matches_sympy_real_gaunt_order_3():
    # sympy's real harmonics differ from ours by a factor (-1)^m per factor; a non-zero
    # real Gaunt coefficient has m1 + m2 + m3 even (|m| of one is the sum/difference of
    # the others), so the product of the three signs is +1 and the coefficients agree.
    wigner = pytest.importorskip("sympy.physics.wigner")
    order = 3
    l, m = _band_index(order)
    dense = gaunt_tensor(order).dense()
    ref = np.zeros_like(dense)
    for a, b, c in itertools.combinations_with_replacement(range(order * order), 3):
        v = float(wigner.real_gaunt(int(l[a]), int(l[b]), int(l[c]), int(m[a]), int(m[b]), int(m[c])))
        for p in set(itertools.permutations((a, b, c))):
            ref[p] = v
    np.testing.assert_allclose(dense, ref, atol=1e-14)
    assert np.count_nonzero(dense) == np.count_nonzero(ref)


def test_matches_sympy_sampled_order_6(rng):
    wigner = pytest.importorskip("sympy.physics.wigner")
    order = 6
    g = gaunt_tensor(order)
    l, m = _band_index(order)
    dense = g.dense()
    picks = rng.integers(0, g.nnz, size=20)
    for e in picks:
        a, b, c = g.i[e], g.j[e], g.k[e]
        ref = float(wigner.real_gaunt(int(l[a]), int(l[b]), int(l[c]), int(m[a]), int(m[b]), int(m[c])))
        assert dense[a, b, c] == pytest.approx(ref, abs=1e-14)


# ----------------------------------------------------------------------------- structure and selection rules


@pytest.mark.parametrize("order", [1, 2, 4, 8])
def test_selection_rules_and_symmetry(order):
    g = gaunt_tensor(order)
    l, m = _band_index(order)
    li, lj, lk = l[g.i], l[g.j], l[g.k]
    assert np.all((li + lj + lk) % 2 == 0)
    assert np.all((lk <= li + lj) & (lk >= np.abs(li - lj)))
    assert np.all(_selection_rules(li, m[g.i], lj, m[g.j], lk, m[g.k]))
    dense = g.dense()
    for perm in itertools.permutations(range(3)):
        np.testing.assert_array_equal(dense, dense.transpose(perm))
    # sorted by (k, i, j), no duplicates
    key = (g.k * order**4 + g.i * order**2 + g.j)
    assert np.all(np.diff(key) > 0)


def test_zero_count_matches_selection_rules_order_4():
    order = 4
    l, m = _band_index(order)
    a, b, c = np.meshgrid(np.arange(16), np.arange(16), np.arange(16), indexing="ij")
    allowed = _selection_rules(l[a], m[a], l[b], m[b], l[c], m[c])
    dense = gaunt_tensor(order).dense()
    # every allowed entry except accidental 3j zeros is non-zero; none outside the rules
    assert np.count_nonzero(dense[~allowed]) == 0
    assert gaunt_tensor(order).nnz == 353
    assert 0 < allowed.sum() - gaunt_tensor(order).nnz < 40


def test_cached_and_read_only():
    g1, g2 = gaunt_tensor(4), gaunt_tensor(np.int64(4))
    assert g1 is g2
    with pytest.raises(ValueError, match="read-only"):
        g1.value[0] = 1.0


# ----------------------------------------------------------------------------- identities


@given(order=st.integers(1, 5), seed=st.integers(0, 2**31))
def test_contraction_reproduces_pointwise_products(order, seed):
    """sum_k G_ijk Y_k(w) = Y_i(w) Y_j(w) when l_i + l_j < order (the product is band-limited)."""
    rng = np.random.default_rng(seed)
    dirs = random_directions(rng, 7)
    big = 2 * order - 1
    y = basis_reference(dirs, big)
    g = gaunt_tensor(big).dense()[: order * order, : order * order]
    lhs = np.einsum("ijk,nk->nij", g, y)
    rhs = y[:, : order * order, None] * y[:, None, : order * order]
    np.testing.assert_allclose(lhs, rhs, atol=1e-12)


def test_quadrature_is_exact_for_its_degree(rng):
    for degree in (0, 1, 5, 12):
        dirs, w = _quad(degree)
        order = degree // 2 + 1
        y = basis_reference(dirs, order)
        np.testing.assert_allclose((y * w[:, None]).T @ y, np.eye(order * order), atol=1e-13)


# ----------------------------------------------------------------------------- errors


def test_errors():
    with pytest.raises(ValueError, match="order must be an int >= 1"):
        gaunt_tensor(0)
    with pytest.raises(TypeError, match="order must be an int"):
        gaunt_tensor(2.0)

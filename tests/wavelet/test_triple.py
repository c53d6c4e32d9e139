"""Tests of prtlab/wavelet/_triple.py: tripling coefficients against numeric integrals of the basis,
and the quadtree triple products / products against the brute-force (reconstruct, multiply) reference."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from prtlab.geometry._spheremaps import cubemap_solid_angles
from prtlab.wavelet import haar2d, ihaar2d, keep_largest, product, triple_product, tripling_coefficient

METHODS = ["numba", "reference"]

cases = st.tuples(
    st.integers(0, 2**32 - 1),
    st.sampled_from([1, 2, 4, 8, 16, 32]),
    st.sampled_from([(), (1,), (3,)]),
    st.booleans(),  # sparsify the inputs (non-linear approximation) or not
)


def random_triple(case):
    seed, r, batch, sparse = case
    rng = np.random.default_rng(seed)
    x, y, z = rng.normal(size=(3,) + batch + (6, r, r)) * 10.0 ** rng.uniform(-2, 2, size=3)[
        (slice(None),) + (None,) * (len(batch) + 3)
    ]
    a, b, c = haar2d(x), haar2d(y), haar2d(z)
    if sparse:
        k = max(1, 6 * r * r // 5)
        a, b, c = (keep_largest(v, k)[0] for v in (a, b, c))
        x, y, z = ihaar2d(a), ihaar2d(b), ihaar2d(c)
    return x, y, z, a, b, c


def brute_force_integral(x, y, z):
    r = x.shape[-1]
    return (x * y * z).sum(axis=(-3, -2, -1)) / (r * r)


# --------------------------------------------------------------------------- tripling coefficients


def continuous_basis(r):
    """Values on the r x r texels of every continuous orthonormal Haar basis function of the unit square."""
    basis = {}
    for i, j in itertools.product(range(r), range(r)):
        e = np.zeros((6, r, r))
        e[0, i, j] = 1.0
        basis[(i, j)] = ihaar2d(e)[0] * r  # texel-space unit vector -> function with unit L2 norm
    return basis


@pytest.mark.parametrize("r", [1, 2, 4])
def test_tripling_coefficients_are_integrals_of_the_basis(r):
    basis = continuous_basis(r)
    keys = list(basis)
    nonzero = 0
    for i, j, k in itertools.product(keys, keys, keys):
        numeric = (basis[i] * basis[j] * basis[k]).sum() / (r * r)
        rule = tripling_coefficient(i, j, k, r)
        assert rule == pytest.approx(numeric, abs=1e-12), (i, j, k)
        nonzero += rule != 0.0
    if r == 4:
        # rule 1: one triple; rule 2: 3 orderings x (3 level-0 wavelets with the scaling function as
        # third + 12 level-1 wavelets with the scaling function or one of 3 ancestors); rule 3: 6
        # orderings at each of the 5 nodes
        assert nonzero == 1 + 3 * (3 * 1 + 12 * (1 + 3)) + 6 * 5


def test_tripling_known_values():
    r = 8
    assert tripling_coefficient((0, 0), (0, 0), (0, 0), r) == 1.0
    # three distinct types at node (1, 0) of level 2 (h = 4): C = 2**2
    assert tripling_coefficient((1, 4), (5, 0), (5, 4), r) == 4.0
    # the same wavelet twice and the scaling function: 1
    assert tripling_coefficient((3, 6), (3, 6), (0, 0), r) == 1.0
    # the same wavelet twice and an ancestor: its value (+-2**level of the ancestor) on the support
    # [3, 6] is "01" of node (3, 2) at level 2, in quadrant (di, dj) = (1, 0) of node (1, 1) at level 1;
    # there "11" ([3, 3]) is -2 and "01" ([1, 3]) is +2
    assert tripling_coefficient((3, 6), (3, 6), (3, 3), r) == -2.0
    assert tripling_coefficient((3, 6), (3, 6), (1, 3), r) == 2.0
    assert tripling_coefficient((3, 6), (3, 6), (3, 1), r) == -2.0  # "10" of node (1, 1): di = 1
    # a descendant instead of an ancestor: 0
    assert tripling_coefficient((1, 3), (1, 3), (3, 6), r) == 0.0


# --------------------------------------------------------------------------- triple products


@given(cases)
def test_triple_product_tiers_match_brute_force(case):
    x, y, z, a, b, c = random_triple(case)
    expected = brute_force_integral(x, y, z)
    scale = np.sqrt((x * x).sum(axis=(-3, -2, -1)) * ((y * z) ** 2).sum(axis=(-3, -2, -1))) / x.shape[-1] ** 2
    for method in METHODS:
        got = triple_product(a, b, c, method=method)
        assert got.shape == expected.shape
        np.testing.assert_allclose(got, expected, atol=1e-12 * np.max(scale) + 1e-300)


@given(cases)
def test_product_tiers_match_brute_force(case):
    x, y, _, a, b, _ = random_triple(case)
    expected = haar2d(x * y, method="reference")
    tol = 1e-12 * max(1e-300, np.abs(x).max() * np.abs(y).max()) * x.shape[-1]
    for method in METHODS:
        np.testing.assert_allclose(product(a, b, method=method), expected, atol=tol)


@pytest.mark.parametrize("r", [1, 4, 32])
def test_product_then_dot_is_the_triple_product(r, rng):
    a, b, c = haar2d(rng.normal(size=(3, 2, 6, r, r)))
    np.testing.assert_allclose(
        (product(a, b) * c).sum(axis=(-3, -2, -1)) / (r * r), triple_product(a, b, c), rtol=1e-11, atol=1e-13
    )


def test_symmetry_and_identity(rng):
    r = 16
    a, b, c = haar2d(rng.normal(size=(3, 6, r, r)))
    t = triple_product(a, b, c)
    for p in itertools.permutations((a, b, c)):
        assert triple_product(*p) == pytest.approx(t, rel=1e-12, abs=1e-14)
    one = haar2d(np.ones((6, r, r)))
    np.testing.assert_allclose(product(a, one), a, atol=1e-13)
    np.testing.assert_allclose(product(b, a), product(a, b), atol=1e-13)
    # two factors of one: the dot product of coefficients over r**2
    assert triple_product(a, b, one) == pytest.approx((a * b).sum() / r**2, rel=1e-12)
    assert triple_product(one, one, one) == pytest.approx(6.0, rel=1e-14)  # six unit faces


def test_per_face(rng):
    r = 8
    x, y, z = rng.normal(size=(3, 6, r, r))
    a, b, c = haar2d(x), haar2d(y), haar2d(z)
    for method in METHODS:
        per_face = triple_product(a, b, c, method=method, per_face=True)
        assert per_face.shape == (6,)
        np.testing.assert_allclose(per_face, (x * y * z).sum(axis=(-2, -1)) / r**2, atol=1e-13)
        single = triple_product(a[2], b[2], c[2], method=method, per_face=True)
        assert np.ndim(single) == 0 and single == pytest.approx(per_face[2], abs=1e-13)
        np.testing.assert_allclose(product(a[1], b[1], method=method, per_face=True), product(a, b)[1], atol=1e-13)


@pytest.mark.parametrize("method", METHODS)
def test_solid_angle_measure(method, rng):
    r = 16
    light, visibility, brdf = rng.random((3, 2, 6, r, r))
    omega = cubemap_solid_angles(r)
    expected = (light * visibility * brdf * omega).sum(axis=(-3, -2, -1))
    got = triple_product(haar2d(light), haar2d(visibility), haar2d(brdf), method=method, measure="solid_angle")
    np.testing.assert_allclose(got, expected, rtol=1e-12)
    ones = haar2d(np.ones((6, r, r)))
    assert triple_product(ones, ones, ones, method=method, measure="solid_angle") == pytest.approx(4 * np.pi, rel=1e-13)


def test_broadcasting_and_empty_batches(rng):
    r = 4
    a = haar2d(rng.normal(size=(2, 3, 6, r, r)))
    b = haar2d(rng.normal(size=(6, r, r)))
    c = haar2d(rng.normal(size=(3, 6, r, r)))
    for method in METHODS:
        t = triple_product(a, b, c, method=method)
        assert t.shape == (2, 3)
        assert t[1, 2] == pytest.approx(triple_product(a[1, 2], b, c[2]), rel=1e-12)
        assert product(a, b, method=method).shape == (2, 3, 6, r, r)
        empty = np.zeros((0, 6, r, r))
        assert triple_product(empty, b, b, method=method).shape == (0,)
        assert product(empty, b, method=method).shape == (0, 6, r, r)
        assert triple_product(np.zeros((0, r, r)), b[0], b[0], method=method, per_face=True).shape == (0,)


def test_large_resolution_is_linear_not_cubic(rng):
    """r = 128 (98,304 coefficients per cubemap): the dense tripling tensor would have ~1e15 entries."""
    r = 128
    x, y, z = rng.random((3, 6, r, r))
    got = triple_product(haar2d(x), haar2d(y), haar2d(z))
    assert got == pytest.approx(brute_force_integral(x, y, z), rel=1e-11)


# --------------------------------------------------------------------------- errors


def test_errors():
    a = np.zeros((6, 4, 4))
    with pytest.raises(ValueError, match="share one face resolution"):
        triple_product(a, a, np.zeros((6, 8, 8)))
    with pytest.raises(ValueError, match="do not broadcast"):
        triple_product(np.zeros((2, 6, 4, 4)), np.zeros((3, 6, 4, 4)), a)
    with pytest.raises(ValueError, match="measure must be one of"):
        triple_product(a, a, a, measure="sphere")
    with pytest.raises(ValueError, match="needs whole cubemaps"):
        triple_product(a[0], a[0], a[0], measure="solid_angle", per_face=True)
    with pytest.raises(ValueError, match="per_face=True"):
        triple_product(a[0], a[0], a[0])
    with pytest.raises(ValueError, match="power of two"):
        product(np.zeros((6, 3, 3)), np.zeros((6, 3, 3)))
    with pytest.raises(ValueError, match="method must be one of"):
        product(a, a, method="dense")
    for method in METHODS:
        for value in (np.nan, np.inf):
            for position in ((0, 0, 0), (3, 2, 3)):  # a scaling and a finest-level coefficient
                bad = a.copy()
                bad[position] = value
                with pytest.raises(ValueError, match="b contains NaN or inf"):
                    triple_product(a, bad, a, method=method)
                with pytest.raises(ValueError, match="b contains NaN or inf"):
                    product(a, bad, method=method)
    huge = np.full((6, 4, 4), 1e200)
    with pytest.raises(ValueError, match="overflow"):
        triple_product(huge, huge, huge)
    with pytest.raises(ValueError, match="overflow"):
        product(huge, huge)


@pytest.mark.slow
def test_tripling_coefficients_exhaustive_r8():
    """All 64**3 tripling coefficients of an 8 x 8 face: rules against the dense numeric tensor."""
    r = 8
    basis = continuous_basis(r)
    keys = list(basis)
    values = np.stack([basis[k].ravel() for k in keys])  # (N, texels)
    dense = np.einsum("ip,jp,kp->ijk", values, values, values) / (r * r)
    rules = np.array([[[tripling_coefficient(i, j, k, r) for k in keys] for j in keys] for i in keys])
    np.testing.assert_allclose(rules, dense, atol=1e-12)
    # sparsity of the tensor: O(N log N) non-zeros, not O(N^3)
    assert np.count_nonzero(rules) < 64 * 64 * 3

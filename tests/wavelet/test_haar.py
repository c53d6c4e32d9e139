"""Tests of prtlab/wavelet/_haar.py: the non-standard 2D Haar transform (numba tier held to the
numpy reference tier), its layout against PyWavelets, and the solid-angle helpers."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from prtlab.geometry._spheremaps import cubemap_solid_angles
from prtlab.wavelet import coefficient_levels, haar2d, ihaar2d, solid_angle_weight, support_solid_angles
from tests.conftest import FLOAT_TOLERANCE

TOL = FLOAT_TOLERANCE[np.float64]
METHODS = ["numba", "reference"]
RESOLUTIONS = [1, 2, 4, 8, 16, 32]

cubemap_cases = st.tuples(
    st.integers(0, 2**32 - 1),  # seed
    st.sampled_from(RESOLUTIONS),
    st.sampled_from([(), (1,), (3,), (2, 2)]),  # batch shape
)


def random_cubemaps(case):
    seed, r, batch = case
    rng = np.random.default_rng(seed)
    scale = 10.0 ** rng.uniform(-3, 3)
    return scale * rng.normal(size=batch + (6, r, r))


# --------------------------------------------------------------------------- known answers


@pytest.mark.parametrize("method", METHODS)
def test_constant_face_is_one_scaling_coefficient(method):
    r = 8
    x = np.arange(1.0, 7.0)[:, None, None] * np.ones((6, r, r))
    c = haar2d(x, method=method)
    np.testing.assert_allclose(c[:, 0, 0], np.arange(1.0, 7.0) * r, atol=TOL)  # sum / r
    c[:, 0, 0] = 0.0
    np.testing.assert_allclose(c, 0.0, atol=TOL)


@pytest.mark.parametrize("method", METHODS)
def test_two_by_two_block_formulas(method):
    a, b, cc, d = 1.0, 2.0, 5.0, 11.0
    x = np.broadcast_to(np.array([[a, b], [cc, d]]), (6, 2, 2))
    coeffs = haar2d(x, method=method)[0]
    expected = 0.5 * np.array([[a + b + cc + d, a - b + cc - d], [a + b - cc - d, a - b - cc + d]])
    np.testing.assert_allclose(coeffs, expected, atol=TOL)


def test_layout_of_a_single_wavelet():
    """A texel-space basis vector at [p, h + q] is the "01" wavelet of node (p, q) at level log2(h)."""
    r, h, p, q = 8, 2, 1, 0
    e = np.zeros((6, r, r))
    e[3, p, h + q] = 1.0
    texels = ihaar2d(e)[3]
    m = r // h
    expected = np.zeros((r, r))
    block = np.ones((m, m)) / m
    block[:, m // 2 :] *= -1.0  # varies along the column index j: + on the left half
    expected[p * m : (p + 1) * m, q * m : (q + 1) * m] = block
    np.testing.assert_allclose(texels, expected, atol=TOL)


def test_pywavelets_agreement():
    pywt = pytest.importorskip("pywt")
    rng = np.random.default_rng(7)
    for r in [2, 4, 8, 32]:
        x = rng.normal(size=(6, r, r))
        ours = haar2d(x)
        for f in range(6):
            theirs, _ = pywt.coeffs_to_array(pywt.wavedec2(x[f], "haar", mode="periodization"))
            np.testing.assert_allclose(ours[f], theirs, atol=1e-12)
        back = np.stack([pywt.waverec2(pywt.array_to_coeffs(ours[f], pywt.coeffs_to_array(
            pywt.wavedec2(x[f], "haar", mode="periodization"))[1], output_format="wavedec2"),
            "haar", mode="periodization") for f in range(6)])
        np.testing.assert_allclose(back, x, atol=1e-12)


def test_coefficient_levels():
    expected = np.array([[-1, 0, 1, 1], [0, 0, 1, 1], [1, 1, 1, 1], [1, 1, 1, 1]])
    np.testing.assert_array_equal(coefficient_levels(4), expected)
    assert coefficient_levels(1).tolist() == [[-1]]


def test_support_solid_angles():
    r = 8
    area = support_solid_angles(r)
    omega = cubemap_solid_angles(r)
    np.testing.assert_allclose(area[:, 0, 0].sum(), 4 * np.pi, rtol=1e-13)
    levels = coefficient_levels(r)
    for level in range(3):
        # each wavelet type of a level tiles the face once
        h = 2**level
        np.testing.assert_allclose(area[0, :h, h : 2 * h].sum(), omega[0].sum(), rtol=1e-13)
        assert np.all(levels[:h, h : 2 * h] == level)
    # the finest level is the sum of 2x2 texels
    np.testing.assert_allclose(area[0, 4:, :4], omega[0].reshape(4, 2, 4, 2).sum(axis=(1, 3)), rtol=1e-13)


# --------------------------------------------------------------------------- identities (hypothesis)


@given(cubemap_cases)
def test_numba_matches_reference(case):
    x = random_cubemaps(case)
    scale = max(1.0, np.abs(x).max())
    np.testing.assert_allclose(haar2d(x), haar2d(x, method="reference"), atol=1e-13 * scale)
    np.testing.assert_allclose(ihaar2d(x), ihaar2d(x, method="reference"), atol=1e-13 * scale)


@pytest.mark.parametrize("method", METHODS)
@given(case=cubemap_cases)
def test_round_trip(method, case):
    x = random_cubemaps(case)
    scale = max(1.0, np.abs(x).max())
    np.testing.assert_allclose(ihaar2d(haar2d(x, method=method), method=method), x, atol=1e-12 * scale)
    np.testing.assert_allclose(haar2d(ihaar2d(x, method=method), method=method), x, atol=1e-12 * scale)


@pytest.mark.parametrize("method", METHODS)
@given(case=cubemap_cases)
def test_parseval_and_adjointness(method, case):
    x = random_cubemaps(case)
    y = random_cubemaps((case[0] + 1,) + case[1:])
    cx = haar2d(x, method=method)
    axes = (-3, -2, -1)
    np.testing.assert_allclose((cx * cx).sum(axis=axes), (x * x).sum(axis=axes), rtol=1e-12)
    np.testing.assert_allclose(
        (cx * y).sum(axis=axes), (x * ihaar2d(y, method=method)).sum(axis=axes),
        atol=1e-12 * np.sqrt((x * x).sum() * (y * y).sum()),
    )


def test_orthonormal_basis_matrix():
    """The transform of the texel basis is an orthogonal matrix (r = 4, one face)."""
    r = 4
    eye = np.eye(6 * r * r).reshape(-1, 6, r, r)
    for method in METHODS:
        w = haar2d(eye, method=method).reshape(6 * r * r, -1)
        np.testing.assert_allclose(w @ w.T, np.eye(6 * r * r), atol=1e-14)


# --------------------------------------------------------------------------- batches, colour, dtypes


@pytest.mark.parametrize("method", METHODS)
def test_channels_match_per_channel_transform(method, rng):
    x = rng.normal(size=(2, 6, 8, 8, 3))
    c = haar2d(x, method=method, channels=True)
    for ch in range(3):
        np.testing.assert_allclose(c[..., ch], haar2d(x[..., ch]), atol=1e-13)
    np.testing.assert_allclose(ihaar2d(c, method=method, channels=True), x, atol=1e-13)


@pytest.mark.parametrize("method", METHODS)
def test_empty_batches(method):
    assert haar2d(np.zeros((0, 6, 4, 4)), method=method).shape == (0, 6, 4, 4)
    assert ihaar2d(np.zeros((2, 0, 6, 4, 4)), method=method).shape == (2, 0, 6, 4, 4)
    assert haar2d(np.zeros((0, 6, 4, 4, 3)), method=method, channels=True).shape == (0, 6, 4, 4, 3)


def test_integer_input_is_promoted():
    x = np.ones((6, 2, 2), dtype=np.int32)
    c = haar2d(x)
    assert c.dtype == np.float64
    np.testing.assert_allclose(c[:, 0, 0], 2.0)


def test_solid_angle_weight_turns_dot_products_into_integrals(rng):
    r = 16
    light = rng.random((2, 6, r, r))
    visibility = (rng.random((6, r, r)) < 0.5).astype(float)
    omega = cubemap_solid_angles(r)
    integral = (light * visibility * omega).sum(axis=(-3, -2, -1))
    dot = (haar2d(solid_angle_weight(light)) * haar2d(visibility)).sum(axis=(-3, -2, -1))
    np.testing.assert_allclose(dot, integral, rtol=1e-12)
    # int 1 dw = 4 pi
    ones = np.ones((6, r, r))
    np.testing.assert_allclose((haar2d(solid_angle_weight(ones)) * haar2d(ones)).sum(), 4 * np.pi, rtol=1e-13)
    coloured = solid_angle_weight(np.ones((6, r, r, 3)), channels=True)
    np.testing.assert_allclose(coloured[..., 1], omega, rtol=1e-15)


# --------------------------------------------------------------------------- errors


@pytest.mark.parametrize(
    "shape, match",
    [
        ((6, 3, 3), "power of two"),
        ((6, 6, 6), "power of two"),
        ((6, 0, 0), "power of two"),
        ((5, 4, 4), "six faces"),
        ((2, 1, 4, 4), "six faces"),
        ((6, 4, 8), "square"),
        ((4, 4), "shape"),
    ],
)
def test_bad_shapes(shape, match):
    with pytest.raises(ValueError, match=match):
        haar2d(np.zeros(shape))
    with pytest.raises(ValueError, match=match):
        ihaar2d(np.zeros(shape))


def test_bad_channel_shape():
    with pytest.raises(ValueError, match=r"\(\.\.\., 6, r, r, C\) with r a power of two"):
        haar2d(np.zeros((6, 4, 4)), channels=True)
    with pytest.raises(ValueError, match="six faces"):
        haar2d(np.zeros((2, 6, 4, 4)), channels=True)


def test_bad_values_and_types():
    x = np.zeros((6, 4, 4))
    x[2, 1, 3] = np.nan
    with pytest.raises(ValueError, match="NaN or inf"):
        haar2d(x)
    x[2, 1, 3] = np.inf
    with pytest.raises(ValueError, match="NaN or inf"):
        ihaar2d(x)
    for method in METHODS:
        for bad in (np.nan, np.inf, -np.inf):
            y = np.zeros((2, 6, 4, 4))
            y[1, 5, 3, 0] = bad
            with pytest.raises(ValueError, match="NaN or inf"):
                haar2d(y, method=method)
    with pytest.raises(ValueError, match="too large"):
        haar2d(np.full((6, 4, 4), 1e308))
    with pytest.raises(TypeError, match="real array"):
        haar2d(np.zeros((6, 4, 4), dtype=complex))
    with pytest.raises(ValueError, match="method must be one of"):
        haar2d(np.zeros((6, 4, 4)), method="fast")


def test_bad_resolution_arguments():
    with pytest.raises(ValueError, match="power of two"):
        coefficient_levels(12)
    with pytest.raises(ValueError, match="power of two"):
        support_solid_angles(0)
    with pytest.raises(TypeError, match="must be an int"):
        support_solid_angles(4.0)

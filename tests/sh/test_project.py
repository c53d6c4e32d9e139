"""Tests of prtlab/sh/_project.py: product quadrature, projection of samples, functions and sphere images."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from prtlab.geometry import cubemap_directions, equirect_directions
from prtlab.geometry._spheremaps import _face_directions
from prtlab.sh import (
    basis_reference,
    evaluate,
    project,
    project_cubemap,
    project_equirect,
    project_function,
    quadrature,
)
from tests.conftest import random_directions

METHODS = ["numba", "reference"]


# --------------------------------------------------------------------------- quadrature


@given(order=st.integers(1, 14))
def test_quadrature_weights_and_size(order):
    dirs, w = quadrature(order)
    assert dirs.shape == (order * (2 * order - 1), 3) and w.shape == (dirs.shape[0],)
    assert w.sum() == pytest.approx(4 * np.pi, rel=1e-14)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, atol=1e-15)
    assert not dirs.flags.writeable


@given(degree=st.integers(0, 24))
def test_quadrature_exact_to_its_degree(degree):
    # Y_i Y_j with l_i + l_j <= degree is a spherical polynomial of that degree.
    dirs, w = quadrature(1, degree=degree)
    half = degree // 2
    y_lo = basis_reference(dirs, half + 1)
    y_hi = basis_reference(dirs, degree - half + 1)
    gram = (y_lo * w[:, None]).T @ y_hi
    np.testing.assert_allclose(gram, np.eye(*gram.shape), atol=1e-12)


def test_quadrature_errors():
    with pytest.raises(TypeError, match="degree must be an int"):
        quadrature(3, degree=2.5)
    with pytest.raises(ValueError, match="degree must be an int >= 0"):
        quadrature(3, degree=-1)
    with pytest.raises(TypeError, match="order must be an int"):
        quadrature("3")


# --------------------------------------------------------------------------- exactness


@pytest.mark.parametrize("method", METHODS)
@given(order=st.integers(1, 12), seed=st.integers(0, 2**32 - 1))
def test_band_limited_projects_to_itself(method, order, seed):
    c = np.random.default_rng(seed).normal(size=order * order)
    got = project_function(lambda d: evaluate(c, d), order, method=method)
    np.testing.assert_allclose(got, c, atol=1e-12)


def test_colour_and_higher_degree(rng):
    # A function with 10 bands projected to order 4 with a rule exact for degree 9 + 3:
    # exactly the first 16 coefficients.
    c = rng.normal(size=(100, 3))
    got = project_function(lambda d: evaluate(c, d), 4, degree=9 + 3)
    np.testing.assert_allclose(got, c[:16], atol=1e-12)


def test_project_samples(rng):
    d = random_directions(rng, 1000)
    w = rng.uniform(0.0, 1.0, size=1000)
    v = rng.normal(size=(1000, 2))
    y = basis_reference(d, 5)
    np.testing.assert_allclose(project(v, d, w, 5), y.T @ (w[:, None] * v), atol=1e-12)
    np.testing.assert_allclose(project(v[:, 0], d, w, 5, method="reference"), y.T @ (w * v[:, 0]), atol=1e-12)
    assert project(np.zeros(0), np.zeros((0, 3)), np.zeros(0), 3).shape == (9,)
    assert project(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), 3).shape == (9, 3)


def test_project_constant_is_exact():
    # The solid-angle weights of both sphere images sum to 4 pi, so constants project exactly.
    c00 = np.sqrt(4 * np.pi)
    eq = project_equirect(np.ones((33, 64, 3)), 3)
    np.testing.assert_allclose(eq[0], c00, rtol=1e-13)
    cube = project_cubemap(np.ones((6, 8, 8)), 3)
    assert cube[0] == pytest.approx(c00, rel=1e-13)


# --------------------------------------------------------------------------- sphere images: error expansions
#
# Both rules integrate ``g_i = f Y_i`` of a band-limited ``f`` with an error whose first term is known in
# closed form (Euler-Maclaurin); the next term is O(h^4), so the first predicts the error to O(h^2) of
# itself: (pi / 127)^2 = 6e-4 for a 128-row map, (2 / 64)^2 = 1e-3 for 64-texel faces. PREDICTED (1 %)
# leaves room for a constant of 10 in that term (and for the quadratures of the predictions, far finer).

PREDICTED = 0.01


def _f_times_basis(dirs, c, order):
    y = basis_reference(dirs, order)
    return (y @ c)[..., None] * y


def equirect_leading_error(c, order, height, step=1e-3):
    """``(h^2 / 12) int int d^2 g_i / d theta^2 sin(theta) dtheta dphi`` with ``h = pi / (H - 1)``: the first
    error term of the rows' rule (the exact integral of the linear interpolant in ``theta``, weight
    ``sin theta``); the columns' rule is exact for ``|m| < W``. Gauss-Legendre in ``theta``, uniform ``phi``
    (exact: ``g_i`` has degree ``2 (order - 1)`` in ``phi``), central differences for the derivative."""
    x, w = np.polynomial.legendre.leggauss(64)
    theta, wt = 0.5 * np.pi * (x + 1.0), 0.5 * np.pi * w
    m = 4 * order
    phi = 2.0 * np.pi * (np.arange(m) + 0.5) / m

    def g(t):
        tt, pp = np.meshgrid(t, phi, indexing="ij")
        return _f_times_basis(np.stack([np.sin(tt) * np.sin(pp), np.cos(tt), -np.sin(tt) * np.cos(pp)], -1), c,
                              order)

    g2 = (g(theta + step) - 2.0 * g(theta) + g(theta - step)) / step**2
    integral = np.einsum("tpi,t->i", g2, wt * np.sin(theta)) * 2.0 * np.pi / m
    return (np.pi / (height - 1)) ** 2 / 12.0 * integral


def cubemap_leading_error(c, order, res, step=1e-3):
    """``-(D^2 / 12) sum_faces int int (grad g_i . grad J + J lap g_i / 2) ds dt`` with ``D = 2 / res`` the
    texel edge in face coordinates ``s, t in [-1, 1]`` and ``J = (1 + s^2 + t^2)^(-3/2)`` the solid angle
    density: the first error term of the midpoint rule with exact texel weights (expand ``g`` and ``J``
    about the texel centre). Gauss-Legendre on each face, central differences for the derivatives."""
    x, w = np.polynomial.legendre.leggauss(48)
    s, t = np.meshgrid(x, x, indexing="ij")
    weight = w[:, None] * w[None, :]
    r2 = 1.0 + s**2 + t**2
    jac, jac_s, jac_t = r2**-1.5, -3.0 * s * r2**-2.5, -3.0 * t * r2**-2.5
    total = 0.0
    for face in range(6):
        def g(a, b):
            d = _face_directions(face, a, b)
            return _f_times_basis(d / np.linalg.norm(d, axis=-1, keepdims=True), c, order)

        g0, gsp, gsm, gtp, gtm = g(s, t), g(s + step, t), g(s - step, t), g(s, t + step), g(s, t - step)
        grad_dot = (gsp - gsm) / (2 * step) * jac_s[..., None] + (gtp - gtm) / (2 * step) * jac_t[..., None]
        lap = (gsp + gsm + gtp + gtm - 4.0 * g0) / step**2
        total = total + np.einsum("st,sti->i", weight, grad_dot + 0.5 * jac[..., None] * lap)
    return -((2.0 / res) ** 2) / 12.0 * total


def test_equirect_error_is_its_leading_term(rng):
    """The error of projecting an order-8 function sampled on the map is the first term of its expansion
    (within ``PREDICTED`` of it), at 128 x 256 and 256 x 512; halving h quarters it."""
    order = 8
    for _ in range(3):
        c = rng.normal(size=order * order)
        for height in (128, 256):
            err = project_equirect(evaluate(c, equirect_directions(height, 2 * height)), order) - c
            lead = equirect_leading_error(c, order, height)
            assert np.abs(err - lead).max() <= PREDICTED * np.abs(lead).max(), height
        # second order in h: the leading term is h^2 times a function of c alone, so the checks above
        # hold the error ratio to (255 / 127)^2 (1 +- PREDICTED) / (1 -+ PREDICTED)


def test_cubemap_error_is_its_leading_term(rng):
    """As above for cubemaps of 64 and 128 texels per face edge (three colour channels)."""
    order = 8
    for _ in range(3):
        c = rng.normal(size=(order * order, 3))
        for res in (64, 128):
            err = project_cubemap(evaluate(c, cubemap_directions(res)), order) - c
            for ch in range(3):
                lead = cubemap_leading_error(c[:, ch], order, res)
                assert np.abs(err[:, ch] - lead).max() <= PREDICTED * np.abs(lead).max(), (res, ch)
        # second order in h: the leading term is h^2 times a function of c alone, so the checks above
        # hold the error ratio to 4 (1 +- PREDICTED) / (1 -+ PREDICTED)


@given(order=st.integers(1, 12), height=st.integers(2, 40), width=st.integers(1, 70), channels=st.integers(1, 3),
       seed=st.integers(0, 2**32 - 1))
def test_equirect_rows_sum_the_reference_rule(order, height, width, channels, seed):
    """The default tier sums the map row by row (a Fourier series per row); the reference tier pixel by pixel with
    the reference basis. The same rule: they agree within the rounding of a sum of ``H W`` terms, ``(H W + H + W +
    8 n) 2**-53`` times the terms' magnitude bound ``2 n max|Y| sum_ij w_i |L_ij|`` (``max|Y| <= sqrt((2n - 1) / (4
    pi))``)."""
    from prtlab.geometry import equirect_solid_angles

    rng = np.random.default_rng(seed)
    img = rng.normal(size=(height, width, channels)) * rng.uniform(0.1, 10.0)
    got = project_equirect(img, order)
    want = project_equirect(img, order, method="reference")
    weights = equirect_solid_angles(height, width)
    size = 2 * order * np.sqrt((2 * order - 1) / (4 * np.pi)) * np.einsum("hw,hwc->c", weights, np.abs(img))
    bound = (height * width + height + width + 8 * order) * 2.0**-53 * size
    assert np.all(np.abs(got - want) <= bound[None, :]), (np.abs(got - want).max(axis=0), bound)


def test_equirect_orientation(rng):
    # A lobe towards +Y (the map's top row) lands in Y_1,-1 (= c y).
    img = np.clip(equirect_directions(65, 128)[..., 1], 0, None)
    c = project_equirect(img, 2)
    assert c[1] > 0.5 and abs(c[2]) < 1e-3 and abs(c[3]) < 1e-3


# --------------------------------------------------------------------------- errors


def test_errors(rng):
    d = random_directions(rng, 4)
    w = np.ones(4)
    with pytest.raises(ValueError, match=r"values must be \(4,\) or \(4, C\)"):
        project(np.ones(5), d, w, 2)
    with pytest.raises(ValueError, match=r"weights must be \(4,\)"):
        project(np.ones(4), d, np.ones(3), 2)
    with pytest.raises(ValueError, match=r"dirs must be an \(N, 3\) array"):
        project(np.ones(4), d[None], w, 2)
    with pytest.raises(ValueError, match="values contains NaN"):
        project(np.array([1.0, np.nan, 0, 0]), d, w, 2)
    with pytest.raises(ValueError, match="weights contains NaN"):
        project(np.ones(4), d, np.array([1.0, np.inf, 0, 0]), 2)
    with pytest.raises(ValueError, match="dirs contains NaN"):
        project(np.ones(4), np.full((4, 3), np.nan), w, 2)
    with pytest.raises(TypeError, match="values must be a real array"):
        project(np.array(["a"] * 4), d, w, 2)
    with pytest.raises(TypeError, match="weights must be a real array"):
        project(np.ones(4), d, np.array(["a"] * 4), 2)
    with pytest.raises(TypeError, match="f must be a callable"):
        project_function(3.0, 2)
    with pytest.raises(ValueError, match="f must return a real"):
        project_function(lambda d: np.ones(3), 2)
    with pytest.raises(ValueError, match=r"image must be \(H, W\) or \(H, W, C\)"):
        project_equirect(np.ones(5), 2)
    with pytest.raises(ValueError, match="image contains NaN"):
        project_equirect(np.full((4, 8), np.nan), 2)
    with pytest.raises(TypeError, match="image must be a real array"):
        project_equirect(np.full((4, 8), "a"), 2)
    with pytest.raises(ValueError, match=r"faces must be \(6, res, res\)"):
        project_cubemap(np.ones((5, 4, 4)), 2)
    with pytest.raises(ValueError, match="faces contains NaN"):
        project_cubemap(np.full((6, 4, 4), np.nan), 2)

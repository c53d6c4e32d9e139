"""Tests of prtlab/sh/_zh.py: ZH rotation, Funk-Hecke convolution, clamped cosine, irradiance."""

from __future__ import annotations

import math

import numpy as np
import pytest
import sympy
from hypothesis import given
from hypothesis import strategies as st

from prtlab.sh import (
    clamped_cosine_zh,
    convolve,
    evaluate,
    irradiance,
    project_function,
    quadrature,
    rotate,
    zh_project,
    zh_rotate,
)
from tests.conftest import MC_SIGMAS, random_directions, random_rotation

METHODS = ["numba", "reference"]


def zonal_vector(zh):
    n = zh.shape[-1]
    c = np.zeros(zh.shape[:-1] + (n * n,))
    for l in range(n):
        c[..., l * l + l] = zh[..., l]
    return c


# --------------------------------------------------------------------------- ZH rotation


@pytest.mark.parametrize("method", METHODS)
@given(seed=st.integers(0, 2**32 - 1), order=st.integers(1, 10))
def test_zh_rotate_equals_full_rotation(method, seed, order):
    rng = np.random.default_rng(seed)
    zh = rng.normal(size=order)
    R = random_rotation(rng)
    axis = R[:, 2]  # R takes z to this axis
    np.testing.assert_allclose(
        zh_rotate(zh, axis, method=method), rotate(zonal_vector(zh), R, method=method), atol=1e-12
    )


def test_zh_rotate_poles_and_batches(rng):
    zh = rng.normal(size=(4, 5))
    up = np.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(zh_rotate(zh, up), zonal_vector(zh), atol=1e-14)
    down = zh_rotate(zh[0], -up)
    np.testing.assert_allclose(down, zonal_vector(zh[0] * (-1.0) ** np.arange(5)), atol=1e-14)
    axes = random_directions(rng, 4)
    out = zh_rotate(zh, axes)
    for k in range(4):
        np.testing.assert_allclose(out[k], zh_rotate(zh[k], axes[k]), atol=1e-15)
    assert zh_rotate(zh[0], random_directions(rng, 6)).shape == (6, 25)
    assert zh_rotate(zh[0], np.zeros((0, 3))).shape == (0, 25)


def test_zh_rotate_errors():
    with pytest.raises(ValueError, match="do not broadcast"):
        zh_rotate(np.ones((3, 4)), np.ones((2, 3)))
    with pytest.raises(ValueError, match=r"zh must be a \(\.\.\., n\) array"):
        zh_rotate(np.ones((3, 0)), np.ones(3))
    with pytest.raises(ValueError, match="zh contains NaN"):
        zh_rotate(np.array([1.0, np.nan]), np.ones(3))
    with pytest.raises(TypeError, match="zh must be a real"):
        zh_rotate(np.array(["a"]), np.ones(3))
    with pytest.raises(ValueError, match="axes contains NaN"):
        zh_rotate(np.ones(2), np.array([np.nan, 0, 1]))
    with pytest.raises(ValueError, match="axes contains a zero vector"):
        zh_rotate(np.ones(2), np.zeros(3), method="reference")
    with pytest.raises(ValueError, match=r"axes must be a \(\.\.\., 3\) array"):
        zh_rotate(np.ones(2), np.ones(2))


# --------------------------------------------------------------------------- clamped cosine and irradiance


def test_clamped_cosine_closed_form():
    order = 12
    zh = clamped_cosine_zh(order)
    t = sympy.Symbol("t")
    for l in range(order):
        integral = float(sympy.integrate(t * sympy.legendre(l, t), (t, 0, 1)))  # exact rational
        assert zh[l] == pytest.approx(2 * math.pi * math.sqrt((2 * l + 1) / (4 * math.pi)) * integral, abs=1e-13)
    factors = np.sqrt(4 * np.pi / (2 * np.arange(order) + 1)) * zh
    np.testing.assert_allclose(factors[:5], [np.pi, 2 * np.pi / 3, np.pi / 4, 0.0, -np.pi / 24], atol=1e-15)


def test_clamped_cosine_is_a_fresh_array_each_call():
    """The coefficients are made once per order; each call returns its own writeable copy."""
    a = clamped_cosine_zh(5)
    a[0] = 0.0
    b = clamped_cosine_zh(5)
    assert b[0] == pytest.approx(math.sqrt(math.pi) / 2) and b.flags.writeable and b is not a


def test_constant_radiance_gives_pi_L():
    L = np.zeros((9, 3))
    L[0] = np.array([1.0, 2.0, 0.5]) * np.sqrt(4 * np.pi)  # L(w) = (1, 2, 0.5)
    normals = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.3, -0.4, 0.866]])
    np.testing.assert_allclose(evaluate(irradiance(L), normals), np.pi * np.array([[1.0, 2.0, 0.5]] * 4), rtol=1e-14)


def test_irradiance_against_monte_carlo(rng):
    order = 5
    L = rng.normal(size=order * order)
    normals = random_directions(rng, 5)
    exact = evaluate(irradiance(L), normals)
    n_samples = 200_000
    w = random_directions(rng, n_samples)
    radiance = evaluate(L, w)
    for k, n in enumerate(normals):
        samples = 4 * np.pi * radiance * np.clip(w @ n, 0.0, None)
        estimate = samples.mean()
        stderr = samples.std(ddof=1) / np.sqrt(n_samples)
        assert abs(estimate - exact[k]) <= MC_SIGMAS * stderr


# --------------------------------------------------------------------------- convolution and ZH projection


def test_funk_hecke_against_quadrature(rng):
    # h(n) = int K(n . w) f(w) dw for a smooth kernel, by a high-degree product rule.
    order, kappa = 6, 2.0
    kernel = lambda t: np.exp(kappa * (t - 1.0))  # noqa: E731
    k_zh = zh_project(kernel, order + 4)
    f = rng.normal(size=(order * order, 2))
    normals = random_directions(rng, 4)
    dirs, w = quadrature(1, degree=80)
    fw = evaluate(f, dirs)
    direct = np.stack([(w * kernel(dirs @ n)) @ fw for n in normals])
    np.testing.assert_allclose(evaluate(convolve(f, k_zh), normals), direct, atol=1e-10)


def test_zh_project_matches_sphere_projection():
    order = 7
    g = lambda t: 1.0 + t - 2.0 * t**3 + 0.5 * t**6  # noqa: E731
    zh = zh_project(g, order)
    full = project_function(lambda d: g(d[:, 2]), order)
    np.testing.assert_allclose(zonal_vector(zh), full, atol=1e-12)
    two = zh_project(lambda t: np.stack([g(t), 2 * g(t)], axis=-1), order)
    np.testing.assert_allclose(two[:, 1], 2 * zh, atol=1e-13)


def test_convolve_shapes_and_errors(rng):
    c = rng.normal(size=(3, 16, 3))
    k = clamped_cosine_zh(6)  # longer kernels are fine
    out = convolve(c, k)
    assert out.shape == c.shape
    np.testing.assert_allclose(out[:, 1:4], c[:, 1:4] * 2 * np.pi / 3, rtol=1e-14)
    batched = convolve(c[..., 0], np.stack([k, 2 * k, 3 * k]))
    np.testing.assert_allclose(batched[2], 3 * convolve(c[2, :, 0], k), rtol=1e-14)
    with pytest.raises(ValueError, match="zh_kernel has 3 bands but coeffs has order 4"):
        convolve(c, k[:3])
    with pytest.raises(ValueError, match="do not broadcast"):
        convolve(c[..., 0], np.ones((2, 4)))
    with pytest.raises(ValueError, match="zh_kernel contains NaN"):
        convolve(c, np.full(4, np.nan))
    with pytest.raises(ValueError, match="perfect square"):
        irradiance(np.ones(7))
    with pytest.raises(TypeError, match="order must be an int"):
        clamped_cosine_zh(2.0)
    with pytest.raises(TypeError, match="g must be a callable"):
        zh_project(1.0, 3)
    with pytest.raises(ValueError, match="g must return a real"):
        zh_project(lambda t: np.ones(2), 3)
    with pytest.raises(ValueError, match="g returned NaN"):
        zh_project(lambda t: np.full_like(t, np.nan), 3)
    with pytest.raises(ValueError, match="n_nodes must be an int >= 1"):
        zh_project(lambda t: t, 3, n_nodes=0)

"""Tests of prtlab/sh/_project.py: product quadrature, projection of samples, functions and sphere images."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from prtlab.geometry import cubemap_directions, equirect_directions
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


# --------------------------------------------------------------------------- sphere images: measured accuracy


def _equirect_error(c, order, height):
    img = evaluate(c, equirect_directions(height, 2 * height))
    return np.abs(project_equirect(img, order) - c).max() / np.linalg.norm(c)


def _cubemap_error(c, order, res):
    faces = evaluate(c, cubemap_directions(res))
    return np.abs(project_cubemap(faces, order) - c).max() / np.linalg.norm(c)


def test_equirect_accuracy_and_rate(rng):
    order = 8
    for _ in range(3):
        c = rng.normal(size=order * order)
        e128, e256 = _equirect_error(c, order, 128), _equirect_error(c, order, 256)
        assert e256 < 1e-4  # documented in project_equirect
        assert 3.5 < e128 / e256 < 4.5  # second order in 1/H


def test_cubemap_accuracy_and_rate(rng):
    order = 8
    for _ in range(3):
        c = rng.normal(size=(order * order, 3))
        e64, e128 = _cubemap_error(c, order, 64), _cubemap_error(c, order, 128)
        assert e128 < 5e-5  # documented in project_cubemap
        assert 3.5 < e64 / e128 < 4.5  # second order in 1/res


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

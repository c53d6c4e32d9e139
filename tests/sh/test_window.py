"""Tests of prtlab/sh/_window.py: window shapes, dense minimum, non-negative window search."""

from __future__ import annotations

import numpy as np
import pytest

from prtlab.sh import (
    apply_window,
    is_nonnegative,
    min_value,
    nonnegative_window,
    project_function,
    window,
)

Y00 = 0.5 / np.sqrt(np.pi)
C1 = np.sqrt(3 / (4 * np.pi))


def cap_coeffs(order, cos_edge=0.7):
    """A narrow indicator cap about z, projected to `order` bands: it rings negative."""
    return project_function(lambda d: (d[:, 2] > cos_edge).astype(float), order, degree=120)


# --------------------------------------------------------------------------- shapes


def test_window_values():
    l = np.arange(6)
    np.testing.assert_allclose(window(6, "hanning", 4.0), np.where(l < 4, 0.5 * (1 + np.cos(np.pi * l / 4)), 0))
    lanczos = window(6, "lanczos", 5.0)
    np.testing.assert_allclose(lanczos[1], np.sin(np.pi / 5) / (np.pi / 5), rtol=1e-15)
    np.testing.assert_allclose(window(6, "sinc4", 5.0), lanczos**4, rtol=1e-14)
    for kind in ("hanning", "lanczos", "sinc4"):
        f = window(6, kind)  # default width = order: every band kept
        assert f[0] == 1.0 and np.all(f > 0) and np.all(np.diff(f) < 0)
        np.testing.assert_array_equal(window(6, kind, np.inf), np.ones(6))
    assert window(1, "hanning").tolist() == [1.0]


def test_apply_window(rng):
    c = rng.normal(size=(2, 9, 3))
    f = np.array([1.0, 0.5, 0.25])
    out = apply_window(c, f)
    np.testing.assert_array_equal(out[:, 1:4], 0.5 * c[:, 1:4])
    np.testing.assert_array_equal(out[:, 4:], 0.25 * c[:, 4:])
    np.testing.assert_array_equal(apply_window(c[..., 0], f)[:, 0], c[:, 0, 0])


def test_window_errors():
    with pytest.raises(ValueError, match="kind must be one of"):
        window(4, "gauss")
    with pytest.raises(ValueError, match="width must be > 0"):
        window(4, "hanning", 0.0)
    with pytest.raises(ValueError, match="width must be > 0"):
        window(4, "hanning", np.nan)
    with pytest.raises(ValueError, match=r"factors must have shape \(3,\)"):
        apply_window(np.ones(9), np.ones(4))
    with pytest.raises(ValueError, match="factors contains NaN"):
        apply_window(np.ones(9), np.array([1.0, np.nan, 1.0]))
    with pytest.raises(TypeError, match="factors must be a real"):
        apply_window(np.ones(9), np.array(["a", "b", "c"]))


# --------------------------------------------------------------------------- dense minimum


def test_min_value_known_function():
    # f = a Y00 + b Y10 has its minimum a/(2 sqrt pi) - |b| C1 at a pole; the Fibonacci lattice's
    # nearest node has z = +-(1 - 1/N), so the sampled minimum is above the true one by <= |b| C1 / N.
    a, b, n = 5.0, 2.0, 10_000
    c = np.array([a, 0.0, b, 0.0])
    true_min = a * Y00 - abs(b) * C1
    got = min_value(c, n_dirs=n)
    assert true_min <= got <= true_min + abs(b) * C1 / n
    both = min_value(np.stack([c, -c, 2 * c]))
    assert both.shape == (3,) and both[1] < 0 < both[0] < both[2]
    colour = min_value(np.stack([c, 2 * c], axis=-1))
    assert colour.shape == (2,)
    assert is_nonnegative(c) and not is_nonnegative(-c)
    assert is_nonnegative(c - np.array([true_min / Y00 + 1e-3, 0, 0, 0]), tol=1e-2)


def test_min_value_errors():
    with pytest.raises(ValueError, match="n_dirs must be an int >= 1"):
        min_value(np.ones(4), n_dirs=0)
    with pytest.raises(ValueError, match="tol must be >= 0"):
        is_nonnegative(np.ones(4), tol=-1.0)
    with pytest.raises(ValueError, match="coeffs contains NaN"):
        min_value(np.full(4, np.nan))


# --------------------------------------------------------------------------- non-negative window search


@pytest.mark.parametrize("kind", ["sinc4", "hanning", "lanczos"])
def test_nonnegative_window_is_widest(kind):
    order = 8
    c = cap_coeffs(order)
    assert not is_nonnegative(c)  # ringing
    factors, width = nonnegative_window(c, kind=kind, return_width=True)
    np.testing.assert_allclose(factors, window(order, kind, width))
    assert min_value(apply_window(c, factors)) >= 0.0
    assert min_value(apply_window(c, window(order, kind, width * 1.001))) < 0.0
    assert 1.0 <= width < 16 * order


def test_nonnegative_window_trivial_and_errors():
    c = np.zeros(16)
    c[0] = 1.0
    factors, width = nonnegative_window(c, return_width=True)
    assert width == np.inf and np.all(factors == 1.0)
    colour = np.stack([cap_coeffs(6), cap_coeffs(6, 0.5), np.eye(36)[0]], axis=-1)  # (36, 3)
    f = nonnegative_window(colour)
    assert np.all(min_value(apply_window(colour, f)) >= 0.0)
    with pytest.raises(ValueError, match="negative mean"):
        nonnegative_window(-c)
    with pytest.raises(ValueError, match="kind must be one of"):
        nonnegative_window(c, kind="box")

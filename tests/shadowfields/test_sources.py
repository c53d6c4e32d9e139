"""Tests of prtlab/shadowfields/_sources.py: SH of the radiance of an area light."""

from __future__ import annotations

import numpy as np
import pytest

from prtlab.scene import AreaLight
from prtlab.shadowfields import area_light_sh

LIGHT = AreaLight(center=np.array([0.0, 2.0, 0.0]), u=np.array([0.3, 0.0, 0.0]), v=np.array([0.0, 0.0, 0.2]),
                  radiance=np.array([1.0, 2.0, 3.0]))  # cross(u, v) = -y: emits downward


def corner_form_factor(x, y):
    """Differential area to a parallel rectangle with one corner above it (sides x, y in heights)."""
    ax, ay = x / np.sqrt(1 + x * x), y / np.sqrt(1 + y * y)
    return (ax * np.arctan(y / np.sqrt(1 + x * x)) + ay * np.arctan(x / np.sqrt(1 + y * y))) / (2 * np.pi)


def test_known_answers_below_the_centre():
    """c_00 = L Omega / sqrt(4 pi) with the rectangle's solid angle; c_1,-1 = L sqrt(3 / 4 pi) pi F (F the
    form factor of the four corner rectangles): the y moment of the light's directions."""
    h, a, b = 2.0, 0.3, 0.2
    c = area_light_sh(LIGHT, np.zeros(3), 2)
    omega = 4 * np.arcsin(a * b / np.sqrt((a * a + h * h) * (b * b + h * h)))
    np.testing.assert_allclose(c[0], LIGHT.radiance * omega / np.sqrt(4 * np.pi), rtol=1e-8)
    form = 4 * corner_form_factor(a / h, b / h)
    np.testing.assert_allclose(c[1], LIGHT.radiance * np.sqrt(3 / (4 * np.pi)) * np.pi * form, rtol=1e-8)
    np.testing.assert_allclose(c[[2, 3]], 0.0, atol=1e-14)  # symmetric about the y axis


def test_behind_the_light_is_dark_and_tiers_agree(rng):
    np.testing.assert_array_equal(area_light_sh(LIGHT, [[0.0, 3.0, 0.0], [1.0, 2.0, 0.0]], 3), 0.0)
    pts = rng.normal(size=(7, 3))
    np.testing.assert_allclose(area_light_sh(LIGHT, pts, 4), area_light_sh(LIGHT, pts, 4, method="reference"),
                               atol=1e-12)
    assert area_light_sh(LIGHT, np.zeros((0, 3)), 2).shape == (0, 4, 3)
    assert area_light_sh(LIGHT, np.zeros((2, 5, 3)), 2).shape == (2, 5, 4, 3)


def test_errors():
    with pytest.raises(ValueError, match="n_nodes must be"):
        area_light_sh(LIGHT, np.zeros(3), 2, n_nodes=0)
    with pytest.raises(ValueError, match="points must be"):
        area_light_sh(LIGHT, np.zeros(2), 2)
    with pytest.raises(ValueError, match="NaN or inf"):
        area_light_sh(LIGHT, [np.nan, 0, 0], 2)
    with pytest.raises(ValueError, match="method must be"):
        area_light_sh(LIGHT, np.zeros(3), 2, method="gpu")
    with pytest.raises(TypeError, match="order must be an int"):
        area_light_sh(LIGHT, np.zeros(3), 2.0)

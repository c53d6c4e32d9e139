"""Tests of prtlab.spherelights._tables (w_theta and the Voronoi-cell sums)."""

import numpy as np
import pytest

from prtlab import sh
from prtlab.geometry import geodesic_directions
from prtlab.spherelights import average_radiance_weight, voronoi_cell_sums, w_theta_zh


def test_eq17_matches_the_papers_form():
    a = np.linspace(0.01, 1.5, 50)
    for th in (0.1, 0.5, 1.2):
        s = np.sin(th)
        paper = np.maximum(0, np.sin(np.arctan((1 - s * np.cos(a)) / (s * np.sin(a))) - a))
        np.testing.assert_allclose(average_radiance_weight(a, th), paper, atol=1e-12)


def test_w_theta_limits():
    kl = np.sqrt((2 * np.arange(4) + 1) / (4 * np.pi))
    np.testing.assert_allclose(w_theta_zh(0.0, 4), sh.clamped_cosine_zh(4) / np.pi, atol=1e-12)
    np.testing.assert_allclose(w_theta_zh(np.pi / 2, 4), kl, atol=1e-12)
    # a weighted average of a constant is that constant
    np.testing.assert_allclose(w_theta_zh(np.linspace(0, np.pi / 2, 7), 4)[:, 0], kl[0], atol=1e-12)


def test_w_theta_against_independent_midpoint_rule():
    th = 0.7
    alpha = (np.arange(200000) + 0.5) * (np.pi / 200000)
    f = average_radiance_weight(alpha, th) * np.sin(alpha)
    norm = f.sum()
    p = np.polynomial.legendre.legvander(np.cos(alpha), 5)
    ref = np.sqrt((2 * np.arange(6) + 1) / (4 * np.pi)) * (f @ p) / norm
    np.testing.assert_allclose(w_theta_zh(th, 6, method="direct"), ref, atol=1e-6)


def test_w_theta_table_against_direct():
    th = np.linspace(0, np.pi / 2, 101)[1:-1] + 0.003
    err = np.abs(w_theta_zh(th, 4) - w_theta_zh(th, 4, method="direct")).max()
    assert err < 1e-4  # linear interpolation on knots of pi/512: O(h^2) with h = 0.006


def test_voronoi_cell_sums_project_constants_and_cells():
    y = voronoi_cell_sums(4)
    assert y.shape == (92, 16)
    np.testing.assert_allclose(y.sum(axis=0)[0], np.sqrt(4 * np.pi), rtol=1e-12)  # exact DC
    # jittered stratification: the higher bands of the constant vanish up to O(N^-3/4)
    assert np.abs(y.sum(axis=0)[1:]).max() < 5e-3
    # a function that is constant on each Voronoi cell projects to sum_j L_j Y_j: check one cell's
    # solid angle (DC) against the mean cell size 4 pi / 92
    np.testing.assert_allclose(y[:, 0].mean() * np.sqrt(4 * np.pi), 4 * np.pi / 92, rtol=1e-12)


def test_errors():
    with pytest.raises(ValueError, match="theta must be finite"):
        w_theta_zh(2.0, 4)
    with pytest.raises(ValueError, match="method must be 'table' or 'direct'"):
        w_theta_zh(0.1, 4, method="exact")
    with pytest.raises(ValueError, match="order must be a positive int"):
        w_theta_zh(0.1, 0)
    with pytest.raises(ValueError, match="order must be a positive int"):
        voronoi_cell_sums(0)

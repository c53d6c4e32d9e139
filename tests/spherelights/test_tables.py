"""Tests of prtlab.spherelights._tables (w_theta and the Voronoi-cell sums)."""

import numpy as np
import pytest

from prtlab import sh
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
    with pytest.raises(ValueError, match="order must be an int >= 1"):
        w_theta_zh(0.1, 0)
    with pytest.raises(ValueError, match="order must be an int >= 1"):
        voronoi_cell_sums(0)


# --------------------------------------------------------------------------- irradiance kernel (cosine average)

from prtlab.spherelights import emission_times_direction, irradiance_kernel_zh  # noqa: E402


def _sphere_irradiance_brute(l_sh, centre, radius, p, n, n_alpha=400, n_phi=400):
    """``int L(u) max(0, n . w) r^2 cos(gamma) / d^2 du`` over the part of the sphere seen from ``p``, by a product
    Gauss-Legendre (in cos alpha over the visible cap) x midpoint (phi) rule about the axis ``b = (p - c)/D``."""
    order = int(np.sqrt(l_sh.shape[0]))
    d_vec = p - centre
    dist = np.linalg.norm(d_vec)
    b = d_vec / dist
    s = radius / dist
    t, wt = np.polynomial.legendre.leggauss(n_alpha)
    t = s + (1 - s) * 0.5 * (t + 1)
    wt = wt * 0.5 * (1 - s)
    phi = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi
    e1 = np.cross(b, [1.0, 0, 0] if abs(b[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(b, e1)
    st = np.sqrt(1 - t * t)
    u = (t[:, None, None] * b + st[:, None, None] * (np.cos(phi)[None, :, None] * e1 + np.sin(phi)[None, :, None] * e2))
    u = u.reshape(-1, 3)
    w = (wt[:, None] * np.full(n_phi, 2 * np.pi / n_phi)).reshape(-1)
    q = centre + radius * u
    v = q - p
    d = np.linalg.norm(v, axis=1)
    om = v / d[:, None]
    cos_g = np.einsum("ij,ij->i", u, -om)
    f = np.maximum(cos_g, 0) * radius**2 / d**2 * np.maximum(om @ n, 0)
    return (w * f) @ (sh.basis(u, order) @ l_sh)


def test_irradiance_kernel_table_matches_direct():
    from prtlab.spherelights._tables import N_THETA_K, THETA_MAX_K

    knots = np.arange(0, N_THETA_K + 1, 256) * (THETA_MAX_K / N_THETA_K)
    np.testing.assert_allclose(irradiance_kernel_zh(knots, 5), irradiance_kernel_zh(knots, 5, method="direct"),
                               rtol=1e-13, atol=1e-13)
    # between knots: linear interpolation, h^2 |K''| / 8 with h = 1.55 / 4096; the kernel grows like 1/(1 - s)
    th = np.linspace(0.0, np.pi / 2, 41)
    np.testing.assert_allclose(irradiance_kernel_zh(th, 5), irradiance_kernel_zh(th, 5, method="direct"), rtol=2e-4,
                               atol=1e-9)
    # clamped beyond THETA_MAX_K
    np.testing.assert_array_equal(irradiance_kernel_zh(np.pi / 2, 5), irradiance_kernel_zh(THETA_MAX_K, 5))


@pytest.mark.parametrize("theta", [0.05, 0.4, 1.0, 1.45])
def test_irradiance_kernel_of_a_constant_light_is_the_projected_cap(theta):
    """L = 1: E_n = pi s^2 (n . a), the projected solid angle of a cap above the tangent plane."""
    s = np.sin(theta)
    k = irradiance_kernel_zh(theta, 2, method="direct")
    # with L = 1: L . K = sqrt(4 pi) k_0 and (L u) . K = sqrt(4 pi / 3) k_1 b: E = -(n.b) sqrt(4pi) (k_0 - s k_1/sqrt3)
    e = np.sqrt(4 * np.pi) * k[0] - s * np.sqrt(4 * np.pi / 3) * k[1]
    np.testing.assert_allclose(e, np.pi * s * s, rtol=1e-10)


def test_irradiance_kernel_against_brute_force(rng):
    """E_n = s n.(Lu . K) - (n.b) L . K against a product quadrature over the sphere, for a random light."""
    order = 4
    l_sh = rng.normal(size=order * order)
    l_sh[0] = 4.0
    centre, radius = np.array([0.2, 0.9, -0.1]), 0.5
    for p, n in [(np.array([0.9, 0.0, 0.3]), np.array([0.1, 1.0, 0.05])), (np.array([0.0, 0.0, 0.0]), np.array([0, 1.0, 0])),
                 (np.array([2.5, 0.1, 1.0]), np.array([-0.3, 1.0, 0.0]))]:
        n = n / np.linalg.norm(n)
        d = p - centre
        dist = np.linalg.norm(d)
        b = d / dist
        s = radius / dist
        assert n @ -b >= s  # sphere above the tangent plane
        k = sh.zh_rotate(irradiance_kernel_zh(np.arcsin(s), order + 1, method="direct"), b)
        lu = emission_times_direction(l_sh[None, :, None])[0, :, :, 0]
        e = s * n @ (lu @ k) - (n @ b) * (l_sh @ k[: order * order])
        np.testing.assert_allclose(e, _sphere_irradiance_brute(l_sh, centre, radius, p, n), rtol=1e-6)


def test_emission_times_direction_is_the_pointwise_product(rng):
    em = rng.normal(size=(2, 16, 3))
    lu = emission_times_direction(em)
    dirs = random_dirs = rng.normal(size=(50, 3))
    dirs = random_dirs / np.linalg.norm(random_dirs, axis=1, keepdims=True)
    for j in range(3):
        np.testing.assert_allclose(np.einsum("dk,skc->sdc", sh.basis(dirs, 5), lu[:, j]),
                                   np.einsum("dk,skc->sdc", sh.basis(dirs, 4), em) * dirs[None, :, j, None], atol=1e-12)


def test_irradiance_kernel_errors():
    with pytest.raises(ValueError, match="method must be"):
        irradiance_kernel_zh(0.3, 4, method="gpu")
    with pytest.raises(ValueError, match="order must be an int >= 1"):
        irradiance_kernel_zh(0.3, 0)
    with pytest.raises(ValueError, match="theta must be finite"):
        irradiance_kernel_zh(2.0, 4)
